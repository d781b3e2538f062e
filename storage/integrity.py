"""Integrity: does the data a provenance record vouches for exist, and is it intact?

A chunk record names the arrays it wrote and their content digests. Two checks use that:

- presence (cheap, metadata only): every storage object (a Zarr chunk or shard file)
  covering the record's frames exists. One recursive listing per clip answers it for all
  of the clip's units, locally or on object storage. ``curate`` runs it before skipping a
  chunk, and for every complete shard before skipping the shard; ``release`` and ``bench
  build`` run it before publishing.
- content (``--deep``): the stored frames re-hash to the recorded digest, which also
  catches garbage bytes (a decode or checksum error is reported the same way).

``repair`` drops the records of every problem chunk and marks their shards incomplete,
so the next ``curate`` recomputes exactly those chunks; what depends on them is then
recomputed only if the recomputed data differs (the inputs are content digests).

Every array is written with ``write_empty_chunks`` on (``handedit.storage.store``), so a
chunk that was written always has its object, even when it holds only the fill value.
"""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import dataclass

import numpy as np
import zarr

from handedit.storage.layout import Unit, clip_path
from handedit.storage.provenance import ChunkRecord, read_records


@dataclass(frozen=True)
class Problem:
    """One chunk whose data does not back its record."""

    unit: Unit
    chunk: int
    array: str  # path inside the store, e.g. clips/c/embodiments/allegro/harmonize/image
    start: int
    stop: int
    kind: str  # missing | mismatch | unreadable | damaged metadata
    detail: str = ""

    def describe(self) -> str:
        if self.chunk < 0:
            return f"{self.array}/zarr.json: {self.kind} ({self.detail})"
        return f"{self.array} frames {self.start}-{self.stop - 1} (chunk {self.chunk}): {self.kind}" + (
            f" ({self.detail})" if self.detail else "")

    def to_json(self) -> dict:
        return {"unit": self.unit.label, "clip": self.unit.clip, "stage": self.unit.stage, "chunk": self.chunk,
                "array": self.array, "frames": [self.start, self.stop], "kind": self.kind, "detail": self.detail}


