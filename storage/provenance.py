"""Provenance: one record per (unit, chunk), each its own small JSON file.

Records lie beside the store, ``<store>.records/<unit path>/<chunk>.json`` (e.g.
``runs/demo/handedit.zarr.records/clips/c/segment/3.json``): writing one chunk's record
touches no other record, so its cost does not grow with the clip, and no two writers ever
share a file. Stores written before kept a unit's records in its ``provenance``
attribute; those are still read (a file wins), and dropping a record drops both.

A record says what produced a chunk: stage name and version, parameters, fingerprints
of the exact input arrays read, digests of the arrays written, code version, host,
attempt count and timings, and the chunk's rejections with reasons.

The provenance *key* hashes (stage, version, params, input fingerprints). A chunk whose
stored record has the same key and completed is skipped on re-run. Inputs are content
digests of what a stage read, so a change propagates exactly as far as the data it
changes: new harmonize parameters rewrite harmonize images, but QC, which reads only
status codes, sees the same inputs and is skipped.

The record is written after the data by the walk that owns the unit; it is the commit
marker. A chunk whose task died half-way has no matching record and is recomputed.
"""

from __future__ import annotations

import hashlib
import json
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
    setup_seconds: float = 0.0  # of ``seconds``, building per-process machinery later tasks reuse (handedit.setup_meter)
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return jsonable(asdict(self))

    @classmethod
    def from_json(cls, data: dict) -> "ChunkRecord":
        known = {k: v for k, v in data.items() if k in cls.__dataclass_fields__}
        return cls(**known)


def _records_dir(root: zarr.Group, unit: Unit):
    from handedit.storage.location import location_of

    loc = location_of(root)
    return loc, f"{loc.store_name}.records/{unit.path}"


def read_records(root: zarr.Group, unit: Unit) -> dict[int, ChunkRecord]:
    if unit.path not in root:
        return {}
    legacy = root[unit.path].attrs.get(PROVENANCE_ATTR) or {}
    out = {int(k): ChunkRecord.from_json(v) for k, v in legacy.items()}
    loc, folder = _records_dir(root, unit)
    names = [n for n in loc.listdir(folder) if n.endswith(".json") and n[:-5].isdigit()]
    if names:
        paths = [loc.path(folder, n) for n in names]
        for path, data in loc.fs.cat(paths, on_error="omit").items():
            out[int(path.rsplit("/", 1)[1][:-5])] = ChunkRecord.from_json(json.loads(data))
    return out


def write_records(root: zarr.Group, unit: Unit, records: list[ChunkRecord]) -> None:
    """Write each record to its own file (whole, atomically): the unit's only writer calls this."""
    loc, folder = _records_dir(root, unit)
    for rec in records:
        loc.write_bytes(f"{folder}/{rec.chunk}.json", dumps(rec.to_json()).encode())


def drop_records(root: zarr.Group, unit: Unit, chunks=None) -> None:
    """Forget chunks' records (all of the unit's when ``chunks`` is None; ``handedit verify
    --repair``, a recreated unit): they count as never computed."""
    loc, folder = _records_dir(root, unit)
    everything = chunks is None
    if everything:
        chunks = [n[:-5] for n in loc.listdir(folder) if n.endswith(".json")]
    for k in chunks:
        loc.remove(f"{folder}/{k}.json")
    if unit.path in root:
        group = root[unit.path]
        legacy = dict(group.attrs.get(PROVENANCE_ATTR) or {})
        if legacy:
            group.attrs.update({PROVENANCE_ATTR: {} if everything else
                                {k: v for k, v in legacy.items() if k not in {str(c) for c in chunks}}})


def _input_label(name: str) -> str:
    """What an input key names, for people: ``clips/c/source#0/frames`` -> ``ingest data``."""
    from handedit.storage.layout import stage_layouts

    if "#" in name:  # an array of a chunk: <unit path>#<chunk>/<array>
        parts = name.split("#", 1)[0].split("/")
        stage = "ingest" if parts[-1] == "source" else next((p for p in reversed(parts) if p in stage_layouts()), parts[-1])
        return f"{stage} output"
    if "@" in name:  # an attribute: <unit path>@<name>
        return name.rsplit("@", 1)[1]
    return {"robot": "robot URDF or meshes", "clip": "clip facts", "versions": "config versions",
            "source": "source content"}.get(name, name.replace("model:", "model file "))


def changed_inputs(old: dict, version: int, params: dict, inputs: dict[str, str]) -> str:
    """Why a stored chunk's key no longer matches: what changed, in words."""
    why = []
    if old.get("version") != version:
        why.append(f"version {old.get('version')} -> {version}")
    if dumps(old.get("params") or {}) != dumps(params):
        names = sorted(k for k in {*(old.get("params") or {}), *params} if (old.get("params") or {}).get(k) != params.get(k))
        why.append("parameters " + ", ".join(names))
    before = old.get("inputs") or {}
    labels = sorted({_input_label(k) for k in {*before, *inputs} if before.get(k) != inputs.get(k)})
    why += [f"{label} changed" for label in labels]
    if old.get("outcome") not in (None, "ok") and not why:
        return "failed before"
    return "; ".join(why) or "key scheme changed"


def is_current(record: ChunkRecord | dict | None, key: str) -> bool:
    """A stored chunk can be reused: same key, and it completed (errors are retried)."""
    if isinstance(record, dict):
        return record.get("key") == key and record.get("outcome") == "ok"
    return record is not None and record.key == key and record.outcome == "ok"


def pending_review(records: dict) -> set[str]:
    """Sides of a hand-arm sequence whose base waits for an operator (``review: manual``, not yet
    decided with ``handedit review``): their pairs are held back from a release."""
    out = set()
    for rec in records.values():
        for side, vb in ((rec.extra or {}).get("virtual_base") or {}).items():
            if str((vb or {}).get("selected_by", "")).startswith("pending"):
                out.add(side)
    return out
