"""ingest: copy one chunk of a source clip (frames, camera, keypoints, object, GT) into the store.

The object's depth comes from the source too (its mesh and pose, rasterized once per source
frame), so every embodiment's composite reads it instead of rasterizing it again."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import zarr
from prefect import task

from handedit.sources import frame_status, open_source_json
from handedit.sources.base import on_sides
from handedit.tasks._options import stage_options
from handedit.tasks.common import ChunkJob, StageOutput, execute


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    source = open_source_json(job.context["source"])
    video = getattr(source, "video", None)  # video sources: what this chunk cost the decoder
    before = replace(video.stats) if video is not None else None
    chunk = source.read(job.start, job.stop)
    kp, valid = on_sides(chunk.keypoints, chunk.keypoints_valid, job.context.get("source_hands"), job.context.get("hands"))
    arrays = {"frames": chunk.frames, "world_from_camera": chunk.world_from_camera, "keypoints": kp, "keypoints_valid": valid}
    if job.context.get("has_arm"):
        arrays["arm_keypoints"], arrays["arm_valid"] = chunk.arms()
    if job.context.get("has_object"):
        arrays["object_mask"] = chunk.object_mask
        arrays["object_pose"] = chunk.object_pose
        # 0 (no surface known) where the source has no object geometry: the mask alone occludes
        arrays["object_depth"] = chunk.object_depth if chunk.object_depth is not None else np.zeros(chunk.object_mask.shape, np.float32)
    if job.context.get("has_gt"):
        arrays.update({f"gt_{k}": v for k, v in chunk.gt.items()})
    status, details = frame_status(chunk)
    extra = {"decode": video.stats.since(before)} if video is not None else {}
    return StageOutput(arrays, status, method=type(source).__name__, details=details, extra=extra)


@task(**stage_options("ingest"))
def ingest(job: ChunkJob) -> dict:
    return execute(job, body)
