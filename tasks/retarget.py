"""retarget: robot joint trajectory and root pose for one chunk of hand keypoints."""

from __future__ import annotations

import zarr
from prefect import task

from handedit.reasons import combine, gate
from handedit.retarget import RetargetConfig, retarget as retarget_keypoints
from storage import Unit, read_chunk
from tasks._options import stage_options
from tasks.common import ChunkJob, StageOutput, execute


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    src = read_chunk(root, Unit("ingest", job.unit.clip), ["keypoints", "keypoints_valid", "status"], job.start, job.stop)
    result = retarget_keypoints(src["keypoints"], src["keypoints_valid"], job.unit.embodiment, RetargetConfig(**job.params))
    arrays = {
        "qpos": result.qpos,
        "root_pose": result.root_pose,
        "fingertip_error_mm": result.fingertip_error_mm,
        "wrist_error_mm": result.wrist_error_mm,
    }
    return StageOutput(arrays, combine(result.status, gate(src["status"])), method="casadi:ipopt-position")


@task(**stage_options("retarget"))
def retarget(job: ChunkJob) -> dict:
    return execute(job, body)
