"""Final quality control: which frames (and which hands of them) are kept.

Each stage already applies the automatic checks of the paper's QC table to its own
output and rejects with a reason; this stage gates on all of them, so the ledger names
each cause once (at the stage that found it) and QC marks the rest ``UPSTREAM``.

Bimanual frames (``keep``):
* ``all_hands`` (default): a frame is kept only if every hand in view was replaced by its
  robot; one failed hand rejects the frame, so every kept pseudo-GT shows robots only.
* ``per_hand``: a frame is kept if at least one hand was replaced; a hand that failed
  keeps its human pixels in the pseudo-GT (the composite pastes them back) and the pair
  records which hands were replaced (``hand_status`` OK), so its instruction names them.
A hand that is not in view (``ABSENT``) never blocks a frame.
"""

from __future__ import annotations

from typing import ClassVar, Literal, Sequence

import numpy as np
from pydantic import BaseModel, ConfigDict

from handedit.reasons import STATUS_DTYPE, Reason


class QCConfig(BaseModel):
    VERSION: ClassVar[int] = 2
    model_config = ConfigDict(frozen=True, extra="forbid")

    keep: Literal["all_hands", "per_hand"] = "all_hands"


def final_status(frame_statuses: Sequence[np.ndarray], hand_statuses: Sequence[np.ndarray], cfg: QCConfig,
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(status (n,), hand_status (n,S)) from every upstream stage's frame and hand statuses.

    A hand is replaced where every per-hand stage says OK; ``ABSENT`` anywhere upstream
    keeps it ``ABSENT``; everything else is ``UPSTREAM`` (the cause is in the ledger).
    """
    frames_ok = np.stack([np.asarray(s) for s in frame_statuses]).__eq__(Reason.OK).all(axis=0)
    hs = np.stack([np.asarray(h) for h in hand_statuses])  # (stages, n, S)
    absent = (hs == Reason.ABSENT).any(axis=0)
    ok = (hs == Reason.OK).all(axis=0) & frames_ok[:, None]
    failed = ~ok & ~absent
    if cfg.keep == "all_hands":
        keep = frames_ok & ok.any(axis=1) & ~failed.any(axis=1)
    else:
        keep = frames_ok & ok.any(axis=1)
    hand = np.where(absent, Reason.ABSENT, Reason.UPSTREAM).astype(STATUS_DTYPE)
    hand[ok & keep[:, None]] = Reason.OK
    return np.where(keep, Reason.OK, Reason.UPSTREAM).astype(STATUS_DTYPE), hand


def primary_cause(stages: Sequence[str], statuses: Sequence[np.ndarray]) -> list[str | None]:
    """Per frame, the first stage (in pipeline order) that rejected it, for dashboards."""
    stacked = np.stack([np.asarray(s) for s in statuses])
    out: list[str | None] = []
    for col in stacked.T:
        rejected = np.flatnonzero(col >= 100)
        out.append(stages[rejected[0]] if rejected.size else None)
    return out
