"""Thin Prefect tasks, one module per stage: read inputs, call handedit, write the chunk.

Each returns a provenance record to the flow driver. Retries live here (tasks._options);
the math lives in ``handedit``.
"""

from handedit.tasks import composite as _composite
from handedit.tasks import estimate_hands as _estimate_hands
from handedit.tasks import harmonize as _harmonize
from handedit.tasks import ingest as _ingest
from handedit.tasks import qc as _qc
from handedit.tasks import registration as _registration
from handedit.tasks import render as _render
from handedit.tasks import restore_background as _restore_background
from handedit.tasks import retarget as _retarget
from handedit.tasks import segment as _segment

_MODULES = {
    "ingest": _ingest,
    "estimate_hands": _estimate_hands,
    "registration": _registration,
    "segment": _segment,
    "restore_background": _restore_background,
    "retarget": _retarget,
    "render": _render,
    "composite": _composite,
    "harmonize": _harmonize,
    "qc": _qc,
}
# stage -> Prefect task (what the flow submits)
STAGE_TASKS = {stage: getattr(module, stage) for stage, module in _MODULES.items()}
# stage -> the task's body without Prefect (what bench/curate_overhead.py loops over)
STAGE_BODIES = {stage: module.body for stage, module in _MODULES.items()}

__all__ = ["STAGE_TASKS", "STAGE_BODIES"]
