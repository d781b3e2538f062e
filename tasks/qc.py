"""qc: the final keep/reject decision per frame, from every upstream stage's status."""

from __future__ import annotations

import zarr
from prefect import task

from handedit.qc import QCConfig, final_status
from handedit.tasks._options import stage_options
from handedit.tasks.common import ChunkJob, StageOutput, execute
from handedit.storage import Unit, read_chunk


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    units = [Unit(**u) for u in job.context["upstream"]]
    statuses = [read_chunk(root, u, ["status"], job.start, job.stop)["status"] for u in units]
    status, details = final_status([u.stage for u in units], statuses, QCConfig(**job.params))
    return StageOutput({}, status, method="status-gate", details=details)


@task(**stage_options("qc"))
def qc(job: ChunkJob) -> dict:
    return execute(job, body)
