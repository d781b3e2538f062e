"""segment: hand and hand-arm masks for one chunk, seeded by the projected keypoints."""

from __future__ import annotations

import zarr
from prefect import task

from handedit.camera import Intrinsics, project
from handedit.reasons import combine, gate
from handedit.vision.segment import SegmentConfig, segment as segment_frames
from handedit.storage import Unit, read_chunk
from handedit.tasks._options import stage_options
from handedit.tasks.common import ChunkJob, StageOutput, execute


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    src = read_chunk(root, Unit("ingest", job.unit.clip), ["frames", "keypoints", "keypoints_valid", "status"], job.start, job.stop)
    intr = Intrinsics(**job.context["intrinsics"])
    result = segment_frames(src["frames"], project(src["keypoints"], intr), src["keypoints_valid"], SegmentConfig(**job.params))
    arrays = {"hand_mask": result.hand_mask, "handarm_mask": result.handarm_mask, "confidence": result.confidence}
    return StageOutput(arrays, combine(result.status, gate(src["status"])), method=result.method)


@task(**stage_options("segment"))
def segment(job: ChunkJob) -> dict:
    return execute(job, body)
