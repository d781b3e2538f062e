"""retarget: robot joint trajectory and root pose for one chunk of hand keypoints."""

from __future__ import annotations

import zarr
from prefect import task

from handedit.reasons import combine, gate
from handedit.retarget import RetargetConfig, retarget as retarget_keypoints
from storage import Unit, open_store, read_chunk
from tasks._options import stage_options
from tasks.common import ChunkJob, StageOutput, execute


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    if job.context.get("track") == "hand_arm":
        return _hand_arm_body(root, job)
    src = read_chunk(root, Unit("ingest", job.unit.clip), ["keypoints", "keypoints_valid", "status"], job.start, job.stop)
    result = retarget_keypoints(src["keypoints"], src["keypoints_valid"], job.unit.embodiment, RetargetConfig(**job.params))
    arrays = {
        "qpos": result.qpos,
        "root_pose": result.root_pose,
        "fingertip_error_mm": result.fingertip_error_mm,
        "wrist_error_mm": result.wrist_error_mm,
    }
    return StageOutput(arrays, combine(result.status, gate(src["status"])), method="casadi:ipopt-position")


def _hand_arm_body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    """Whole-sequence hand retargeting + virtual base + arm IK; this chunk's frames are written,
    the sequence-level record (all 27 candidate scores, choice, policy) goes to provenance."""
    from handedit.retarget.hand_arm import retarget_hand_arm

    lo, hi = job.context["clip_frames"]
    src = read_chunk(root, Unit("ingest", job.unit.clip), ["keypoints", "keypoints_valid", "world_from_camera", "status"], lo, hi)
    # an operator's choice from `handedit review` (read fresh: the cached root may predate it)
    review = (open_store(job.store).attrs.get("reviews") or {}).get(f"{job.unit.clip}/{job.unit.embodiment}")
    res = retarget_hand_arm(src["keypoints"], src["keypoints_valid"], job.unit.embodiment, RetargetConfig(**job.params),
                            world_from_camera=src["world_from_camera"], choice=None if review is None else review["choice"])
    a, b = job.start - lo, job.stop - lo
    arrays = {"qpos": res.qpos[a:b], "root_pose": res.root_pose[a:b],
              "fingertip_error_mm": res.fingertip_error_mm[a:b], "wrist_error_mm": res.wrist_error_mm[a:b]}
    ready = gate(src["status"][a:b])
    details = {i - a: d for i, d in res.details.items() if a <= i < b}
    return StageOutput(arrays, combine(res.status[a:b], ready), method="casadi:ipopt-hybrid+virtual-base",
                       details=details, extra={"virtual_base": res.summary()})


@task(**stage_options("retarget"))
def retarget(job: ChunkJob) -> dict:
    return execute(job, body)
