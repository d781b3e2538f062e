"""render: the embodiment at its retargeted joint states, seen by the source camera."""

from __future__ import annotations

import numpy as np
import zarr
from prefect import task

from handedit.camera import Intrinsics
from handedit.reasons import Reason, combine, gate
from handedit.render.stage import RenderConfig, render_stage
from handedit.storage import Unit, read_chunk
from handedit.tasks._options import stage_options
from handedit.tasks.common import ChunkJob, StageOutput, execute


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    emb = job.unit.embodiment
    ret = read_chunk(root, Unit("retarget", job.unit.clip, embodiment=emb), ["qpos", "root_pose", "status"], job.start, job.stop)
    intr = Intrinsics(**job.context["intrinsics"])
    ready = gate(ret["status"])
    rgba = np.zeros((job.n, intr.height, intr.width, 4), np.uint8)
    depth = np.zeros((job.n, intr.height, intr.width), np.float32)
    own = np.full(job.n, int(Reason.UPSTREAM), np.int16)
    method = ""
    if ready.any():
        result = render_stage(emb, ret["qpos"][ready], ret["root_pose"][ready], intr, RenderConfig(**job.params))
        rgba[ready], depth[ready], own[ready], method = result.rgba, result.depth, result.status, result.method
    return StageOutput({"rgba": rgba, "depth": depth}, combine(own, ready), method=method)


@task(**stage_options("render"))
def render(job: ChunkJob) -> dict:
    return execute(job, body)
