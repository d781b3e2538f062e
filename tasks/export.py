"""``encode-episode``: one episode's videos for an export (a Prefect task on Dask).

Reads the episode's frames from the curated store, each chunk re-hashed against its record
first (``storage.integrity.VerifiedReads``: changed bytes are refused, naming the file), and
encodes one MP4 per camera into the export's staging folder, which becomes the dataset only
when every episode is there (``flows.export``). Returns the image statistics of each video.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from prefect import task
from prefect.cache_policies import NO_CACHE

from handedit.export import lerobot
from handedit.export.video import VideoSpec, encode
from handedit.release.samples import union_sides
from handedit.storage import Unit
from handedit.storage.integrity import VerifiedReads
from handedit.tasks.common import open_root, retry_transient

# what each video key shows: (stage, array) of the store
CAMERAS = {lerobot.EGO: ("harmonize", "image"), lerobot.SOURCE: ("ingest", "frames")}
PAIR_VIDEOS = {"source": ("ingest", "frames"), "pseudo_gt": ("harmonize", "image"), "robot_mask": ("composite", "robot_mask")}


@dataclass(frozen=True)
class EpisodeJob:
    store: str  # the curated store's URL
    clip: str
    embodiment: str
    n_frames: int
    fps: float
    videos: tuple[tuple[str, str], ...]  # (what: a CAMERAS or PAIR_VIDEOS key, path to write)
    spec: VideoSpec = VideoSpec()
    sides: tuple[str, ...] = ()  # robot_mask: the union of these sides' masks
    frames: tuple[int, ...] | None = None  # the frames to encode (None: all)


def frames_of(reads: VerifiedReads, root, job: EpisodeJob, what: str):
    stage, name = {**CAMERAS, **PAIR_VIDEOS}[what]
    unit = Unit(stage, job.clip) if stage == "ingest" else Unit(stage, job.clip, embodiment=job.embodiment)
    sides_all = list(root[unit.path].attrs.get("hands") or []) or list(job.sides)
    for t in (range(job.n_frames) if job.frames is None else job.frames):
        img = reads.frame(unit, name, t)
        yield union_sides(img, sides_all, list(job.sides)) if name == "robot_mask" else img


def encode_episode(job: EpisodeJob) -> dict:
    """{"frames": {what: frames written}, "stats": {what: image statistics (colour videos)}}."""
    root = open_root(job.store)
    reads = VerifiedReads(root)
    out: dict = {"frames": {}, "stats": {}}
    for what, path in job.videos:
        sample = []  # every 4th pixel of every frame, for the statistics

        def tee(frames):
            for img in frames:
                if img.ndim == 3:
                    sample.append(img[::4, ::4])
                yield img
        out["frames"][what] = encode(tee(frames_of(reads, root, job, what)), Path(path), job.fps, job.spec)
        if sample:
            out["stats"][what] = lerobot.image_stats(np.stack(sample))
    return out


@task(name="encode-episode", task_run_name="encode[{job.clip}/{job.embodiment}]", retries=2,
      retry_delay_seconds=[2.0, 10.0], retry_condition_fn=retry_transient, persist_result=False, cache_policy=NO_CACHE)
def encode_episode_task(job: EpisodeJob) -> dict:
    return encode_episode(job)
