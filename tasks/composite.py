"""composite: the rendered robots over the restored background, respecting occlusion.

Occlusion by the object: the source's object mask always; plus the object's depth where
the source knows its geometry (ingest stored it, once per source frame: its mesh and
pose rasterized, ``handedit.vision.object_depth``), so the nearer surface wins per pixel.
A source without either (EgoDex, a video): what hid the human fingers, from the registered
keypoints and the hand masks (``handedit.vision.occluder``), stays in front of the robot.
Hands whose robot is not drawn get their source pixels back; replaced hands are checked
for visible human residue (beside the robot: HUMAN_VISIBLE; in the restored background where
no robot covers it: RESIDUE), and hand-arm robots for lying where the human arm was (OFF_ARM) and for an arm link hiding
the robot's hand where the human hand was seen (HAND_HIDDEN).
"""

from __future__ import annotations

import numpy as np

from handedit.camera import Intrinsics, project
from handedit.reasons import Reason, combine, gate, per_frame
from handedit.storage import Unit, writable
from handedit.storage.layout import ArraySpec, HAND_MASK, HAND_MASK_DIMS, HAND_STATUS, RGB, RGB_DIMS, SCOPE_MASK, STATUS
from handedit.tasks.common import ChunkJob, StageOutput
from handedit.tasks.stage import At, Inputs, Stage
from handedit.vision.arm import hand_hidden_shares, limbs, off_arm_shares, screen_status
from handedit.vision.composite import CompositeConfig, composite as composite_frames, robot_windows
from handedit.vision.object_depth import object_occluder
from handedit.vision.occluder import hidden_fingers

RESTORED = ("background", "hole", "status")
RENDERED = ("rgba", "depth", "robot_side", "hand_status", "status")


def _arrays(plan, track: str) -> tuple[list[str], list[str]]:
    """What it reads of ingest and of registration; the tracked arm widens the off-arm corridor."""
    arm = track == "hand_arm" and plan.has_arm
    src = ["frames", *(["arm_valid"] if arm else []), *(["object_mask", "object_depth"] if plan.has_object else [])]
    return src, ["keypoints", "keypoints_valid", *(["arm_keypoints"] if arm else [])]


def _parts(track: str) -> tuple[list[str], list[str]]:
    """What it reads of render and of segment: a hand-arm's arm pixels over the hands (HAND_HIDDEN)."""
    arm = track == "hand_arm"
    return [*RENDERED, *(["robot_arm"] if arm else [])], [SCOPE_MASK[track], "hand_status", *(["hand_mask"] if arm else [])]


def reads(at: At) -> list:
    clip, emb, track = at.plan.clip, at.unit.embodiment, at.track
    src, reg = _arrays(at.plan, track)
    ren, seg = _parts(track)
    return [*at.each(Unit("restore_background", clip, scope=track), RESTORED),
            *at.each(Unit("render", clip, embodiment=emb), ren),
            *at.each(Unit("segment", clip), seg),
            *at.each(Unit("ingest", clip), src), *at.each(Unit("registration", clip), reg)]


def body(inp: Inputs, job: ChunkJob) -> StageOutput:
    plan, clip, emb, scope = job.plan, job.unit.clip, job.unit.embodiment, job.track
    src_names, reg_names = _arrays(plan, scope)
    bg = inp.read(Unit("restore_background", clip, scope=scope), RESTORED)
    ren_names, seg_names = _parts(scope)
    ren = inp.read(Unit("render", clip, embodiment=emb), [n for n in ren_names if n != "depth"])
    seg = inp.read(Unit("segment", clip), seg_names)
    reg = inp.read(Unit("registration", clip), reg_names)
    src = inp.read(Unit("ingest", clip), src_names)
    intr = Intrinsics(**plan.intrinsics)
    cfg = CompositeConfig(**job.params)
    windows = robot_windows(ren["rgba"], cfg)
    occluder, occluder_depth, occluder_tag = None, None, ""
    if plan.has_object:
        occluder, occluder_depth = object_occluder(src["object_mask"], src["object_depth"])
        occluder_tag = "+object-mesh-depth" if occluder_depth is not None else ""
    elif cfg.image_occluder is not None and plan.has_keypoints:  # in front of the fingers, so in front of the robot
        occluder = hidden_fingers(reg["keypoints"], reg["keypoints_valid"], seg[SCOPE_MASK[scope]], intr, cfg.image_occluder,
                                  frames=src["frames"])
        cfg, occluder_tag = cfg.model_copy(update={"occluder_in_front_without_depth": True}), "+occluder-from-hidden-fingers"
    robot_depth = None if occluder_depth is None else inp.read(Unit("render", clip, embodiment=emb), ["depth"])["depth"]
    ready = gate(bg["status"], ren["status"])
    replace = ready[:, None] & (ren["hand_status"] == Reason.OK)
    result = composite_frames(bg["background"], ren["rgba"], robot_depth, occluder, occluder_depth, cfg,
                              robot_side=ren["robot_side"], replace=replace, source=src["frames"], human_mask=seg[SCOPE_MASK[scope]],
                              keypoints_2d=project(reg["keypoints"], intr), keypoints_valid=reg["keypoints_valid"], windows=windows,
                              out=writable(bg["background"]), hole=bg["hole"])  # read for this chunk only: composited in place
    own = result.hand_status
    extra = {"residue_max": _side_max(result.residue), "restore_residue_frames": int(result.restored_residue.sum())}
    if scope == "hand_arm":  # base plausibility: the robot arm where the human arm was
        limbs_3d = limbs(reg["keypoints"], reg["arm_keypoints"], src["arm_valid"]) if "arm_keypoints" in reg else None
        checked = replace & (own == Reason.OK)
        off = off_arm_shares(result.robot_mask, seg[SCOPE_MASK[scope]], limbs_3d, intr, checked, cfg.arm_corridor_frac)
        own = screen_status(own, checked, off, cfg.max_off_arm, Reason.OFF_ARM)
        extra["off_arm_max"] = _side_max(off)
        checked = replace & (own == Reason.OK)  # the robot's hand is seen where the human hand was
        hidden = hand_hidden_shares(ren["robot_arm"] & result.union, seg["hand_mask"], checked)
        own = screen_status(own, checked, hidden, cfg.max_hand_hidden, Reason.HAND_HIDDEN)
        extra["hand_hidden_max"] = _side_max(hidden)
    upstream = ren["hand_status"]
    hand_status = np.where(replace, own,
                           np.where(upstream == Reason.ABSENT, Reason.ABSENT, Reason.UPSTREAM)).astype(np.int16)
    method = result.method + occluder_tag
    return StageOutput({"image": result.image, "robot_mask": result.robot_mask}, combine(per_frame(hand_status), ready),
                       method=method, hand_status=hand_status, extra=extra)


def _side_max(values: np.ndarray) -> list[float | None]:
    """Per side, the largest measured value of the chunk (None: not measured), for provenance."""
    return [float(np.nanmax(v)) if np.isfinite(v).any() else None for v in np.asarray(values).T]


WRITES = (
    ArraySpec("image", RGB, "uint8", RGB_DIMS, image=True),
    ArraySpec("robot_mask", HAND_MASK, "bool", HAND_MASK_DIMS, image=True, fill=False),
    HAND_STATUS,
    STATUS,
)
STAGE = Stage("composite", "embodiment", CompositeConfig, reads, body, writes=WRITES)
