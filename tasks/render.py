"""render: the embodiment's robots (one per replaced hand) seen by the source camera."""

from __future__ import annotations

import numpy as np
import zarr
from prefect import task

from handedit.camera import Intrinsics
from handedit.reasons import Reason, combine, gate, per_frame
from handedit.render.stage import RenderConfig, render_stage
from handedit.storage import Unit, read_chunk
from handedit.tasks._options import stage_options
from handedit.tasks.common import ChunkJob, StageOutput, execute


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    emb = job.unit.embodiment
    ret = read_chunk(root, Unit("retarget", job.unit.clip, embodiment=emb), ["qpos", "root_pose", "hand_status", "status"],
                     job.start, job.stop)
    intr = Intrinsics(**job.context["intrinsics"])
    ready = gate(ret["status"])[:, None] & (ret["hand_status"] == Reason.OK)
    result = render_stage(emb, ret["qpos"], ret["root_pose"], ready, tuple(job.context["hands"]), intr, RenderConfig(**job.params))
    hand_status = np.where(ret["hand_status"] == Reason.ABSENT, Reason.ABSENT, result.hand_status).astype(np.int16)
    return StageOutput({"rgba": result.rgba, "depth": result.depth, "robot_side": result.robot_side},
                       combine(per_frame(hand_status), gate(ret["status"])), method=result.method, hand_status=hand_status)


@task(**stage_options("render"))
def render(job: ChunkJob) -> dict:
    return execute(job, body)
