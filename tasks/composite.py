"""composite: the rendered robot over the restored background, respecting occlusion."""

from __future__ import annotations

import zarr
from prefect import task

from handedit.reasons import combine, gate
from handedit.vision.composite import CompositeConfig, composite as composite_frames
from storage import Unit, read_chunk
from tasks._options import stage_options
from tasks.common import ChunkJob, StageOutput, execute


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    clip, emb = job.unit.clip, job.unit.embodiment
    bg = read_chunk(root, Unit("restore_background", clip, scope=job.context["scope"]), ["background", "status"], job.start, job.stop)
    ren = read_chunk(root, Unit("render", clip, embodiment=emb), ["rgba", "depth", "status"], job.start, job.stop)
    occluder = None
    if job.context.get("has_object"):
        occluder = read_chunk(root, Unit("ingest", clip), ["object_mask"], job.start, job.stop)["object_mask"]
    result = composite_frames(bg["background"], ren["rgba"], ren["depth"], occluder, None, CompositeConfig(**job.params))
    ready = gate(bg["status"], ren["status"])
    arrays = {"image": result.image, "robot_mask": result.robot_mask}
    return StageOutput(arrays, combine(result.status, ready), method=result.method)


@task(**stage_options("composite"))
def composite(job: ChunkJob) -> dict:
    return execute(job, body)
