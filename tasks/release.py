"""``write-release-shard``: one WebDataset shard of a release (a Prefect task on Dask).

Reads its pairs' frames and masks from the curated store, each chunk re-hashed against its
record first (``storage.integrity.VerifiedReads``: changed bytes are refused, naming the
array, frames and file), writes the shard to a local temporary file (deterministic bytes:
``handedit.release.samples.TarWriter``), hashes it, then moves or uploads it whole to
``shards/<key>.tar`` with a ``<key>.json`` beside it (hash, size, pairs, ``verified``). A
shard whose sidecar already exists and says its bytes were verified (an earlier,
interrupted attempt of the same content) is not written again.
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
from handedit.storage.integrity import VerifiedReads
from handedit.tasks.common import open_root, retry_transient


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
    if done and done.get("verified"):
        return {**done, "written": False}
    root = open_root(job.store)
    reads = VerifiedReads(root)
    fd, tmp = tempfile.mkstemp(prefix="release-", suffix=".tar")
    n = 0
    try:
        with os.fdopen(fd, "wb") as f:
            writer = TarWriter(f)
            for d in job.pairs:
                p = Pair(**{**d, "sides": tuple(d["sides"])})
                src, seg = Unit("ingest", p.clip), Unit("segment", p.clip)
                comp, harm = (Unit(s, p.clip, embodiment=p.embodiment) for s in ("composite", "harmonize"))
                sides_all = list(root[seg.path].attrs.get("hands") or ["right"])
                t = p.frame
                for name, data in sample_files(
                        p, reads.frame(src, "frames", t), reads.frame(harm, "image", t), reads.frame(comp, "image", t),
                        union_sides(reads.frame(seg, SCOPE_MASK[p.track], t), sides_all, list(p.sides)),
                        union_sides(reads.frame(comp, "robot_mask", t), sides_all, list(p.sides)),
                        reads.frame(src, "object_mask", t) if "object_mask" in root[src.path] else None):
                    writer.add(name, data)
                n += 1
            writer.close()
    except BaseException:
        os.unlink(tmp)
        raise
    sha = file_sha256(tmp)
    size = os.path.getsize(tmp)
    loc.put_file(tmp, shard_rel(job.key))
    info = {"key": job.key, "path": shard_rel(job.key), "sha256": sha, "bytes": size, "pairs": n, "verified": True}
    loc.write_json(sidecar, info)  # after the tar: a sidecar vouches for a complete shard
    return {**info, "written": True}


@task(name="write-release-shard", task_run_name="release-shard[{job.key}]", retries=2, retry_delay_seconds=[2.0, 10.0],
      retry_condition_fn=retry_transient, persist_result=False, cache_policy=NO_CACHE)
def write_release_shard(job: ShardJob) -> dict:
    return write_shard(job)



@dataclass(frozen=True)
class VideoJob:
    out: str  # the releases location
    store: str  # the curated store's URL
    key: str
    clip: str
    embodiment: str
    n_frames: int
    fps: float
    kept: tuple[int, ...]  # the clip's frames this release holds as pairs


def write_videos(job: VideoJob) -> dict:
    """One clip x embodiment's source, pseudo-GT and robot-mask videos (every frame of the clip,
    in order), encoded into a local temporary folder, hashed, then moved or uploaded whole; the
    sidecar last, so a sidecar vouches for complete videos (an interrupted attempt is redone)."""
    import shutil

    from handedit.export.video import PAIR_SPECS
    from handedit.storage.releases import video_info_rel, video_rel
    from handedit.tasks.export import PAIR_VIDEOS, EpisodeJob, encode_episode

    loc = Location(job.out)
    sidecar = video_info_rel(job.key)
    done = loc.read_json(sidecar)
    if done and done.get("verified"):
        return {**done, "written": False}
    tmp = tempfile.mkdtemp(prefix="release-videos-")
    try:
        files = {}
        root = open_root(job.store)
        sides = tuple(root[Unit("composite", job.clip, embodiment=job.embodiment).path].attrs.get("hands") or ["right"])
        for name in PAIR_VIDEOS:
            path = os.path.join(tmp, f"{name}.mp4")
            encode_episode(EpisodeJob(job.store, job.clip, job.embodiment, job.n_frames, job.fps, ((name, path),),
                                      PAIR_SPECS[name], sides))
            files[name] = {"path": video_rel(job.key, name), "sha256": file_sha256(path), "bytes": os.path.getsize(path)}
        for name, f in files.items():
            loc.put_file(os.path.join(tmp, f"{name}.mp4"), f["path"])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    info = {"key": job.key, "clip": job.clip, "embodiment": job.embodiment, "frames": job.n_frames, "fps": job.fps,
            "kept": list(job.kept), "files": files, "verified": True}
    loc.write_json(sidecar, info)
    return {**info, "written": True}


@task(name="write-release-videos", task_run_name="release-videos[{job.clip}/{job.embodiment}]", retries=2,
      retry_delay_seconds=[2.0, 10.0], retry_condition_fn=retry_transient, persist_result=False, cache_policy=NO_CACHE)
def write_release_videos(job: VideoJob) -> dict:
    return write_videos(job)