def object_keys(array: zarr.Array, start: int, stop: int) -> list[str]:
    """Store keys of the objects (chunk files, or shard files) holding frames [start, stop)."""
    grid = array.shards or array.chunks
    first = range(start // grid[0], (stop - 1) // grid[0] + 1)
    rest = [range(math.ceil(s / g)) for s, g in zip(array.shape[1:], grid[1:])]
    enc = array.metadata.chunk_key_encoding
    return [f"{array.path}/{enc.encode_chunk_key(c)}" for c in itertools.product(first, *rest)]


def stored_objects(loc, prefix: str) -> set[str]:
    """Store keys of every object under ``prefix`` (a clip's or a unit's path): one listing."""
    return {f"{prefix}/{k}" for k in loc.find(f"{loc.store_name}/{prefix}")}


def _outputs(root: zarr.Group, unit: Unit, rec: ChunkRecord, present: set[str]):
    """(output name, array or None when the array itself is gone, its objects not in
    ``present``) per array a record wrote; review previews (``previews/<side>``, their own
    group, their own digests) are not chunked by frame and are skipped."""
    for name in rec.outputs:
        if "/" in name:
            continue
        path = f"{unit.path}/{name}"
        if path not in root:
            yield name, None, [path]
            continue
        arr = root[path]
        yield name, arr, [k for k in object_keys(arr, rec.start, rec.stop) if k not in present]


def missing_objects(root: zarr.Group, unit: Unit, record: ChunkRecord | dict, present: set[str]) -> list[str]:
    """Output objects a record vouches for that are not in ``present`` (a listing)."""
    rec = record if isinstance(record, ChunkRecord) else ChunkRecord.from_json(record)
    return [k for _, _, gone in _outputs(root, unit, rec, present) for k in gone]


def check_unit(root: zarr.Group, unit: Unit, present: set[str], deep: bool = False) -> list[Problem]:
    """Problems of one unit's chunks (records with outcome ``ok`` or ``error`` alike)."""
    from handedit.storage.store import CorruptChunk, digest, read_array

    problems = []
    for k, rec in sorted(read_records(root, unit).items()):
        for name, arr, gone in _outputs(root, unit, rec, present):
            where = arr.path if arr is not None else gone[0]
            if gone:
                detail = "the array itself is gone" if arr is None else ", ".join(gone[:3])
                problems.append(Problem(unit, k, where, rec.start, rec.stop, "missing", detail))
                continue
            if not deep:
                continue
            try:
                got = digest(read_array(arr, slice(rec.start, rec.stop)), like=rec.outputs[name])
            except CorruptChunk as exc:
                problems.append(Problem(unit, k, where, rec.start, rec.stop, "unreadable", exc.cause))
                continue
            if got != rec.outputs[name]:
                problems.append(Problem(unit, k, where, rec.start, rec.stop, "mismatch",
                                        f"digest {got[:12]} != recorded {rec.outputs[name][:12]}"))
    return problems


def verify(loc, clips=None, deep: bool = False) -> list[Problem]:
    """Every problem chunk of the store (or of ``clips``): see the module doc."""
    from handedit.storage.ledger import iter_units
    from handedit.storage.store import open_store

    root = open_store(loc)
    if clips is None:
        clips = sorted(root["clips"].group_keys()) if "clips" in root else []
    problems: list[Problem] = []
    for clip in clips:
        present = stored_objects(loc, clip_path(clip))
        try:
            for unit in iter_units(root, [clip]):
                problems += check_unit(root, unit, present, deep=deep)
        except json.JSONDecodeError:
            problems += damaged_metadata(loc, clip, present)
    return problems


def damaged_metadata(loc, clip: str, present: set[str]) -> list[Problem]:
    """The clip's ``zarr.json`` files that do not parse (a truncated write, garbage)."""
    bad = []
    for key in sorted(k for k in present if k.endswith("zarr.json")):
        try:
            json.loads(loc.read_bytes(f"{loc.store_name}/{key}") or b"")
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            bad.append(Problem(Unit("ingest", clip), -1, key.rsplit("/", 1)[0], 0, 0, "damaged metadata", str(exc)))
    return bad


def repair(loc, problems: list[Problem]) -> dict:
    """Drop the records of the problem chunks; mark the shards holding their clips
    incomplete. The next ``curate`` recomputes exactly those chunks."""
    from handedit.storage.provenance import drop_records
    from handedit.storage.shards import invalidate
    from handedit.storage.store import open_store

    root = open_store(loc, mode="r+")
    by_unit: dict[Unit, set[int]] = {}
    for p in problems:
        if p.kind == "damaged metadata":  # the group or array cannot be read at all: rebuilt from scratch
            for key in stored_objects(loc, p.array):
                loc.remove(f"{loc.store_name}/{key}")
            continue
        by_unit.setdefault(p.unit, set()).add(p.chunk)
    for unit, chunks in by_unit.items():
        drop_records(root, unit, chunks)
    shards = invalidate(loc, sorted({p.unit.clip for p in problems}))
    return {"records_dropped": sum(len(c) for c in by_unit.values()), "units": len(by_unit), "shards": shards}


class VerifiedReads:
    """Frames read for publishing (``release``, ``bench build``): the chunk holding a frame is
    read whole and re-hashed against its record before any of its frames is returned, so
    bytes changed after they were written (still decodable) are refused, never published.
    The cost belongs there: every published pair is read anyway, and a chunk is read once
    for all its frames (the last chunk per array is kept)."""

    def __init__(self, root: zarr.Group):
        self.root = root
        self._records: dict[Unit, dict[int, ChunkRecord]] = {}
        self._chunk: dict[tuple[str, str], tuple[int, int, np.ndarray]] = {}

    def frame(self, unit: Unit, name: str, t: int) -> np.ndarray:
        from handedit.storage.store import CorruptChunk, StoreError, digest, object_file, read_array

        held = self._chunk.get((unit.path, name))
        if held is None or not held[0] <= t < held[1]:
            if unit not in self._records:
                self._records[unit] = read_records(self.root, unit)
            rec = next((r for r in self._records[unit].values() if r.start <= t < r.stop), None)
            arr = self.root[unit.path][name]
            if rec is None or name not in rec.outputs:
                raise StoreError(f"{arr.path} frame {t}: no provenance record vouches for it; run `handedit curate` "
                                 f"again before publishing")
            data = read_array(arr, slice(rec.start, rec.stop))
            got = digest(data, like=rec.outputs[name])
            if got != rec.outputs[name]:
                keys = object_keys(arr, rec.start, rec.stop)
                raise CorruptChunk(arr.path, rec.start, rec.stop, f"its bytes changed after they were written (digest "
                                   f"{got[:12]} != recorded {rec.outputs[name][:12]})",
                                   object_file(arr, keys[0]) if keys else "")
            held = self._chunk[(unit.path, name)] = (rec.start, rec.stop, data)
        return held[2][t - held[0]]


def root_damaged(loc) -> bool:
    """Whether the store's root ``zarr.json`` is there but does not parse."""
    data = loc.read_bytes(f"{loc.store_name}/zarr.json")
    try:
        json.loads(data) if data is not None else None
    except (json.JSONDecodeError, UnicodeDecodeError):
        return True
    return False


def rebuild_root(loc) -> dict:
    """Write the root ``zarr.json`` anew from what the groups below still say: the schema
    this code writes, ``frames_per_chunk`` from a status array's chunking (every unit has
    one), and a note in place of the creation time. Raises ``StoreError`` when no unit is
    left to read it from."""
    from handedit.storage.layout import SCHEMA_VERSION
    from handedit.storage.store import StoreError, now_iso

    for path in sorted(p for p in loc.find(f"{loc.store_name}/clips") if p.endswith("/status/zarr.json")):
        try:
            meta = json.loads(loc.read_bytes(f"{loc.store_name}/clips/{path}"))
            f = int(meta["chunk_grid"]["configuration"]["chunk_shape"][0])
        except (TypeError, ValueError, KeyError, IndexError, json.JSONDecodeError):
            continue
        attrs = {"schema_version": SCHEMA_VERSION, "frames_per_chunk": f, "created": "unknown",
                 "created_by": f"rebuilt by handedit verify --repair at {now_iso()}"}
        loc.write_json(f"{loc.store_name}/zarr.json", {"zarr_format": 3, "node_type": "group", "attributes": attrs})
        return attrs
    raise StoreError(f"{loc.store_url}/zarr.json is damaged and no unit is left to rebuild it from: curate into a new --out")


def require_complete(loc, clips, command: str) -> None:
    """Publishing reads only finished runs and data the records vouch for: a ``StoreError``
    naming the shards a run left incomplete (failed chunks or tasks, a full disk: their
    rejections are not the data's), or listing what is missing (presence check)."""
    from handedit.storage.shards import read_manifest, shard_ids
    from handedit.storage.store import StoreError

    open_shards = [s for s in shard_ids(loc) if not (read_manifest(loc, s) or {}).get("complete")]
    if open_shards:
        raise StoreError(f"{command}: {len(open_shards)} shard(s) of {loc.store_url} were left incomplete by their last "
                         f"curate run ({', '.join(open_shards[:5])}); run `handedit curate` again until it completes, "
                         f"then {command}")

    problems = verify(loc, clips=clips)
    if problems:
        listing = "\n  ".join(p.describe() for p in problems[:10])
        raise StoreError(f"{command}: {len(problems)} recorded chunk(s) of {loc.store_url} are missing:\n  {listing}\n"
                         f"run `handedit verify {loc.url} --repair`, then `handedit curate` again, before publishing")


def chunk_object_count(loc, clip: str) -> int:
    """Chunk objects stored under a clip (one listing): what a complete shard records."""
    return sum(1 for k in stored_objects(loc, clip_path(clip)) if "/c/" in k)


def clips_missing_objects(loc, counts: dict[str, int]) -> list[tuple[str, int, int]]:
    """(clip, stored, recorded) for every clip that now holds fewer chunk objects than
    ``counts`` (a shard's manifest) recorded: a deleted chunk or array."""
    out = []
    for clip, n in counts.items():
        have = chunk_object_count(loc, clip)
        if have < n:
            out.append((clip, have, n))
    return out
