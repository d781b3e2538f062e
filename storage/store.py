"""Opening the store, creating unit arrays, chunk reads and writes.

Concurrency contract (measured on this stack: two writers in one chunk, or concurrent
attribute updates, silently lose data):
- ``create_or_open_store`` and the root's attributes: the flow driver only.
- ``create_unit`` / ``set_attrs`` / ``write_chunk`` of a unit: the one task that owns the unit
  (``tasks.clip``), for whole chunks; provenance records are files of their own
  (``storage.provenance``). ``handedit review`` writes a retarget unit's ``reviews``
  attribute while no curate run works on that clip.
"""

from __future__ import annotations

import hashlib
import json
import math
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import xxhash
import zarr
from zarr.codecs import BloscCodec, BloscShuffle

from handedit.storage import handoff
from handedit.storage.layout import (PREVIEW_CANDIDATES, SCHEMA_VERSION, ArraySpec, Unit, arrays_for, stage_arrays,
                            preview_path)

# Masks and label maps compress best bit-shuffled; 8-bit colour frames do not (their bits
# are not independent), and zstd level 1 writes them ~40 % faster than level 3 with
# bitshuffle at a smaller size (measured on the real video and EgoDex frames, 960x540).
# Float depth compresses best byte-shuffled at level 1 (a third of bit-shuffled level 3's
# encoding time, half its decoding, 14 % smaller: render depth of the demo clips). Blosc
# blocks of 256 KiB rather than its default for these levels: on EgoDex frames colour
# encodes 22 % and decodes 39 % faster and comes out 8 % smaller, the render's RGBA twice as
# fast both ways (bench: 16-frame chunks of each, numcodecs' Blosc, this machine).
BLOCK = 1 << 18
IMAGE_CODEC = BloscCodec(cname="zstd", clevel=3, shuffle=BloscShuffle.bitshuffle, blocksize=BLOCK)
COLOUR_CODEC = BloscCodec(cname="zstd", clevel=1, shuffle=BloscShuffle.noshuffle, blocksize=BLOCK)
DEPTH_CODEC = BloscCodec(cname="zstd", clevel=1, shuffle=BloscShuffle.shuffle, blocksize=BLOCK)


def image_codec(spec: ArraySpec) -> BloscCodec:
    if spec.dtype == "uint8" and spec.dims[-1] in ("rgb", "rgba"):
        return COLOUR_CODEC
    return DEPTH_CODEC if np.dtype(spec.dtype).kind == "f" else IMAGE_CODEC

# Every written chunk gets its object, even when it equals the fill value (all-OK status,
# an empty mask): presence of the object is what a skip checks (handedit.storage.integrity).
zarr.config.set({"array.write_empty_chunks": True})

REPAIR_HINT = "run `handedit verify DIR --deep --repair`, then `handedit curate` again to recompute it"


class StoreError(RuntimeError):
    """A store that cannot be opened or does not match this code's schema."""


class StoreFull(StoreError):
    """The store's device is full (or over quota, or read-only): the run fails, naming the
    file; no frame is rejected for it (a rejection would be published as a removed pair)."""


def store_full(exc: BaseException, where: str = "") -> StoreFull | None:
    """A ``StoreFull`` for an OSError that no retry can help (no space, quota, read-only);
    ``where``: what was being written when the error does not name its file."""
    import errno

    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS):
        where = exc.filename or where or "the run's files"
        return StoreFull(f"cannot write {where}: {exc.strerror or exc} (errno {exc.errno}); free space on that device (or "
                         f"curate into another --out), then run again: committed chunks are kept")
    return None


class CorruptChunk(StoreError):
    """Stored bytes that do not decode (or fail their checksum), named down to the file."""

    def __init__(self, array_path: str, start: int, stop: int, reason: str, file: str = ""):
        self.array_path, self.start, self.stop, self.cause, self.file = array_path, start, stop, reason, file
        where = f" (file {file})" if file else ""
        super().__init__(f"corrupt chunk in {array_path} frames {start}-{stop - 1}{where}: {reason}; {REPAIR_HINT}")

    def __reduce__(self):  # travels between Dask processes
        return (CorruptChunk, (self.array_path, self.start, self.stop, self.cause, self.file))


