"""render: the embodiment's robots (one per replaced hand) seen by the source camera."""

from __future__ import annotations

import numpy as np

from handedit.camera import Intrinsics
from handedit.reasons import Reason, combine, gate, per_frame
from handedit.render.stage import RenderConfig, render_stage
from handedit.storage import Unit
from handedit.storage.layout import ArraySpec, HAND_STATUS, MASK, MASK_DIMS, STATUS
from handedit.tasks.common import ChunkJob, StageOutput
from handedit.tasks.stage import At, Inputs, Stage, Value

RETARGETED = ("qpos", "root_pose", "hand_status", "status")


def reads(at: At) -> list:
    return [*at.each(Unit("retarget", at.plan.clip, embodiment=at.unit.embodiment), RETARGETED),
            Value("robot", at.robot.digest)]


def body(inp: Inputs, job: ChunkJob) -> StageOutput:
    emb = job.unit.embodiment
    ret = inp.read(Unit("retarget", job.unit.clip, embodiment=emb), RETARGETED)
    intr = Intrinsics(**job.plan.intrinsics)
    ready = gate(ret["status"])[:, None] & (ret["hand_status"] == Reason.OK)
    result = render_stage(emb, ret["qpos"], ret["root_pose"], ready, job.plan.hands, intr, RenderConfig(**job.params))
    hand_status = np.where(ret["hand_status"] == Reason.ABSENT, Reason.ABSENT, result.hand_status).astype(np.int16)
    return StageOutput({"rgba": result.rgba, "depth": result.depth, "robot_side": result.robot_side,
                        "robot_arm": result.robot_arm},
                       combine(per_frame(hand_status), gate(ret["status"])), method=result.method, hand_status=hand_status)


WRITES = (
    ArraySpec("rgba", ("H", "W", 4), "uint8", ("y", "x", "rgba"), image=True),
    ArraySpec("depth", MASK, "float32", MASK_DIMS, image=True),
    ArraySpec("robot_side", MASK, "uint8", MASK_DIMS, image=True),  # 0: no robot, k+1: hand k's robot
    ArraySpec("robot_arm", MASK, "bool", MASK_DIMS, image=True, fill=False),  # the surface seen is an arm link
    HAND_STATUS,
    STATUS,
)
STAGE = Stage("render", "embodiment", RenderConfig, reads, body, writes=WRITES)
