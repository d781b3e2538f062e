"""qc: the final keep/reject decision per frame and per hand, from every upstream status."""

from __future__ import annotations

import zarr
from prefect import task

from handedit.qc import QCConfig, final_status
from handedit.storage import Unit, read_chunk
from handedit.storage.layout import PER_HAND_STAGES
from handedit.tasks._options import stage_options
from handedit.tasks.common import ChunkJob, StageOutput, execute


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    units = [Unit(**u) for u in job.context["upstream"]]
    frames, hands = [], []
    for u in units:
        per_hand = u.stage in PER_HAND_STAGES
        got = read_chunk(root, u, ["status", *(["hand_status"] if per_hand else [])], job.start, job.stop)
        frames.append(got["status"])
        if per_hand:
            hands.append(got["hand_status"])
    status, hand_status = final_status(frames, hands, QCConfig(**job.params))
    return StageOutput({}, status, method=f"status-gate:{QCConfig(**job.params).keep}", hand_status=hand_status)


@task(**stage_options("qc"))
def qc(job: ChunkJob) -> dict:
    return execute(job, body)