def object_file(array: zarr.Array, key: str) -> str:
    """The file (or object URL) that holds ``key`` of ``array``'s store, for messages."""
    store = array.store
    root = getattr(store, "root", None) or getattr(store, "path", "")
    return f"{str(root).rstrip('/')}/{key}" if root else key


def read_array(array: zarr.Array, selection=slice(None)) -> np.ndarray:
    """``array[selection]``, with a decode or checksum error turned into ``CorruptChunk``
    naming the array, the frames and the file of the first bad object (a slow search that
    runs only after a failure)."""
    try:
        return array[selection]
    except Exception as exc:  # noqa: BLE001 - codecs raise many types; re-raised below when not a decode error
        if isinstance(exc, (KeyError, IndexError, TypeError, MemoryError)):
            raise
        reason = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
    from handedit.storage.integrity import object_keys

    step = (array.shards or array.chunks)[0]
    for start in range(0, array.shape[0], step):
        stop = min(start + step, array.shape[0])
        try:
            array[start:stop]
        except Exception:  # noqa: BLE001 - this is the bad object
            raise CorruptChunk(array.path, start, stop, reason, object_file(array, object_keys(array, start, stop)[0])) from None
    raise CorruptChunk(array.path, 0, array.shape[0], reason)


def jsonable(obj: Any) -> Any:
    """JSON-safe copy: numpy scalars/arrays to Python, NaN/inf to None, paths to str."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, Path):
        return str(obj)
    if obj is None or isinstance(obj, (str, int)):
        return obj
    if hasattr(obj, "model_dump"):
        return jsonable(obj.model_dump(mode="json"))
    return str(obj)


def now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _location(where) -> "Location":
    from handedit.storage.location import Location

    return where if isinstance(where, Location) else Location(where)


def open_store(where, mode: str = "r") -> zarr.Group:
    """Open an existing store (``mode='r'`` or ``'r+'``) after checking its schema.

    ``where``: a run folder, a ``.zarr`` path or URL, or a ``Location``."""
    loc = _location(where)
    if not loc.store_exists():
        raise StoreError(f"{loc.store_url} is not a handedit store (no zarr.json); run `handedit curate --out DIR` to make one")
    root = _open_group(loc, mode)
    version = root.attrs.get("schema_version")
    if version != SCHEMA_VERSION:
        raise StoreError(f"{loc.store_url} has schema {version}, this code reads schema {SCHEMA_VERSION}; "
                         f"re-curate into a new store")
    return root


def _open_group(loc, mode: str) -> zarr.Group:
    try:
        return zarr.open_group(loc.zarr_store(read_only=mode == "r"), mode=mode)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise StoreError(f"{loc.store_url}/zarr.json is not valid JSON ({exc}); the store's root metadata is damaged: "
                         f"run `handedit verify {loc.url} --repair` to rebuild it from the groups") from None


def create_or_open_store(where, frames_per_chunk: int, code_version: str) -> zarr.Group:
    """Driver: open the store, creating it on first use. Chunking is fixed at creation.

    The root's attributes hold only what is fixed per store (schema, chunking, creation);
    registries and run logs are per shard (``handedit.storage.shards``)."""
    loc = _location(where)
    if loc.store_exists():
        root = open_store(loc, mode="r+")
        stored = root.attrs.get("frames_per_chunk")
        if stored != frames_per_chunk:
            raise StoreError(
                f"{loc.store_url} was created with frames_per_chunk={stored}; pass the same value "
                f"(or a new --out) - chunk boundaries are what keeps one writer per chunk"
            )
        return root
    root = zarr.open_group(loc.zarr_store(), mode="w")
    root.attrs.update(jsonable({"schema_version": SCHEMA_VERSION, "frames_per_chunk": frames_per_chunk,
                                "created": now_iso(), "created_by": code_version}))
    return root


def create_unit(
    root: zarr.Group,
    unit: Unit,
    n_frames: int,
    sizes: dict[str, int],
    frames_per_chunk: int,
    has_object: bool = False,
    has_gt: bool = False,
    attrs: dict | None = None,
    has_arm: bool = False,
) -> zarr.Group:
    """The unit's owner: create (or reuse, when the shape matches) its group and arrays.

    An array whose shape changed (e.g. an embodiment's DoF) is recreated empty, and the
    unit's provenance is dropped with it, so none of its chunks counts as current.
    """
    group = root.require_group(unit.path)
    recreated = False
    for spec in arrays_for(unit.stage, has_object, has_gt, has_arm):
        shape = spec.shape(n_frames, sizes)
        if spec.name in group:
            existing = group[spec.name]
            if tuple(existing.shape) == shape and str(existing.dtype) == spec.dtype:
                continue
            del group[spec.name]
            recreated = True
        _create_array(group, spec, shape, frames_per_chunk)
    if recreated:
        from handedit.storage.provenance import drop_records

        drop_records(root, unit)
    if attrs:
        group.attrs.update(jsonable(attrs))
    return group


def _create_array(group: zarr.Group, spec: ArraySpec, shape: tuple[int, ...], f: int) -> None:
    tail = shape[1:]
    dims = ("frame", *spec.dims)
    if spec.image:
        group.create_array(
            spec.name, shape=shape, dtype=spec.dtype, chunks=(1, *tail), shards=(f, *tail),
            compressors=image_codec(spec), fill_value=spec.fill, dimension_names=dims,
        )
    else:
        group.create_array(
            spec.name, shape=shape, dtype=spec.dtype, chunks=(f, *tail),
            fill_value=spec.fill, dimension_names=dims,
        )


def create_previews(root: zarr.Group, unit: Unit, height: int, width: int, side: str, frames: int) -> None:
    """The unit's owner: the (empty) review-preview group of one hand of a hand-arm retarget unit,
    for ``frames`` frames per candidate."""
    group = root.require_group(preview_path(unit, side))
    k, p = PREVIEW_CANDIDATES, frames
    for name in ("ego", "third"):
        if name not in group or group[name].shape != (k, p, height, width, 4):
            group.create_array(name, shape=(k, p, height, width, 4), dtype="uint8", chunks=(1, 1, height, width, 4),
                               compressors=COLOUR_CODEC, fill_value=0, overwrite=True,
                               dimension_names=("candidate", "preview_frame", "y", "x", "rgba"))
    group.create_array("candidates", shape=(k,), dtype="int16", fill_value=-1, overwrite=True, dimension_names=("candidate",))
    group.create_array("frames", shape=(p,), dtype="int32", fill_value=-1, overwrite=True, dimension_names=("preview_frame",))


def drop_previews(root: zarr.Group, unit: Unit, side: str) -> None:
    """The unit's owner, where previews are not asked for: no group, so none of an earlier run's
    previews is shown as this run's."""
    path = preview_path(unit, side)
    if path in root:
        del root[path]


def write_previews(root: zarr.Group, unit: Unit, candidates: list[int], frames: list[int],
                   ego: np.ndarray, third: np.ndarray, side: str) -> dict[str, str]:
    """Task: one hand's top candidates' egocentric and third-person renders (the unit's one writer)."""
    group = root[preview_path(unit, side)]
    k, p = len(candidates), len(frames)
    group["candidates"][:] = np.array([*candidates, *[-1] * (PREVIEW_CANDIDATES - k)], np.int16)
    group["frames"][:p] = np.asarray(frames, np.int32)
    group["ego"][:k, :p] = ego
    group["third"][:k, :p] = third
    return {"previews/ego": digest(ego), "previews/third": digest(third)}


def read_previews(root: zarr.Group, unit: Unit, side: str) -> dict[str, np.ndarray]:
    group = root[preview_path(unit, side)]
    cands = read_array(group["candidates"])
    k = int((cands >= 0).sum())
    frames = read_array(group["frames"])
    p = int((frames >= 0).sum())
    return {"candidates": cands[:k], "frames": frames[:p], "ego": read_array(group["ego"], np.s_[:k, :p]),
            "third": read_array(group["third"], np.s_[:k, :p])}


DIGEST_SCHEME = "xxh3:"


def digest(array: np.ndarray, like: str | None = None) -> str:
    """Content fingerprint of an array (shape, dtype and bytes): XXH3-128, ``xxh3:``-prefixed.

    A fingerprint here guards against corruption and keys caches (nobody chooses the bytes to
    collide), so a non-cryptographic 128-bit hash serves, at ~25x blake2b's speed: every image
    write hashes its frames, 0.03 against 0.67 ms per 640x480 RGB frame. ``like``: a recorded
    digest whose kind to compute; records written before carry un-prefixed blake2b ones."""
    a = np.ascontiguousarray(array)
    if like is not None and not like.startswith(DIGEST_SCHEME):
        h = hashlib.blake2b(digest_size=16)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(memoryview(a).cast("B") if a.size else b"")
        return h.hexdigest()
    h = xxhash.xxh3_128(f"{a.dtype.str}{a.shape}".encode())
    h.update(memoryview(a).cast("B") if a.size else b"")
    return DIGEST_SCHEME + h.hexdigest()


def write_chunk(root: zarr.Group, unit: Unit, start: int, arrays: Mapping[str, np.ndarray]) -> dict[str, str]:
    """Task: write frames [start, start+n) of each named array; return their digests.

    The caller owns this chunk range (chunk-aligned), so this is the only writer.
    """
    group = root[unit.path]
    digests: dict[str, str] = {}
    written: dict[str, np.ndarray] = {}
    for name, value in arrays.items():
        if name not in group:
            raise KeyError(f"{unit.label} has no array {name!r}; schema: {[a.name for a in stage_arrays(unit.stage)]}")
        target = group[name]
        value = np.asarray(value, dtype=target.dtype)
        stop = start + value.shape[0]
        if value.shape[1:] != tuple(target.shape[1:]) or stop > target.shape[0]:
            raise ValueError(f"{unit.label}/{name}: got {value.shape} at {start}, array is {target.shape}")
        try:
            target[start:stop] = value
        except Exception as exc:  # noqa: BLE001 - a partial shard write reads the old shard first
            if isinstance(exc, (KeyError, IndexError, TypeError, MemoryError, OSError)):
                raise
            _delete_objects(target, start, stop)  # its bytes are garbage: this chunk replaces them whole
            target[start:stop] = value
        digests[name] = digest(value)
        written[name] = value
    kept = handoff.current()
    if kept is not None:  # stored whole: the walk's later readers of this chunk may take it from memory
        kept.keep(root.store, unit.path, start, written)
    return digests


def _delete_objects(array: zarr.Array, start: int, stop: int) -> None:
    from zarr.core.sync import sync

    from handedit.storage.integrity import object_keys

    for key in object_keys(array, start, stop):
        sync(array.store.delete(key))


def read_chunk(root: zarr.Group, unit: Unit, names: Iterable[str], start: int, stop: int) -> dict[str, np.ndarray]:
    """Frames [start, stop) of each named array (from memory where this walk just wrote
    them or this worker decoded them for another walk, ``storage.handoff``)."""
    kept, out, group = handoff.current(), {}, None
    for name in names:
        value = None if kept is None else kept.get(root.store, unit.path, name, start, stop)
        if value is None:
            group = root[unit.path] if group is None else group
            value = read_array(group[name], slice(start, stop))
            if kept is not None:
                value = kept.decoded(root.store, unit.path, unit.clip, name, start, stop, value)
        out[name] = value
    return out


def writable(array: np.ndarray) -> np.ndarray | None:
    """``array`` when a stage may write into it (read for this chunk only), None when it is
    shared (read-only: kept or reused, ``storage.handoff``): the stage then allocates."""
    return array if array.flags.writeable else None


def has_array(root: zarr.Group, unit: Unit, name: str) -> bool:
    return unit.path in root and name in root[unit.path]


def unit_attrs(root: zarr.Group, unit: Unit) -> dict:
    return dict(root[unit.path].attrs) if unit.path in root else {}


def set_attrs(root: zarr.Group, path: str, values: dict) -> None:
    """Update attributes of a group (JSON-safe): its one writer (see module doc)."""
    root.require_group(path).attrs.update(jsonable(values))


def dumps(obj: Any) -> str:
    return json.dumps(jsonable(obj), sort_keys=True, separators=(",", ":"))
