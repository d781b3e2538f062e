"""harmonize: match the robot's colour and illumination to its surroundings."""

from __future__ import annotations

from handedit.reasons import combine, gate
from handedit.storage import Unit, writable
from handedit.storage.layout import ArraySpec, RGB, RGB_DIMS, STATUS
from handedit.tasks.common import ChunkJob, StageOutput
from handedit.tasks.stage import At, Inputs, Stage
from handedit.vision.harmonize import HarmonizeConfig, harmonize as harmonize_frames

COMPOSITED = ("image", "robot_mask", "status")


def reads(at: At) -> list:
    return at.each(Unit("composite", at.plan.clip, embodiment=at.unit.embodiment), COMPOSITED)


def body(inp: Inputs, job: ChunkJob) -> StageOutput:
    comp = inp.read(Unit("composite", job.unit.clip, embodiment=job.unit.embodiment), COMPOSITED)
    result = harmonize_frames(comp["image"], comp["robot_mask"].any(axis=1), HarmonizeConfig(**job.params),
                              out=writable(comp["image"]))  # read for this chunk only: harmonized in place
    return StageOutput({"image": result.image}, combine(result.status, gate(comp["status"])), method=result.method)


WRITES = (
    ArraySpec("image", RGB, "uint8", RGB_DIMS, image=True),
    STATUS,
)
STAGE = Stage("harmonize", "embodiment", HarmonizeConfig, reads, body, writes=WRITES)
