"""Hand-over: the chunks a walk writes, kept in memory for the walk's own later readers.

Why: one task walks a clip's stages chunk by chunk (``handedit.tasks.clip``), so what
render writes for chunk k, composite reads back moments later, and harmonize then reads
composite's image. Decoding bytes that were just encoded is a large part of the stages
after rendering (a 640x480 RGBA, depth and label frame: ~2 ms per frame to read back). So
while a walk runs (``handing_over``), ``write_chunk`` keeps each array it wrote if a node
still to come in the same walk reads that chunk (the DAG's deps say which), and
``read_chunk`` serves a range that kept chunks cover from memory. An entry is dropped
once its last reader has run (``done``), and nothing is kept beyond ``budget_bytes``.

The other tasks' chunks a walk reads (an embodiment task reads its clip's background,
frames, masks and statuses, as every other embodiment task of the clip does) are decoded
once per worker process and then reused (``Reused``), keyed by their content: the digest
their provenance record holds, so a recomputed chunk is a new key. A worker runs a clip's
embodiment tasks one after another, each reading the clip's chunks in order, so the clip
whose task is running keeps what it holds and never evicts its own chunks (least recently
used would keep none of a clip longer than the budget): other clips' chunks go first.

What is served equals what is stored: the codecs are lossless, and an entry is the very
array that was written or decoded, made read-only and served as it is (a copy would cost
what decoding does: most of a read is the first touch of fresh memory); a stage that
writes into what it read (composite into the background, harmonize into the composite)
allocates instead when that is shared (``storage.writable``). A walk's own units are
read from the store unless this walk wrote them, so a damaged object of a chunk stored
earlier is still found (``CorruptChunk``); another task's chunk is decoded from the store
the first time a worker reads it.
"""

from __future__ import annotations

import contextlib
import contextvars
import threading
from collections import Counter, OrderedDict
from collections.abc import Iterable, Iterator, Mapping

import numpy as np

_ACTIVE: contextvars.ContextVar["Handoff | None"] = contextvars.ContextVar("handedit_handoff", default=None)


class Reused:
    """Decoded chunks of other tasks' units, per worker process, by content (see module doc);
    shared by the process's task threads, hence the lock."""

    def __init__(self):
        self.entries: OrderedDict[tuple, tuple[str, np.ndarray]] = OrderedDict()  # key -> (clip, array), oldest first
        self.nbytes = 0
        self._lock = threading.Lock()

    def get(self, key: tuple) -> np.ndarray | None:
        entry = self.entries.get(key)
        return None if entry is None else entry[1]

    def put(self, key: tuple, clip: str, array: np.ndarray, budget: int) -> None:
        """Keep ``array`` (not copied: the caller hands it over) within ``budget`` bytes,
        evicting other clips' entries, oldest first, to make room; never this clip's own."""
        with self._lock:
            if key in self.entries or array.nbytes > budget:
                return
            for old in [k for k, (c, _) in self.entries.items() if c != clip]:
                if self.nbytes + array.nbytes <= budget:
                    break
                self.nbytes -= self.entries.pop(old)[1].nbytes
            if self.nbytes + array.nbytes > budget:
                return
            array.flags.writeable = False
            self.entries[key] = (clip, array)
            self.nbytes += array.nbytes

    def clear(self) -> None:
        with self._lock:
            self.entries.clear()
            self.nbytes = 0


REUSED = Reused()  # the worker process's


