"""registration: the chunk's hand keypoints moved onto the pixels of the hands they track."""

from __future__ import annotations

import zarr
from prefect import task

from handedit.camera import Intrinsics
from handedit.reasons import combine, combine_hands, follow_hands, gate
from handedit.vision.registration import RegistrationConfig, register as register_keypoints
from handedit.storage import Unit, read_chunk
from handedit.tasks._options import stage_options
from handedit.tasks.common import ChunkJob, StageOutput, execute


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    arm = job.context.get("has_arm", False)
    clip = job.unit.clip
    estimated = job.context.get("estimated", False)  # keypoints from estimate_hands, already on the pixels
    if estimated:
        src = read_chunk(root, Unit("ingest", clip), ["frames", "status"], job.start, job.stop)
        est = read_chunk(root, Unit("estimate_hands", clip), ["keypoints", "keypoints_valid", "hand_status", "status"],
                         job.start, job.stop)
        src.update(keypoints=est["keypoints"], keypoints_valid=est["keypoints_valid"])
    else:
        names = ["frames", "keypoints", "keypoints_valid", "status", *(["arm_keypoints", "arm_valid"] if arm else [])]
        src = read_chunk(root, Unit("ingest", clip), names, job.start, job.stop)
    r = register_keypoints(src["frames"], src["keypoints"], src["keypoints_valid"], Intrinsics(**job.context["intrinsics"]),
                           RegistrationConfig(**job.params), src.get("arm_keypoints"), exact=job.context.get("keypoints_exact", False))
    ok = gate(src["status"], est["status"]) if estimated else gate(src["status"])
    arrays = {"keypoints": r.keypoints, "keypoints_valid": r.keypoints_valid, "offset_px": r.offset_px, "scale": r.scale}
    if arm:
        arrays["arm_keypoints"] = r.arm_keypoints
    present = r.hand_status == 1
    extra = {"offset_px_mean": [float(abs(r.offset_px[:, k][present[:, k]]).mean()) if present[:, k].any() else None
                                for k in range(present.shape[1])]}
    hand_status = combine_hands(r.hand_status, ok[:, None])
    if estimated:  # a side the estimate did not see is ABSENT here, one it rejected UPSTREAM
        hand_status = follow_hands(hand_status, est["hand_status"])
    return StageOutput(arrays, combine(r.status, ok), method=r.method, extra=extra, hand_status=hand_status)


@task(**stage_options("registration"))
def registration(job: ChunkJob) -> dict:
    return execute(job, body)
