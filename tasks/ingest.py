"""ingest: copy one chunk of a source clip (frames, camera, keypoints, object, GT) into the store.

The object's depth comes from the source too (its mesh and pose, rasterized once per source
frame), so every embodiment's composite reads it instead of rasterizing it again. Its input
is the source's content (its fingerprint: file digests, or a generator's seed and version),
not the spec's paths."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from handedit.sources import frame_status, open_source_json
from handedit.storage.layout import ArraySpec, MASK, MASK_DIMS, RGB, RGB_DIMS, STATUS
from handedit.sources.base import IngestConfig, on_sides
from handedit.tasks.common import ChunkJob, StageOutput
from handedit.tasks.stage import At, Inputs, Stage, Value


def reads(at: At) -> list:
    return [Value("source", at.plan.fingerprint)]


def body(inp: Inputs, job: ChunkJob) -> StageOutput:
    plan = job.plan
    source = open_source_json(plan.source_json)
    video = getattr(source, "video", None)  # video sources: what this chunk cost the decoder
    before = replace(video.stats) if video is not None else None
    chunk = source.read(job.start, job.stop)
    kp, valid = on_sides(chunk.keypoints, chunk.keypoints_valid, list(plan.source_hands), list(plan.hands))
    arrays = {"frames": chunk.frames, "world_from_camera": chunk.world_from_camera, "keypoints": kp, "keypoints_valid": valid}
    if plan.has_arm:
        arrays["arm_keypoints"], arrays["arm_valid"] = chunk.arms()
    if plan.has_object:
        arrays["object_mask"] = chunk.object_mask
        arrays["object_pose"] = chunk.object_pose
        # 0 (no surface known) where the source has no object geometry: the mask alone occludes
        arrays["object_depth"] = chunk.object_depth if chunk.object_depth is not None else np.zeros(chunk.object_mask.shape, np.float32)
    if plan.has_gt:
        arrays.update({f"gt_{k}": v for k, v in chunk.gt.items()})
    status, details = frame_status(chunk)
    extra = {"decode": video.stats.since(before)} if video is not None else {}
    return StageOutput(arrays, status, method=type(source).__name__, details=details, extra=extra)


WRITES = (
    ArraySpec("frames", RGB, "uint8", RGB_DIMS, image=True),
    ArraySpec("world_from_camera", (4, 4), "float64", ("row", "col")),
    ArraySpec("keypoints", ("S", 21, 3), "float32", ("hand", "joint", "xyz")),
    ArraySpec("keypoints_valid", ("S", 21), "bool", ("hand", "joint"), fill=False),
    ArraySpec("arm_keypoints", ("S", 3, 3), "float32", ("hand", "arm_joint", "xyz"), when="arm"),
    ArraySpec("arm_valid", ("S", 3), "bool", ("hand", "arm_joint"), when="arm", fill=False),
    ArraySpec("object_mask", MASK, "bool", MASK_DIMS, image=True, when="object", fill=False),
    ArraySpec("object_pose", (4, 4), "float64", ("row", "col"), when="object"),
    ArraySpec("object_depth", MASK, "float32", MASK_DIMS, image=True, when="object"),  # 0: no surface known
    ArraySpec("gt_hand_mask", MASK, "bool", MASK_DIMS, image=True, when="gt", fill=False),
    ArraySpec("gt_handarm_mask", MASK, "bool", MASK_DIMS, image=True, when="gt", fill=False),
    ArraySpec("gt_background", RGB, "uint8", RGB_DIMS, image=True, when="gt"),
    STATUS,
)
STAGE = Stage("ingest", "clip", IngestConfig, reads, body, writes=WRITES)
