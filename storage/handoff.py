"""Hand-over: the chunks a walk writes, kept in memory for the walk's own later readers.

Why: one task walks a clip's stages chunk by chunk (``handedit.tasks.clip``), so what
render writes for chunk k, composite reads back moments later, and harmonize then reads
composite's image. Decoding bytes that were just encoded is a large part of the stages
after rendering (a 640x480 RGBA, depth and label frame: ~2 ms per frame to read back). So
while a walk runs (``handing_over``), ``write_chunk`` keeps each array it wrote if a node
still to come in the same walk reads that chunk (the DAG's deps say which), and
``read_chunk`` serves a range that kept chunks cover from memory. An entry is dropped
once its last reader has run (``done``), and nothing is kept beyond ``budget_bytes``.

What is served equals what is stored: the codecs are lossless and an entry is the very
array that was written (made read-only); readers get a copy, because stages write into
what they read (composite into the background, harmonize into the composite). Only the
walk's own writes are kept, so a chunk stored by an earlier run is always read from the
store, where a damaged object is still found (``CorruptChunk``).
"""

from __future__ import annotations

import contextlib
import contextvars
from collections import Counter
from collections.abc import Iterable, Iterator, Mapping

import numpy as np

_ACTIVE: contextvars.ContextVar["Handoff | None"] = contextvars.ContextVar("handedit_handoff", default=None)


class Handoff:
    """Kept chunks of one walk on one store; ``readers``: (unit path, chunk start frame) ->
    how many nodes still to run read that chunk (and which of its arrays)."""

    def __init__(self, store: object, readers: Mapping[tuple[str, int], int], names: Mapping[tuple[str, int], set[str]],
                 budget_bytes: int):
        self.store, self.budget = store, int(budget_bytes)
        self.readers: Counter = Counter(readers)
        self.names = {k: set(v) for k, v in names.items()}
        self.kept: dict[str, dict[int, tuple[int, dict[str, np.ndarray]]]] = {}  # path -> start -> (stop, arrays)
        self.nbytes = 0
        self.served = 0  # arrays served from memory (bench and tests read it)

    def keep(self, store: object, path: str, start: int, arrays: Mapping[str, np.ndarray]) -> None:
        key = (path, start)
        if store is not self.store or self.readers[key] <= 0:
            return
        wanted = {n: a for n, a in arrays.items() if n in self.names.get(key, ())}
        size = sum(a.nbytes for a in wanted.values())
        if not wanted or self.nbytes + size > self.budget:
            return
        stop = start + len(next(iter(wanted.values())))
        frozen = {}
        for n, a in wanted.items():
            view = a.view()
            view.flags.writeable = False
            frozen[n] = view
        old = self.kept.setdefault(path, {}).pop(start, None)
        if old is not None:
            self.nbytes -= sum(a.nbytes for a in old[1].values())
        self.kept[path][start] = (stop, frozen)
        self.nbytes += size

    def get(self, store: object, path: str, name: str, start: int, stop: int) -> np.ndarray | None:
        """A copy of frames [start, stop) of ``name``, when kept chunks cover them all."""
        if store is not self.store or path not in self.kept or stop <= start:
            return None
        pieces, at = [], start
        for s in sorted(self.kept[path]):
            e, arrays = self.kept[path][s]
            if e <= at or s >= stop:
                continue
            if s > at or name not in arrays:
                return None  # a gap, or this array was not kept
            pieces.append(arrays[name][at - s:min(stop, e) - s])
            at = min(stop, e)
            if at == stop:
                break
        if at != stop:
            return None
        self.served += 1
        return pieces[0].copy() if len(pieces) == 1 else np.concatenate(pieces)

    def done(self, read: Iterable[tuple[str, int]]) -> None:
        """A node ran (or was skipped): its reads no longer hold their chunks."""
        for key in read:
            self.readers[key] -= 1
            if self.readers[key] <= 0:
                entry = self.kept.get(key[0], {}).pop(key[1], None)
                if entry is not None:
                    self.nbytes -= sum(a.nbytes for a in entry[1].values())


@contextlib.contextmanager
def handing_over(handoff: Handoff | None) -> Iterator[Handoff | None]:
    """Make ``handoff`` the current one for ``read_chunk``/``write_chunk`` in this context."""
    token = _ACTIVE.set(handoff)
    try:
        yield handoff
    finally:
        _ACTIVE.reset(token)


def current() -> Handoff | None:
    return _ACTIVE.get()
