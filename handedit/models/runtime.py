"""Loading an ONNX model against a declared input/output contract, with clear errors.

Why a contract: the pipeline never knows which network a user exported (SAM-like,
ProPainter, Harmonizer, or their own), only what tensors it exchanges. Each plug-in
module declares its ``Contract``; ``load_model`` checks the file exists, opens it with
onnxruntime, and compares names, ranks and dtypes before any frame is processed, so a
wrong file fails at once with a message naming the file and the expected signature.
The file's sha256 goes into the stage's ``method`` string (provenance).

How onnxruntime runs it (``OnnxRuntime``: execution providers, threads) changes the numbers,
so it is part of each model stage's config (its ``onnx`` field), hence of its provenance
key: CPU with one thread by default, the same bytes on every machine; list
``CUDAExecutionProvider`` first to use a GPU where a worker has one.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from handedit.digests import file_sha256
from handedit.setup_meter import metered


class OnnxRuntime(BaseModel):
    """How a stage's ONNX model runs (see module doc)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    providers: tuple[str, ...] = Field(("CPUExecutionProvider",), description="onnxruntime execution providers, in order of "
                                       "preference; those a worker lacks are skipped (CPU is the last resort)")
    threads: int = Field(1, ge=1, description="intra-op threads (more threads can change the numbers)")


class ModelContractError(ValueError):
    """The model file is missing, unreadable, or its signature does not match the contract."""


@dataclass(frozen=True)
class TensorSpec:
    name: str
    rank: int
    dtype: str = "tensor(float)"
    doc: str = ""  # shape and meaning, shown in error messages

    def describe(self) -> str:
        return f"{self.name}: {self.dtype} rank {self.rank} {self.doc}".rstrip()


@dataclass(frozen=True)
class Contract:
    kind: str  # "segmenter", "video inpainter", "harmonizer"
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]
    optional_inputs: tuple[TensorSpec, ...] = ()

    def signature(self) -> str:
        ins = "; ".join(t.describe() for t in self.inputs)
        opt = "; ".join(t.describe() for t in self.optional_inputs)
        outs = "; ".join(t.describe() for t in self.outputs)
        return f"inputs [{ins}]" + (f" optional [{opt}]" if opt else "") + f" -> outputs [{outs}]"


@dataclass
class LoadedModel:
    path: Path
    sha256: str
    session: object  # onnxruntime.InferenceSession
    contract: Contract
    input_shapes: dict[str, list]  # declared shapes (ints, or str/None for dynamic axes)
    input_names: frozenset[str]

    @property
    def tag(self) -> str:
        """Provenance string: file name and content hash."""
        return f"{self.path.name}@sha256:{self.sha256[:16]}"

    def fixed_hw(self, name: str) -> tuple[int, int] | None:
        """(H, W) when the model declares fixed spatial sizes for input ``name``."""
        shape = self.input_shapes.get(name) or []
        if len(shape) >= 2 and all(isinstance(d, int) and d > 0 for d in shape[-2:]):
            return int(shape[-2]), int(shape[-1])
        return None

    def work_hw(self, name: str, height: int, width: int, max_side: int) -> tuple[int, int]:
        """The (H, W) to feed input ``name``: the model's fixed size if it declares one, else
        the image scaled down (never up) so its longer side is at most ``max_side``."""
        fixed = self.fixed_hw(name)
        if fixed is not None:
            return fixed
        s = min(1.0, max_side / max(height, width))
        return max(1, int(round(height * s))), max(1, int(round(width * s)))

    def fixed_dim(self, name: str, axis: int) -> int | None:
        shape = self.input_shapes.get(name) or []
        d = shape[axis] if len(shape) > abs(axis) else None
        return int(d) if isinstance(d, int) and d > 0 else None

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        feeds = {k: v for k, v in feeds.items() if k in self.input_names}
        names = [t.name for t in self.contract.outputs]
        try:
            outs = self.session.run(names, feeds)
        except Exception as exc:  # onnxruntime raises its own types (shape / type errors)
            raise ModelContractError(
                f"{self.contract.kind} model {self.path} failed at run time ({exc.__class__.__name__}: {exc}); "
                f"expected signature: {self.contract.signature()}"
            ) from exc
        return dict(zip(names, outs))


def _providers(wanted: tuple[str, ...]) -> list[str]:
    import onnxruntime as ort

    avail = ort.get_available_providers()
    return [p for p in wanted if p in avail] or ["CPUExecutionProvider"]


def _mismatch(kind: str, spec, got, required: bool) -> str | None:
    """What is wrong with one tensor of a model against its contract entry, if anything."""
    if got is None:
        return f"missing {kind} '{spec.name}'" if required else None
    if len(got.shape) != spec.rank or got.type != spec.dtype:
        return f"{kind} '{spec.name}' is {got.type} rank {len(got.shape)}, expected {spec.dtype} rank {spec.rank}"
    return None


def load_model(path: str | os.PathLike, contract: Contract, runtime: OnnxRuntime | None = None) -> LoadedModel:
    """Open ``path`` and check it against ``contract`` (cached per file content, runtime and process)."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise ModelContractError(
            f"{contract.kind} model file not found: {p}. Point the stage's model_path at an ONNX file "
            f"exported to the contract: {contract.signature()}"
        )
    st = p.stat()
    return _load_cached(str(p.resolve()), st.st_mtime_ns, st.st_size, contract, runtime or OnnxRuntime())


@lru_cache(maxsize=8)
@metered
def _load_cached(path: str, mtime_ns: int, size: int, contract: Contract, runtime: OnnxRuntime) -> LoadedModel:
    import onnxruntime as ort

    p = Path(path)
    try:
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = runtime.threads
        opts.log_severity_level = 3
        sess = ort.InferenceSession(str(p), sess_options=opts, providers=_providers(runtime.providers))
    except Exception as exc:
        raise ModelContractError(f"{contract.kind} model {p} could not be loaded by onnxruntime ({exc}); "
                                 f"expected an ONNX file with {contract.signature()}") from exc
    got_in = {i.name: i for i in sess.get_inputs()}
    got_out = {o.name: o for o in sess.get_outputs()}
    checks = [("input", t, got_in.get(t.name), True) for t in contract.inputs]
    checks += [("input", t, got_in.get(t.name), False) for t in contract.optional_inputs]
    checks += [("output", t, got_out.get(t.name), True) for t in contract.outputs]
    problems = [msg for msg in (_mismatch(*c) for c in checks) if msg]
    known = {t.name for t in (*contract.inputs, *contract.optional_inputs)}
    extra = sorted(set(got_in) - known)
    if extra:
        problems.append(f"unexpected inputs {extra}")
    if problems:
        have = ", ".join(f"{i.name}:{i.type}{list(i.shape)}" for i in sess.get_inputs())
        raise ModelContractError(
            f"{contract.kind} model {p} does not match the contract: {'; '.join(problems)}. "
            f"It has inputs [{have}]; expected {contract.signature()}"
        )
    shapes = {n: list(i.shape) for n, i in got_in.items()}
    return LoadedModel(p, file_sha256(p), sess, contract, shapes, frozenset(got_in))
