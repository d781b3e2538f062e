"""segment: per-hand hand and hand-arm masks for one chunk, seeded by the registered keypoints."""

from __future__ import annotations

import zarr
from prefect import task

from handedit.camera import Intrinsics, project
from handedit.reasons import Reason, combine, combine_hands, follow_hands, gate, per_frame
from handedit.vision.arm import limbs
from handedit.vision.segment import SegmentConfig, segment as segment_frames
from handedit.storage import Unit, read_chunk
from handedit.tasks._options import stage_options
from handedit.tasks.common import ChunkJob, StageOutput, execute


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    clip = job.unit.clip
    arm = job.context.get("has_arm", False)
    src = read_chunk(root, Unit("ingest", clip), ["frames", "status", *(["arm_valid"] if arm else [])], job.start, job.stop)
    reg = read_chunk(root, Unit("registration", clip), ["keypoints", "keypoints_valid", "hand_status", "status",
                                                    *(["arm_keypoints"] if arm else [])], job.start, job.stop)
    intr = Intrinsics(**job.context["intrinsics"])
    cfg = SegmentConfig(**job.params)
    ok = gate(src["status"], reg["status"])
    if job.context.get("has_keypoints", True):
        present = reg["hand_status"] == Reason.OK
        # the tracked arm (wrist -> elbow -> shoulder, camera frame): its whole length, sleeves included
        arm_limbs = limbs(reg["keypoints"], reg["arm_keypoints"], src["arm_valid"]) if arm else None
        result = segment_frames(src["frames"], project(reg["keypoints"], intr), reg["keypoints_valid"], cfg,
                                present=present, limbs=arm_limbs, intr=intr)
        hand_status = follow_hands(combine_hands(result.hand_status, ok[:, None]), reg["hand_status"])
    else:  # no keypoints at all: the hand is found by skin colour (and removed), not retargeted
        result = segment_frames(src["frames"], None, None, cfg)
        hand_status = combine_hands(result.hand_status, ok[:, None])
    arrays = {"hand_mask": result.hand_mask, "handarm_mask": result.handarm_mask, "confidence": result.confidence}
    return StageOutput(arrays, combine(per_frame(hand_status), ok), method=result.method, hand_status=hand_status)


@task(**stage_options("segment"))
def segment(job: ChunkJob) -> dict:
    return execute(job, body)
