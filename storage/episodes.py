"""A curated run read as episodes: one clip x embodiment, every frame in order, with what QC
kept, the robot's joints and poses, and the key of its content.

What is kept matches a release: QC's status, less the pairs an audit rejected and the sides
whose virtual base still waits for an operator (``review: manual``). An episode's content
key hashes the digests its chunk records hold for every array the export reads (no pixel is
read to plan), with the export's own options: equal keys, equal episode.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field

import numpy as np
import zarr

from handedit.reasons import Reason
from handedit.storage.layout import Unit
from handedit.storage.ledger import unit_sides
from handedit.storage.provenance import pending_review, read_records
from handedit.storage.store import StoreError, read_array

# (unit stage, arrays) an episode reads; clip-level stages first
READS = (("ingest", ("frames",)), ("retarget", ("qpos", "root_pose", "hand_status", "status")),
         ("composite", ("robot_mask",)), ("harmonize", ("image",)), ("qc", ("status", "hand_status")))
CLIP_STAGES = ("ingest",)


def unit_of(stage: str, clip: str, embodiment: str) -> Unit:
    return Unit(stage, clip) if stage in CLIP_STAGES else Unit(stage, clip, embodiment=embodiment)


@dataclass
class Episode:
    clip: str
    embodiment: str
    sides: list[str]
    fps: float
    height: int
    width: int
    intrinsics: dict
    meta: dict
    key: str
    valid: np.ndarray  # (T,) bool: kept
    hand_ok: np.ndarray  # (T, S) bool: the side is retargeted (its joints are real)
    qpos: np.ndarray  # (T, S, dof) float32
    root_pose: np.ndarray  # (T, S, 4, 4) float64
    joint_names: list[str]
    virtual_base: dict = field(default_factory=dict)  # side -> chosen base (hand-arms)

    @property
    def n_frames(self) -> int:
        return len(self.valid)


def has_embodiment(root: zarr.Group, clip: str, embodiment: str) -> bool:
    return Unit("qc", clip, embodiment=embodiment).path in root


def content_key(root: zarr.Group, clip: str, embodiment: str, options: dict, audit: list[int]) -> str:
    digests = []
    for stage, names in READS:
        for chunk, rec in sorted(read_records(root, unit_of(stage, clip, embodiment)).items()):
            digests += [f"{stage}/{n}/{chunk}:{rec.outputs.get(n, '')}" for n in names]
    text = json.dumps({"digests": digests, "options": options, "audit_rejected": audit}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def read_episode(root: zarr.Group, clip: str, embodiment: str, options: dict, audit_rejected: set[int]) -> Episode:
    """The small arrays of one episode (joints, poses, status); frames are read when encoded."""
    info = dict(root[Unit("ingest", clip).path].attrs.get("info") or {})
    ret, qc = Unit("retarget", clip, embodiment=embodiment), Unit("qc", clip, embodiment=embodiment)
    if ret.path not in root or qc.path not in root:
        raise StoreError(f"clip {clip}: no {embodiment} retarget or qc unit; curate it with that embodiment first")
    g = root[ret.path]
    sides = unit_sides(root, qc)
    status = read_array(root[qc.path]["status"])
    hs = read_array(root[qc.path]["hand_status"]) if "hand_status" in root[qc.path] else (status[:, None] == Reason.OK)
    records = read_records(root, ret)
    held = pending_review(records)
    valid = status == Reason.OK
    for t in audit_rejected:
        valid[t] = False
    hand_kept = (hs == Reason.OK) if hs.dtype != bool else hs
    for k, side in enumerate(sides):
        if side in held:
            hand_kept[:, k] = False
    valid &= hand_kept.any(axis=1)  # a frame whose every kept side waits for review is not kept
    ret_hs = read_array(g["hand_status"])
    vb = {}
    for rec in records.values():
        for side, v in ((rec.extra or {}).get("virtual_base") or {}).items():
            vb[side] = {"camera_or_world_from_base": v.get("camera_or_world_from_base"), "chosen": v.get("chosen"),
                        "selected_by": v.get("selected_by"), "reason": v.get("reason")}
    key = content_key(root, clip, embodiment, options, sorted(audit_rejected))
    return Episode(clip, embodiment, sides, float(info.get("fps") or 30.0), int(info["height"]), int(info["width"]),
                   dict(info.get("intrinsics") or {}), dict(info.get("meta") or {}), key, valid,
                   ret_hs == Reason.OK, read_array(g["qpos"]).astype(np.float32), read_array(g["root_pose"]),
                   list(g.attrs.get("joint_names") or []), vb)


def task_text(meta: dict, instruction: str) -> str:
    """The source's own description of the task where it has one (EgoDex: the LLM description
    the annotation names), else the paper's instruction."""
    which = str(meta.get("which_llm_description") or "1")
    for key in (f"llm_description{which if which != '1' else ''}", "llm_description", "task_description"):
        text = str(meta.get(key) or "").strip()
        if text:
            return text
    return instruction


__all__ = ["Episode", "READS", "content_key", "has_embodiment", "read_episode", "task_text", "unit_of"]
