"""estimate_hands: both sides' 3-D keypoints from the pixels, for a clip without any.

One node covers the whole clip (tracking and each track's side run over the sequence); it
reads the ingested frames chunk by chunk, so a clip is never held in memory.
"""

from __future__ import annotations

import numpy as np

from handedit.camera import Intrinsics
from handedit.reasons import combine_hands, gate, per_frame
from handedit.storage import Unit
from handedit.storage.layout import ArraySpec, HAND_STATUS, STATUS
from handedit.tasks.common import ChunkJob, StageOutput
from handedit.tasks.stage import At, Inputs, Stage
from handedit.vision import estimate_hands as domain


def reads(at: At) -> list:
    return at.each(Unit("ingest", at.plan.clip), ("frames", "status"))


def body(inp: Inputs, job: ChunkJob) -> StageOutput:
    ingest = Unit("ingest", job.unit.clip)
    status = np.concatenate([inp.read(ingest, ["status"], s, e)["status"] for s, e in inp.ranges])
    frames = (f for s, e in inp.ranges for f in inp.read(ingest, ["frames"], s, e)["frames"])
    cfg = domain.EstimateHandsConfig(**job.params)
    intr = Intrinsics(**job.plan.intrinsics)
    lifter = None
    if cfg.model_path is not None:
        from handedit.models.hand_pose import HandPoseLifter

        lifter = HandPoseLifter(cfg.model_path, intr, cfg.onnx)
    est = domain.estimate_hands(frames, job.n, intr, job.plan.fps, cfg, lifter=lifter)
    ok = gate(status)
    hand_status = combine_hands(est.hand_status, np.repeat(ok[:, None], est.hand_status.shape[1], 1))
    arrays = {"keypoints": est.keypoints, "keypoints_raw": est.keypoints_raw, "keypoints_valid": est.keypoints_valid & ok[:, None, None],
              "confidence": est.confidence, "box": est.box, "p_right": est.p_right, "reprojection_px": est.reprojection_px}
    method = est.method + (f"+{lifter.tag}" if lifter is not None else "")
    extra = {**est.stats, "intrinsics": intr.to_dict(), "intrinsics_origin": job.plan.intrinsics_origin}
    return StageOutput(arrays, per_frame(hand_status), method=method, extra=extra, hand_status=hand_status,
                       hand_details=est.details)


WRITES = (
    ArraySpec("keypoints", ("S", 21, 3), "float32", ("hand", "joint", "xyz")),
    ArraySpec("keypoints_raw", ("S", 21, 3), "float32", ("hand", "joint", "xyz")),
    ArraySpec("keypoints_valid", ("S", 21), "bool", ("hand", "joint"), fill=False),
    ArraySpec("confidence", ("S", 21), "float32", ("hand", "joint")),
    ArraySpec("box", ("S", 4), "float32", ("hand", "xyxy")),
    ArraySpec("p_right", ("S",), "float32", ("hand",)),
    ArraySpec("reprojection_px", ("S",), "float32", ("hand",)),
    HAND_STATUS,
    STATUS,
)
STAGE = Stage("estimate_hands", "clip", domain.EstimateHandsConfig, reads, body, writes=WRITES,
              whole_clip=lambda plan, track: True, applies=lambda plan: plan.estimate_hands)
