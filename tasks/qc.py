"""qc: the final keep/reject decision per frame and per hand, from every upstream status."""

from __future__ import annotations

from handedit.qc import QCConfig, final_status
from handedit.storage import Unit
from handedit.storage.layout import HAND_STATUS, STATUS, stage_layouts
from handedit.tasks.common import ChunkJob, StageOutput
from handedit.tasks.stage import At, Inputs, Stage


def upstream(clip: str, emb: str, track: str) -> list[tuple[Unit, tuple[str, ...]]]:
    """Every unit a kept pair passed through, with the statuses qc reads of it."""
    units = [Unit("ingest", clip), Unit("registration", clip), Unit("segment", clip),
             Unit("restore_background", clip, scope=track),
             *(Unit(s, clip, embodiment=emb) for s in ("retarget", "render", "composite", "harmonize"))]
    return [(u, ("status", *(("hand_status",) if stage_layouts()[u.stage].per_hand else ()))) for u in units]


def reads(at: At) -> list:
    return [a for u, names in upstream(at.plan.clip, at.unit.embodiment, at.track) for a in at.each(u, names)]


def body(inp: Inputs, job: ChunkJob) -> StageOutput:
    frames, hands = [], []
    for unit, names in upstream(job.unit.clip, job.unit.embodiment, job.track):
        got = inp.read(unit, names)
        frames.append(got["status"])
        if "hand_status" in got:
            hands.append(got["hand_status"])
    cfg = QCConfig(**job.params)
    status, hand_status = final_status(frames, hands, cfg)
    return StageOutput({}, status, method=f"status-gate:{cfg.keep}", hand_status=hand_status)


WRITES = (HAND_STATUS, STATUS)
STAGE = Stage("qc", "embodiment", QCConfig, reads, body, writes=WRITES)
