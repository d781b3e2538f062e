"""harmonize: match the robot's colour and illumination to its surroundings."""

from __future__ import annotations

import zarr
from prefect import task

from handedit.reasons import combine, gate
from handedit.vision.harmonize import HarmonizeConfig, harmonize as harmonize_frames
from handedit.storage import Unit, read_chunk, writable
from handedit.tasks._options import stage_options
from handedit.tasks.common import ChunkJob, StageOutput, execute


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    comp = read_chunk(root, Unit("composite", job.unit.clip, embodiment=job.unit.embodiment), ["image", "robot_mask", "status"], job.start, job.stop)
    result = harmonize_frames(comp["image"], comp["robot_mask"].any(axis=1), HarmonizeConfig(**job.params),
                              out=writable(comp["image"]))  # read for this chunk only: harmonized in place
    return StageOutput({"image": result.image}, combine(result.status, gate(comp["status"])), method=result.method)


@task(**stage_options("harmonize"))
def harmonize(job: ChunkJob) -> dict:
    return execute(job, body)