class Handoff:
    """Kept chunks of one walk on one store; ``readers``: (unit path, chunk start frame) ->
    how many nodes still to run read that chunk; ``names``: the same -> {array: how many of
    them read it} (the last reader of an array takes it over, writable); ``digests``:
    (unit path, start, stop) -> {array: digest} of the other tasks' chunks the walk reads
    (from their provenance records), reused across walks within ``reuse_bytes``."""

    def __init__(self, store: object, readers: Mapping[tuple[str, int], int], names: Mapping[tuple[str, int], Iterable[str]],
                 budget_bytes: int, digests: Mapping[tuple[str, int, int], Mapping[str, str]] | None = None,
                 reuse_bytes: int = 0):
        self.store, self.budget = store, int(budget_bytes)
        self.readers: Counter = Counter(readers)
        self.names = {k: Counter(v) for k, v in names.items()}
        self.kept: dict[str, dict[int, tuple[int, dict[str, np.ndarray]]]] = {}  # path -> start -> (stop, arrays)
        self.written: dict[tuple[str, int, str], np.ndarray] = {}  # the writer's own arrays behind the read-only views
        self.nbytes = 0
        self.served = 0  # arrays served from memory (bench and tests read it)
        self.digests = {k: dict(v) for k, v in (digests or {}).items()}
        self.store_key, self.reuse_budget = str(store), int(reuse_bytes)

    def keep(self, store: object, path: str, start: int, arrays: Mapping[str, np.ndarray]) -> None:
        key = (path, start)
        if store is not self.store or self.readers[key] <= 0:
            return
        self._drop(path, start)  # a chunk written again replaces what was kept of it
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
            self.written[(path, start, n)] = a
        self.kept.setdefault(path, {})[start] = (stop, frozen)
        self.nbytes += size

    def _reuse_key(self, path: str, name: str, start: int, stop: int) -> tuple | None:
        digest = self.digests.get((path, start, stop), {}).get(name)
        return None if digest is None or self.reuse_budget <= 0 else (self.store_key, path, name, start, stop, digest)

    def decoded(self, store: object, path: str, clip: str, name: str, start: int, stop: int, value: np.ndarray) -> np.ndarray:
        """``value`` was just read from the store: kept for reuse when it is another task's
        chunk (and then read-only); returned."""
        key = self._reuse_key(path, name, start, stop) if store is self.store else None
        if key is not None:
            REUSED.put(key, clip, value, self.reuse_budget)  # read-only from now on, when kept
        return value

    def get(self, store: object, path: str, name: str, start: int, stop: int) -> np.ndarray | None:
        """Frames [start, stop) of ``name`` (read-only), when kept chunks cover them all (or,
        another task's chunk, when this worker decoded it already)."""
        if store is not self.store or stop <= start:
            return None
        key = self._reuse_key(path, name, start, stop)
        if key is not None:
            reused = REUSED.get(key)
            if reused is not None:
                self.served += 1
                return reused
        if path not in self.kept:
            return None
        pieces, at = [], start
        for s in sorted(self.kept[path]):
            e, arrays = self.kept[path][s]
            if e <= at or s >= stop:
                continue
            if s > at or name not in arrays:
                return None  # a gap, or this array was not kept
            if (s, e) == (start, stop) and self.names[(path, s)][name] == 1:  # its last reader: take it over
                self.nbytes -= arrays.pop(name).nbytes
                self.served += 1
                return self.written.pop((path, s, name))
            pieces.append(arrays[name][at - s:min(stop, e) - s])
            at = min(stop, e)
            if at == stop:
                break
        if at != stop:
            return None
        self.served += 1
        if len(pieces) == 1:
            return pieces[0]
        joined = np.concatenate(pieces)
        joined.flags.writeable = False
        return joined

    def done(self, read: Iterable[tuple[str, int, Iterable[str]]]) -> None:
        """A node ran (or was skipped): its reads (unit path, start, arrays) no longer hold
        their chunks."""
        for path, start, names in read:
            key = (path, start)
            self.readers[key] -= 1
            self.names.get(key, Counter()).subtract(names)
            if self.readers[key] <= 0:
                self._drop(path, start)

    def _drop(self, path: str, start: int) -> None:
        entry = self.kept.get(path, {}).pop(start, None)
        if entry is not None:
            self.nbytes -= sum(a.nbytes for a in entry[1].values())
            for n in entry[1]:
                self.written.pop((path, start, n), None)


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
