"""Final quality control: a frame is kept only if every stage produced it OK.

Each stage already applies the automatic checks of the paper's QC table to its own
output and rejects with a reason; this stage gates on all of them, so the ledger names
each cause once (at the stage that found it) and QC marks the rest ``UPSTREAM``.
"""

from __future__ import annotations

from typing import ClassVar, Sequence

import numpy as np
from pydantic import BaseModel

from handedit.reasons import Reason


class QCConfig(BaseModel):
    VERSION: ClassVar[int] = 1


def final_status(stages: Sequence[str], statuses: Sequence[np.ndarray], cfg: QCConfig) -> tuple[np.ndarray, dict[int, str]]:
    """OK where every upstream status is OK; UPSTREAM elsewhere (cause is in the ledger)."""
    stacked = np.stack([np.asarray(s) for s in statuses])
    keep = (stacked == Reason.OK).all(axis=0)
    return np.where(keep, Reason.OK, Reason.UPSTREAM).astype(np.int16), {}


def primary_cause(stages: Sequence[str], statuses: Sequence[np.ndarray]) -> list[str | None]:
    """Per frame, the first stage (in pipeline order) that rejected it, for dashboards."""
    stacked = np.stack([np.asarray(s) for s in statuses])
    out: list[str | None] = []
    for col in stacked.T:
        rejected = np.flatnonzero(col >= 100)
        out.append(stages[rejected[0]] if rejected.size else None)
    return out
