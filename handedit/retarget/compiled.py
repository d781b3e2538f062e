"""casadi functions compiled to machine code once per machine, cached by their generated source.

Why: casadi's SX virtual machine interprets the expression graph. The hand fit's cost,
gradient and exact Hessian (Allegro: 22 variables) take 44 us per evaluation interpreted and
3.3 us compiled by the system C compiler at -O1 (the same values), and projected Newton
evaluates them ~5 times per frame: interpreted, that was a third of a frame's solve.

The C source casadi generates is hashed; ``$HANDEDIT_CACHE_DIR/casadi/<name>-<hash>.so`` is
built once (``$CC``, else ``cc``; ~2 s for the hand's Hessian) and loaded by every later
process; workers compiling the same function at once each rename a whole file into place.
A compiled function is checked against the interpreted one at a few points before use.
Without a compiler, when compiling or loading fails, or with ``HANDEDIT_CASADI_COMPILE=0``,
the interpreted function is used (the same results, slower) and ``Compiled.how`` says why.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shlex
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from handedit.cache import cache_root

log = logging.getLogger(__name__)
FLAGS = ("-O1", "-fPIC", "-shared")
COMPILE_TIMEOUT_S = 300


@dataclass(frozen=True)
class Compiled:
    fn: ca.Function  # the compiled function, or the interpreted one it stands for
    how: str  # "compiled <path>" or "interpreted: <why>"


def compiled(fn: ca.Function) -> Compiled:
    """``fn`` as machine code where this machine can build it (module doc)."""
    if os.environ.get("HANDEDIT_CASADI_COMPILE", "1") == "0":
        return Compiled(fn, "interpreted: HANDEDIT_CASADI_COMPILE=0")
    cc = os.environ.get("CC") or "cc"
    cg = ca.CodeGenerator(f"{fn.name()}.c", {"with_header": False})
    cg.add(fn)
    src = cg.dump()
    key = hashlib.sha256("\0".join([src, ca.__version__, cc, *FLAGS]).encode()).hexdigest()[:20]
    path = cache_root() / "casadi" / f"{fn.name()}-{key}.so"
    try:
        ext = _load(fn, path) if path.is_file() else None
    except (RuntimeError, ValueError):  # a broken or foreign file under that name: built again
        ext = None
    try:
        if ext is None:
            _build(src, path, cc)
            ext = _load(fn, path)
    except (OSError, subprocess.SubprocessError, RuntimeError, ValueError) as exc:
        why = f"interpreted: compiling {fn.name()} with {cc!r} failed ({type(exc).__name__}: {str(exc)[:200]})"
        log.warning("%s; the interpreted function gives the same results, slower", why)
        return Compiled(fn, why)
    return Compiled(ext, f"compiled {path}")


def _build(src: str, path: Path, cc: str) -> None:
    """Compile ``src`` into ``path``, whole or not at all (a temporary file beside it, renamed)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=".build-") as tmp:
        c, so = Path(tmp) / "fn.c", Path(tmp) / "fn.so"
        c.write_text(src)
        out = subprocess.run([*shlex.split(cc), *FLAGS, str(c), "-o", str(so)], capture_output=True, text=True,
                             timeout=COMPILE_TIMEOUT_S)
        if out.returncode != 0:
            raise subprocess.SubprocessError(out.stderr.strip()[-500:] or f"exit status {out.returncode}")
        os.chmod(so, 0o755)
        os.replace(so, path)


def _load(fn: ca.Function, path: Path) -> ca.Function:
    ext = ca.external(fn.name(), str(path))
    _check(fn, ext)
    return ext


def _check(fn: ca.Function, ext: ca.Function, points: int = 3) -> None:
    """Both functions agree at a few seeded points (a stale or foreign file fails here)."""
    if ext.n_in() != fn.n_in() or ext.n_out() != fn.n_out():
        raise ValueError(f"{ext.name()}: {ext.n_in()} inputs / {ext.n_out()} outputs, expected {fn.n_in()} / {fn.n_out()}")
    rng = np.random.default_rng(0)
    for _ in range(points):
        args = [rng.uniform(-1, 1, fn.sparsity_in(i).shape) for i in range(fn.n_in())]
        for a, b in zip(*(f.call(args) for f in (fn, ext))):  # call: a list of outputs, however many
            a, b = np.asarray(a, float), np.asarray(b, float)
            if not np.allclose(a, b, rtol=1e-9, atol=1e-12, equal_nan=True):
                raise ValueError(f"{ext.name()}: the compiled values differ from the interpreted ones by {np.nanmax(np.abs(a - b)):.3g}")
