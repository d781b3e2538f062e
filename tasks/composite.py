"""composite: the rendered robot over the restored background, respecting occlusion.

Occlusion by the object: the source's object mask always; plus the object's depth
(rasterized from its mesh and per-frame pose, ``handedit.vision.object_depth``) when the
job's context names the clip's ``source`` (its mesh) and the pose is known, so the
nearer surface wins per pixel.
"""

from __future__ import annotations

import numpy as np
import zarr
from prefect import task

from handedit.camera import Intrinsics
from handedit.reasons import combine, gate
from handedit.sources import open_source_json
from handedit.vision.composite import CompositeConfig, composite as composite_frames
from handedit.vision.object_depth import object_occluder
from handedit.storage import Unit, read_chunk
from handedit.tasks._options import stage_options
from handedit.tasks.common import ChunkJob, StageOutput, execute


def _object_mesh(source_json: str | None):
    if not source_json:
        return None, None
    mesh = open_source_json(source_json).object_mesh()
    return (None, None) if mesh is None else mesh


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    clip, emb = job.unit.clip, job.unit.embodiment
    bg = read_chunk(root, Unit("restore_background", clip, scope=job.context["scope"]), ["background", "status"], job.start, job.stop)
    ren = read_chunk(root, Unit("render", clip, embodiment=emb), ["rgba", "depth", "status"], job.start, job.stop)
    occluder, occluder_depth = None, None
    if job.context.get("has_object"):
        obj = read_chunk(root, Unit("ingest", clip), ["object_mask", "object_pose"], job.start, job.stop)
        vertices, faces = _object_mesh(job.context.get("source"))
        occluder, occluder_depth = object_occluder(
            obj["object_mask"], vertices, faces, obj["object_pose"], Intrinsics(**job.context["intrinsics"])
        )
    result = composite_frames(bg["background"], ren["rgba"], ren["depth"], occluder, occluder_depth, CompositeConfig(**job.params))
    ready = gate(bg["status"], ren["status"])
    arrays = {"image": result.image, "robot_mask": result.robot_mask}
    method = result.method + ("+object-mesh-depth" if occluder_depth is not None else "")
    return StageOutput(arrays, combine(result.status, ready), method=method)


@task(**stage_options("composite"))
def composite(job: ChunkJob) -> dict:
    return execute(job, body)
