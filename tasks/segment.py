"""segment: per-hand hand and hand-arm masks for one chunk, seeded by the registered keypoints."""

from __future__ import annotations

from handedit.camera import Intrinsics, project
from handedit.reasons import Reason, combine, combine_hands, follow_hands, gate, per_frame
from handedit.storage import Unit
from handedit.storage.layout import ArraySpec, HAND_MASK, HAND_MASK_DIMS, HAND_STATUS, STATUS
from handedit.tasks.common import ChunkJob, StageOutput
from handedit.tasks.stage import At, Inputs, Stage
from handedit.vision.arm import limbs
from handedit.vision.segment import SegmentConfig, segment as segment_frames


def _arrays(plan) -> tuple[list[str], list[str]]:
    """What it reads of ingest and of registration."""
    arm = plan.has_arm
    return (["frames", "status", *(["arm_valid"] if arm else [])],
            ["keypoints", "keypoints_valid", "hand_status", "status", *(["arm_keypoints"] if arm else [])])


def reads(at: At) -> list:
    src, reg = _arrays(at.plan)
    return [*at.each(Unit("ingest", at.plan.clip), src), *at.each(Unit("registration", at.plan.clip), reg)]


def body(inp: Inputs, job: ChunkJob) -> StageOutput:
    plan, clip = job.plan, job.unit.clip
    src_names, reg_names = _arrays(plan)
    src = inp.read(Unit("ingest", clip), src_names)
    reg = inp.read(Unit("registration", clip), reg_names)
    intr = Intrinsics(**plan.intrinsics)
    cfg = SegmentConfig(**job.params)
    ok = gate(src["status"], reg["status"])
    if plan.has_keypoints:
        present = reg["hand_status"] == Reason.OK
        # the tracked arm (wrist -> elbow -> shoulder, camera frame): its whole length, sleeves included
        arm_limbs = limbs(reg["keypoints"], reg["arm_keypoints"], src["arm_valid"]) if plan.has_arm else None
        result = segment_frames(src["frames"], project(reg["keypoints"], intr), reg["keypoints_valid"], cfg,
                                present=present, limbs=arm_limbs, intr=intr)
        hand_status = follow_hands(combine_hands(result.hand_status, ok[:, None]), reg["hand_status"])
    else:  # no keypoints at all: the hand is found by skin colour (and removed), not retargeted
        result = segment_frames(src["frames"], None, None, cfg)
        hand_status = combine_hands(result.hand_status, ok[:, None])
    arrays = {"hand_mask": result.hand_mask, "handarm_mask": result.handarm_mask, "confidence": result.confidence}
    return StageOutput(arrays, combine(per_frame(hand_status), ok), method=result.method, hand_status=hand_status)


WRITES = (
    ArraySpec("hand_mask", HAND_MASK, "bool", HAND_MASK_DIMS, image=True, fill=False),
    ArraySpec("handarm_mask", HAND_MASK, "bool", HAND_MASK_DIMS, image=True, fill=False),
    ArraySpec("confidence", ("S",), "float32", ("hand",)),
    HAND_STATUS,
    STATUS,
)
STAGE = Stage("segment", "clip", SegmentConfig, reads, body, writes=WRITES)
