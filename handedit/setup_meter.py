"""Setup time, metered per thread: what a task spent building the per-process machinery that
every later task on its worker reuses (a robot's renderer, an arm's IK solvers, a hand
retargeter, a parsed URDF).

Why: a worker builds each embodiment's machinery once and keeps it for every clip it curates,
so at dataset scale the cost is spread over hundreds of thousands of frames, while a bench
window of 32 frames pays it in full (a robot's renderer costs 0.8-1.6 s to build, its warm
frames 20-40 ms). Each chunk's provenance record keeps its share (``setup_seconds``), so
``bench/egodex.py --roster`` can project the per-frame cost without it and report it apart.
"""

from __future__ import annotations

import functools
import threading
import time
from contextlib import contextmanager
from typing import Callable, Iterator, TypeVar

_local = threading.local()
F = TypeVar("F", bound=Callable)


@contextmanager
def building() -> Iterator[None]:
    """Count this block as setup (a block inside another one counts once, in the outermost)."""
    depth = getattr(_local, "depth", 0)
    _local.depth = depth + 1
    t0 = time.perf_counter()
    try:
        yield
    finally:
        _local.depth = depth
        if depth == 0:
            _local.seconds = getattr(_local, "seconds", 0.0) + time.perf_counter() - t0


def metered(fn: F) -> F:
    """``fn``'s calls count as setup. Put it under ``functools.lru_cache``, so that only a
    cache miss (a build) is timed."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with building():
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


def take() -> float:
    """This thread's setup seconds since its last ``take``; the count starts again from 0."""
    seconds = getattr(_local, "seconds", 0.0)
    _local.seconds = 0.0
    return seconds
