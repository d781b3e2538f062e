"""registration: the chunk's hand keypoints moved onto the pixels of the hands they track."""

from __future__ import annotations

from handedit.camera import Intrinsics
from handedit.reasons import combine, combine_hands, follow_hands, gate
from handedit.storage import Unit
from handedit.storage.layout import ArraySpec, HAND_STATUS, STATUS
from handedit.tasks.common import ChunkJob, StageOutput
from handedit.tasks.stage import At, Inputs, Stage
from handedit.vision.registration import RegistrationConfig, register as register_keypoints

ESTIMATED = ("keypoints", "keypoints_valid", "hand_status", "status")


def _source_arrays(plan) -> list[str]:
    if plan.estimate_hands:  # the keypoints come from estimate_hands, already on the pixels
        return ["frames", "status"]
    return ["frames", "keypoints", "keypoints_valid", "status", *(["arm_keypoints", "arm_valid"] if plan.has_arm else [])]


def reads(at: At) -> list:
    clip = at.plan.clip
    out = at.each(Unit("ingest", clip), _source_arrays(at.plan))
    if at.plan.estimate_hands:
        out += at.each(Unit("estimate_hands", clip), ESTIMATED)
    return out


def body(inp: Inputs, job: ChunkJob) -> StageOutput:
    plan, clip = job.plan, job.unit.clip
    src = inp.read(Unit("ingest", clip), _source_arrays(plan))
    if plan.estimate_hands:
        est = inp.read(Unit("estimate_hands", clip), ESTIMATED)
        src.update(keypoints=est["keypoints"], keypoints_valid=est["keypoints_valid"])
    r = register_keypoints(src["frames"], src["keypoints"], src["keypoints_valid"], Intrinsics(**plan.intrinsics),
                           RegistrationConfig(**job.params), src.get("arm_keypoints"), exact=plan.keypoints_exact)
    ok = gate(src["status"], est["status"]) if plan.estimate_hands else gate(src["status"])
    arrays = {"keypoints": r.keypoints, "keypoints_valid": r.keypoints_valid, "offset_px": r.offset_px, "scale": r.scale}
    if plan.has_arm:
        arrays["arm_keypoints"] = r.arm_keypoints
    present = r.hand_status == 1
    extra = {"offset_px_mean": [float(abs(r.offset_px[:, k][present[:, k]]).mean()) if present[:, k].any() else None
                                for k in range(present.shape[1])]}
    hand_status = combine_hands(r.hand_status, ok[:, None])
    if plan.estimate_hands:  # a side the estimate did not see is ABSENT here, one it rejected UPSTREAM
        hand_status = follow_hands(hand_status, est["hand_status"])
    return StageOutput(arrays, combine(r.status, ok), method=r.method, extra=extra, hand_status=hand_status)


WRITES = (
    ArraySpec("keypoints", ("S", 21, 3), "float32", ("hand", "joint", "xyz")),
    ArraySpec("keypoints_valid", ("S", 21), "bool", ("hand", "joint"), fill=False),
    ArraySpec("arm_keypoints", ("S", 3, 3), "float32", ("hand", "arm_joint", "xyz"), when="arm"),
    ArraySpec("offset_px", ("S", 2), "float32", ("hand", "uv")),
    ArraySpec("scale", ("S",), "float32", ("hand",), fill=1.0),
    HAND_STATUS,
    STATUS,
)
STAGE = Stage("registration", "clip", RegistrationConfig, reads, body, writes=WRITES)
