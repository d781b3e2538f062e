"""``write-release-shard``: one WebDataset shard of a release (a Prefect task on Dask).

Reads its pairs' frames and masks from the curated store, writes the shard to a local
temporary file (deterministic bytes: ``handedit.release.samples.TarWriter``), hashes it,
then moves or uploads it whole to ``shards/<key>.tar`` with a ``<key>.json`` beside it
(hash, size, pairs). A shard whose sidecar already exists (an earlier, interrupted
attempt of the same content) is not written again.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass

from prefect import task
from prefect.cache_policies import NO_CACHE

from handedit.digests import file_sha256
from handedit.release.samples import Pair, TarWriter, sample_files, union_sides
from handedit.storage import Location, Unit
from handedit.storage.layout import SCOPE_MASK
from handedit.storage.releases import shard_info_rel, shard_rel
from handedit.storage.store import read_array
from handedit.tasks.common import open_root


@dataclass(frozen=True)
class ShardJob:
    out: str  # the releases location
    store: str  # the curated store's URL
    key: str
    pairs: tuple[dict, ...]  # Pair fields, frames in order


def write_shard(job: ShardJob) -> dict:
    loc = Location(job.out)
    sidecar = shard_info_rel(job.key)
    done = loc.read_json(sidecar)
    if done:
        return {**done, "written": False}
    root = open_root(job.store)
    fd, tmp = tempfile.mkstemp(prefix="release-", suffix=".tar")
    n = 0
    with os.fdopen(fd, "wb") as f:
        writer = TarWriter(f)
        for d in job.pairs:
            p = Pair(**{**d, "sides": tuple(d["sides"])})
            src_g = root[Unit("ingest", p.clip).path]
            seg = root[Unit("segment", p.clip).path]
            comp = root[Unit("composite", p.clip, embodiment=p.embodiment).path]
            harm = root[Unit("harmonize", p.clip, embodiment=p.embodiment).path]
            sides_all = list(seg.attrs.get("hands") or ["right"])
            t = p.frame
            for name, data in sample_files(
                    p, read_array(src_g["frames"], t), read_array(harm["image"], t), read_array(comp["image"], t),
                    union_sides(read_array(seg[SCOPE_MASK[p.track]], t), sides_all, list(p.sides)),
                    union_sides(read_array(comp["robot_mask"], t), sides_all, list(p.sides)),
                    read_array(src_g["object_mask"], t) if "object_mask" in src_g else None):
                writer.add(name, data)
            n += 1
        writer.close()
    sha = file_sha256(tmp)
    size = os.path.getsize(tmp)
    loc.put_file(tmp, shard_rel(job.key))
    info = {"key": job.key, "path": shard_rel(job.key), "sha256": sha, "bytes": size, "pairs": n}
    loc.write_json(sidecar, info)  # after the tar: a sidecar vouches for a complete shard
    return {**info, "written": True}


@task(name="write-release-shard", task_run_name="release-shard[{job.key}]", retries=2, retry_delay_seconds=[2.0, 10.0],
      persist_result=False, cache_policy=NO_CACHE)
def write_release_shard(job: ShardJob) -> dict:
    return write_shard(job)
