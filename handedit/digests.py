"""Content hashes of files: one implementation for sources, models, assets and releases."""

from __future__ import annotations

import hashlib
from functools import lru_cache
from pathlib import Path

_BLOCK = 1 << 20


def file_sha256(path: str | Path) -> str:
    """sha256 of a file's bytes, cached per process by (path, size, mtime): a file rewritten
    in place is hashed again, an unchanged one once."""
    st = Path(path).stat()
    return _sha256(str(path), st.st_size, st.st_mtime_ns)


@lru_cache(maxsize=256)
def _sha256(path: str, size: int, mtime_ns: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(_BLOCK):
            h.update(block)
    return h.hexdigest()


def file_digest(path: str | Path) -> str:
    """``file_sha256``, or "missing" for a file that is not there (a plan still keys on it;
    the stage that needs the file reports it)."""
    try:
        return file_sha256(path)
    except OSError:
        return "missing"


def model_digests(stage_config) -> dict[str, str]:
    """Content of every model file a stage's config runs, by input name: ``model`` for its
    ``model_path`` (the ONNX plug-ins), plus what the config's own ``model_digests()`` names
    (files it finds itself, e.g. estimate_hands' hand models). New weights at the same path
    change these, so the stage, and only what reads it, runs again."""
    out = {}
    path = getattr(stage_config, "model_path", None)
    if path:
        out["model"] = file_digest(path)
    own = getattr(stage_config, "model_digests", None)
    if callable(own):
        out.update(own())
    return out
