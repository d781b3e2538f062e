"""What every stage shares: the job of one chunk, the retry policy, the record it leaves.

A stage body handles one chunk of frames (never one frame), reading only its declared
inputs (``tasks.stage``); ``execute`` writes the chunk's arrays, and the walk
(``tasks.clip``) writes the chunk's provenance record right after them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Callable

import numpy as np
import zarr

from handedit import setup_meter
from handedit.reasons import Reason
from handedit.secrets import redact
from handedit.storage import ChunkRecord, Unit, write_chunk
from handedit.storage.store import now_iso, store_full
from handedit.tasks.plan import ClipPlan

# Failures worth another attempt: I/O hiccups, lost connections, resource pressure.
TRANSIENT = (OSError, TimeoutError, ConnectionError, MemoryError)
RETRIES = 2
RETRY_DELAYS = [1.0, 5.0]


class TransientError(RuntimeError):
    """Raise to ask for a retry explicitly."""


class InjectedFault(RuntimeError):
    """Raised where ``CurateConfig.inject_faults`` asks for it (drills and tests)."""


def is_transient(exc: BaseException) -> bool:
    return isinstance(exc, (TransientError, *TRANSIENT)) and not isinstance(exc, (FileNotFoundError, PermissionError)) \
        and store_full(exc) is None


def retry_transient(task, task_run, state) -> bool:
    """Prefect retry condition: retry I/O-like failures, not deterministic data errors."""
    exc = state.data if isinstance(state.data, BaseException) else None
    return exc is not None and is_transient(exc)


@dataclass(frozen=True)
class ChunkJob:
    """Everything a task needs, small and picklable: no pixels travel with it."""

    store: str
    unit: Unit
    chunk: int
    start: int
    stop: int
    key: str
    version: int
    params: dict
    inputs: dict[str, str]
    code_version: str
    plan: ClipPlan
    track: str | None = None  # the mask the unit works with: its restore scope or its robot's track
    fault: bool = False

    @property
    def n(self) -> int:
        return self.stop - self.start


@dataclass
class StageOutput:
    """What a stage body hands back: arrays for its chunk, per-frame status, details.

    Per-hand stages also return ``hand_status`` (n,S); their rejections are then recorded
    per hand (the ledger's ``side``), and the frame-level status (derived from the hands)
    adds no rows of its own.
    """

    arrays: dict[str, np.ndarray]
    status: np.ndarray
    method: str = ""
    details: dict[int, str] = field(default_factory=dict)  # chunk-relative frame -> text
    extra: dict = field(default_factory=dict)
    hand_status: np.ndarray | None = None  # (n,S)
    hand_details: dict[tuple[int, int], str] = field(default_factory=dict)  # (frame, hand index) -> text


@lru_cache(maxsize=8)
def open_root(store: str) -> zarr.Group:
    """One store handle per worker process (reads are safe to share); ``store`` is the
    store's path or URL (``Location.store_url``)."""
    from handedit.storage.location import Location

    return zarr.open_group(Location(store).zarr_store(), mode="r+")


def attempt_number() -> int:
    try:
        from prefect.runtime import task_run

        return int(task_run.run_count or 1)
    except Exception:  # outside a Prefect run (bench, bare loop)
        return 1


def seed_from(key: str) -> None:
    """Same inputs, same bytes: OpenCV's global RNG (GrabCut's initialisation) seeded from
    the chunk's provenance key, so a chunk computes the same output in any process."""
    import cv2

    cv2.setRNGSeed(int(key[:8], 16) % (2**31 - 1) if key and all(c in "0123456789abcdef" for c in key[:8]) else 0)


def execute(job: ChunkJob, body: Callable[..., StageOutput], inputs) -> dict:
    """Run a stage body on one chunk (``inputs``: its ``tasks.stage.Inputs``), write its
    outputs, return its provenance record."""
    started, t0 = now_iso(), time.perf_counter()
    if job.fault:
        raise InjectedFault(f"fault injected into {job.unit.label} chunk {job.chunk}")
    seed_from(job.key)
    setup_meter.take()  # what this thread built before this chunk is not its setup
    root = open_root(job.store)
    from distributed.metrics import context_meter

    # the Dask dashboard's fine performance metrics: time per stage (label) within the
    # task's span (curate/clip or curate/<embodiment>); a no-op outside a Dask worker
    with context_meter.meter(job.unit.stage):
        out = body(inputs, job)
        status = np.asarray(out.status, dtype=np.int16)
        arrays = {**out.arrays, "status": status}
        if out.hand_status is not None:
            arrays["hand_status"] = np.asarray(out.hand_status, dtype=np.int16)
        digests = write_chunk(root, job.unit, job.start, arrays)
    return make_record(job, status, digests, out.method, out.details, out.extra, started, time.perf_counter() - t0,
                       hand_status=out.hand_status, hand_details=out.hand_details, setup_seconds=setup_meter.take())


def make_record(
    job: ChunkJob,
    status: np.ndarray,
    digests: dict[str, str],
    method: str,
    details: dict[int, str],
    extra: dict,
    started: str,
    seconds: float,
    outcome: str = "ok",
    error: str | None = None,
    hand_status: np.ndarray | None = None,
    hand_details: dict[tuple[int, int], str] | None = None,
    setup_seconds: float = 0.0,
) -> dict:
    codes, counts = np.unique(status, return_counts=True)

    error = redact(error)  # exception texts can carry URLs with tokens, echoed headers

    def text(code: int, given: str | None) -> str:
        return redact(given) or error or Reason(code).name.lower().replace("_", " ")

    if hand_status is None:
        rejections = [{"frame": job.start + int(i), "reason": int(status[i]), "detail": text(int(status[i]), details.get(int(i)))}
                      for i in np.flatnonzero(status >= 100)]
    else:
        hs = np.asarray(hand_status)
        sides = list(job.plan.hands)
        hand_details = hand_details or {}
        rejections = [{"frame": job.start + int(i), "side": sides[k] if k < len(sides) else str(k), "reason": int(hs[i, k]),
                       "detail": text(int(hs[i, k]), hand_details.get((int(i), int(k))) or details.get(int(i)))}
                      for i, k in zip(*np.nonzero(hs >= 100))]
    return ChunkRecord(
        stage=job.unit.stage,
        chunk=job.chunk,
        start=job.start,
        stop=job.stop,
        key=job.key,
        version=job.version,
        params=job.params,
        inputs=job.inputs,
        outputs=digests,
        method=method,
        outcome=outcome,
        error=error,
        rejections=rejections,
        counts={str(int(c)): int(n) for c, n in zip(codes, counts)},
        code_version=job.code_version,
        attempts=attempt_number(),
        started=started,
        seconds=round(seconds, 4),
        setup_seconds=round(setup_seconds, 4),
        extra=extra,
    ).to_json()


def failure_record(job: ChunkJob, root: zarr.Group, reason: Reason, error: str, attempts: int) -> dict:
    """A chunk whose body failed for good (or that cannot run): its frames get ``reason``.
    Written by the walk that owns the chunk's unit, its only writer."""
    status = np.full(job.n, int(reason), dtype=np.int16)
    arrays = {"status": status}
    group = root[job.unit.path]
    if "hand_status" in group:
        arrays["hand_status"] = np.full((job.n, group["hand_status"].shape[1]), int(reason), np.int16)
    digests = write_chunk(root, job.unit, job.start, arrays)
    record = make_record(job, status, digests, "", {}, {}, now_iso(), 0.0, outcome="error", error=error)
    record["attempts"] = attempts
    return record
