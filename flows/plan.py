"""Planning a run lazily: source trees -> groups -> shards of clips, and what makes a shard current.

The driver never lists more than it works on: groups come one at a time from the sources
(an EgoDex tree yields one task folder at a time), and each group is cut into shards of
``shard_size`` clips in listing order. A shard's id is its group and its index in the
group (``egodex-add_remove_lid-00000``), so subsets (``--task``), truncations
(``--max-clips``) and growing trees give the same ids to the same clips: episodes are
listed in numeric order and new ones append. Clip data lives at ``clips/<clip>/`` whatever
its shard, so a moved shard boundary never moves or recomputes data; it only rewrites the
affected shards' bookkeeping.

A shard's *digest* is what decides, with one manifest read, that it is already done: the
run key (frames per chunk, each stage's version and parameters, each embodiment's id,
track and URDF content, the code's schema) and, per clip, its spec and the size and mtime
of each file it reads. A changed source file, a new embodiment or new stage parameters
change the digest, and the shard is re-planned (its current chunks are still skipped by
their provenance keys).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass
from typing import Iterator

from handedit.sources import iter_groups
from handedit.storage.store import dumps


@dataclass(frozen=True)
class ShardPlan:
    id: str
    group: str
    specs: tuple  # clip specs (pydantic models), in listing order

    @property
    def clip_ids(self) -> list[str]:
        return [s.id for s in self.specs]

    def digest(self, run_key: str) -> str:
        h = hashlib.blake2b(run_key.encode(), digest_size=16)
        for spec in self.specs:
            h.update(spec.model_dump_json().encode())
            h.update(json.dumps(file_stamps(spec)).encode())
        return h.hexdigest()


def file_stamps(spec) -> list:
    """(path, size, mtime_ns) of every file a clip spec reads: a cheap change detector
    (content hashes are computed by ingest, once, and recorded in provenance)."""
    out = []
    for p in getattr(spec, "files", lambda: [])():
        try:
            st = os.stat(p)
            out.append([str(p), st.st_size, st.st_mtime_ns])
        except OSError:
            out.append([str(p), None, None])
    return out


def _group_id(group: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", group).strip("._") or "clips"


def iter_shards(trees, clips, shard_size: int) -> Iterator[ShardPlan]:
    """Shards in listing order, one group at a time (see module doc)."""
    for group, specs in iter_groups(trees, clips):
        gid = _group_id(group)
        for i in range(0, len(specs), shard_size):
            yield ShardPlan(f"{gid}-{i // shard_size:05d}", group, tuple(specs[i:i + shard_size]))


def run_key(frames_per_chunk: int, stage_params: dict, embodiments: list[dict], schema: int) -> str:
    payload = dumps({"F": frames_per_chunk, "stages": stage_params, "embodiments": embodiments, "schema": schema})
    return hashlib.blake2b(payload.encode(), digest_size=16).hexdigest()
