"""Provenance: one record per (unit, chunk), kept in the unit group's attributes.

A record says what produced a chunk: stage name and version, parameters, fingerprints
of the exact input arrays read, digests of the arrays written, code version, host,
attempt count and timings, and the chunk's rejections with reasons.

The provenance *key* hashes (stage, version, params, input fingerprints). A chunk whose
stored record has the same key and completed is skipped on re-run. Inputs are content
digests of what a stage read, so a change propagates exactly as far as the data it
changes: new harmonize parameters rewrite harmonize images, but QC, which reads only
status codes, sees the same inputs and is skipped.

The record is written after the data by the driver; it is the commit marker. A chunk
whose task died half-way has no matching record and is recomputed.
"""

from __future__ import annotations

import hashlib
import os
import socket
from dataclasses import asdict, dataclass, field
from typing import Any

import zarr

from handedit.storage.layout import Unit
from handedit.storage.store import dumps, jsonable

PROVENANCE_ATTR = "provenance"


def provenance_key(stage: str, version: int, params: dict, inputs: dict[str, str]) -> str:
    payload = dumps({"stage": stage, "version": version, "params": params, "inputs": inputs})
    return hashlib.blake2b(payload.encode(), digest_size=16).hexdigest()


@dataclass
class ChunkRecord:
    stage: str
    chunk: int
    start: int
    stop: int
    key: str
    version: int
    params: dict
    inputs: dict[str, str]
    outputs: dict[str, str] = field(default_factory=dict)
    method: str = ""
    outcome: str = "ok"  # "ok" or "error"
    error: str | None = None
    rejections: list[dict] = field(default_factory=list)  # {frame, reason, detail}
    counts: dict[str, int] = field(default_factory=dict)  # status code -> frames
    code_version: str = ""
    host: str = field(default_factory=socket.gethostname)
    pid: int = field(default_factory=os.getpid)
    attempts: int = 1
    started: str = ""
    seconds: float = 0.0
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return jsonable(asdict(self))

    @classmethod
    def from_json(cls, data: dict) -> "ChunkRecord":
        known = {k: v for k, v in data.items() if k in cls.__dataclass_fields__}
        return cls(**known)


def read_records(root: zarr.Group, unit: Unit) -> dict[int, ChunkRecord]:
    if unit.path not in root:
        return {}
    raw = root[unit.path].attrs.get(PROVENANCE_ATTR) or {}
    return {int(k): ChunkRecord.from_json(v) for k, v in raw.items()}


def write_records(root: zarr.Group, unit: Unit, records: list[ChunkRecord]) -> None:
    """Driver only: merge records into the unit's provenance attribute."""
    group = root.require_group(unit.path)
    current = dict(group.attrs.get(PROVENANCE_ATTR) or {})
    for rec in records:
        current[str(rec.chunk)] = rec.to_json()
    group.attrs.update({PROVENANCE_ATTR: current})


def drop_records(root: zarr.Group, unit: Unit, chunks) -> None:
    """Forget chunks' records (``handedit verify --repair``): they count as never computed."""
    group = root[unit.path]
    current = dict(group.attrs.get(PROVENANCE_ATTR) or {})
    for k in chunks:
        current.pop(str(k), None)
    group.attrs.update({PROVENANCE_ATTR: current})


def is_current(record: ChunkRecord | dict | None, key: str) -> bool:
    """A stored chunk can be reused: same key, and it completed (errors are retried)."""
    if isinstance(record, dict):
        return record.get("key") == key and record.get("outcome") == "ok"
    return record is not None and record.key == key and record.outcome == "ok"
