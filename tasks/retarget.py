"""retarget: robot joint trajectories and root poses of every hand in one chunk (hand-only)
or in the whole clip (hand-arm: the virtual base is fixed per sequence).

Its inputs besides the store: the robot (the content of its URDF and meshes), the source
(its object's mesh, where it has one), and, for hand-arms, the operators' review decisions
(``handedit review``) kept on the unit."""

from __future__ import annotations

import numpy as np

from handedit.camera import Intrinsics
from handedit.reasons import Reason, combine, gate, per_frame
from handedit.retarget import RetargetConfig
from handedit.retarget.qc import RetargetQCConfig
from handedit.retarget.sides import SidesResult, preview_intrinsics, retarget_hand_arm_sides, retarget_sides
from handedit.storage import Unit
from handedit.storage.layout import ArraySpec, HAND_STATUS, REVIEWS_ATTR, STATUS
from handedit.tasks.common import ChunkJob, StageOutput
from handedit.tasks.stage import At, Attr, Inputs, Stage, Value

REGISTERED = ["keypoints", "keypoints_valid", "hand_status", "status"]


def _arrays(plan, hand_arm: bool) -> tuple[list[str], list[str]]:
    """What it reads of ingest and of registration (and of segment: ``hand_status``)."""
    arm = plan.has_arm and hand_arm
    src = ["status", *(["world_from_camera"] if hand_arm else []), *(["object_pose"] if plan.has_object else []),
           *(["arm_valid"] if arm else [])]
    return src, [*REGISTERED, *(["arm_keypoints"] if arm else [])]


def reads(at: At) -> list:
    plan, hand_arm = at.plan, at.track == "hand_arm"
    src, reg = _arrays(plan, hand_arm)
    out = [*at.each(Unit("ingest", plan.clip), src), *at.each(Unit("registration", plan.clip), reg),
           *at.each(Unit("segment", plan.clip), ("hand_status",)), Value("robot", at.robot.digest)]
    if plan.has_object:  # the object's mesh comes from the source
        out.append(Value("source", plan.fingerprint))
    if hand_arm:
        out.append(Attr(at.unit, REVIEWS_ATTR))
    return out


def _inputs(inp: Inputs, job: ChunkJob) -> dict:
    plan, clip = job.plan, job.unit.clip
    src_names, reg_names = _arrays(plan, job.track == "hand_arm")
    src = inp.read(Unit("ingest", clip), src_names)
    reg = inp.read(Unit("registration", clip), reg_names)
    seg = inp.read(Unit("segment", clip), ["hand_status"])
    ok = gate(src["status"], reg["status"])
    # a hand is retargeted where it was registered and segmented
    ready = ok[:, None] & (reg["hand_status"] == Reason.OK) & (seg["hand_status"] == Reason.OK)
    return {**src, **{f"reg_{k}": v for k, v in reg.items()}, "seg_hand_status": seg["hand_status"], "ok": ok, "ready": ready}


def _object_mesh(job: ChunkJob):
    from handedit.sources import open_source_json

    return open_source_json(job.plan.source_json).object_mesh() if job.plan.has_object else None


def _method(base: str, job: ChunkJob, config: RetargetConfig) -> str:
    """The solve as provenance names it: "+contact" where the source's object mesh entered it."""
    return base + ("+contact" if job.plan.has_object and config.contact else "")


def _output(res: SidesResult, inp: dict, method: str, extra: dict) -> StageOutput:
    reg_hs = inp["reg_hand_status"]
    own = np.where(inp["ready"], res.hand_status, Reason.UPSTREAM)
    hand_status = np.where(reg_hs == Reason.ABSENT, Reason.ABSENT, own).astype(np.int16)
    arrays = {"qpos": res.qpos, "root_pose": res.root_pose, "fingertip_error_mm": res.fingertip_error_mm,
              "wrist_error_mm": res.wrist_error_mm}
    return StageOutput(arrays, combine(per_frame(hand_status), inp["ok"]), method=method, hand_status=hand_status,
                       hand_details=res.details,
                       extra={"qc_contact_checked": res.contact_checked, "qc_notes": res.notes, **extra})


def body(inp: Inputs, job: ChunkJob) -> StageOutput:
    if job.track == "hand_arm":
        return _hand_arm_body(inp, job)
    arrays = _inputs(inp, job)
    config = RetargetConfig(**job.params)
    res = retarget_sides(arrays["reg_keypoints"], arrays["reg_keypoints_valid"], arrays["ready"], job.plan.hands,
                         job.unit.embodiment, config, object_mesh=_object_mesh(job),
                         object_pose=arrays.get("object_pose"))
    return _output(res, arrays, _method("casadi:ipopt-hybrid", job, config), {})


def _hand_arm_body(inp: Inputs, job: ChunkJob) -> StageOutput:
    """Hand-arm: one node covers the whole clip (the virtual base is fixed per sequence);
    the sequence-level record (all candidate scores per side, the choice and its policy,
    the dual-arm pair) goes to provenance, the top candidates' previews (where asked for:
    ``VirtualBaseConfig.previews``) to the store."""
    from handedit.retarget.preview import top_previews

    plan = job.plan
    arrays = _inputs(inp, job)
    sides = plan.hands
    reviews = inp.attr(job.unit, REVIEWS_ATTR) or {}  # operators' choices from `handedit review`, per hand
    choices = {s: reviews[s]["choice"] for s in sides if s in reviews}
    world = plan.world
    wfc = arrays["world_from_camera"] if world else None
    intr = Intrinsics(**plan.intrinsics)
    config = RetargetConfig(**job.params)
    res = retarget_hand_arm_sides(arrays["reg_keypoints"], arrays["reg_keypoints_valid"], arrays["ready"], sides,
                                  job.unit.embodiment, config, wfc, world,
                                  arrays.get("reg_arm_keypoints"), arrays.get("arm_valid"), choices,
                                  object_mesh=_object_mesh(job), object_pose=arrays.get("object_pose"), intr=intr)
    previews = {}
    for k, side in enumerate(sides if config.virtual_base.wants_previews() else ()):
        arm_res = res.arm_results.get(k)
        if arm_res is None:
            continue
        cands, frames, ego, third = top_previews(arm_res, preview_intrinsics(intr, side),
                                                 world_from_camera=None if wfc is None else _side_world(wfc, side),
                                                 up=None if world is None else np.asarray(world["up"], float),
                                                 frames=config.virtual_base.preview_frames())
        if side == "left":  # rendered in the mirrored view: flip back
            ego, third = ego[..., ::-1, :], third[..., ::-1, :]
        previews[side] = inp.write_previews(cands, frames, ego, third, side=side)
    return _output(res, arrays, _method("casadi:ipopt-hybrid+virtual-base", job, config), {"virtual_base": res.virtual_base, "previews": previews})


def _side_world(wfc: np.ndarray, side: str) -> np.ndarray:
    from handedit.embodiments.mirror import mirror_world

    return mirror_world(wfc) if side == "left" else wfc


WRITES = (
    ArraySpec("qpos", ("S", "dof"), "float32", ("hand", "dof")),
    ArraySpec("root_pose", ("S", 4, 4), "float64", ("hand", "row", "col")),
    ArraySpec("fingertip_error_mm", ("S",), "float32", ("hand",)),
    ArraySpec("wrist_error_mm", ("S",), "float32", ("hand",)),
    HAND_STATUS,
    STATUS,
)
STAGE = Stage("retarget", "embodiment", RetargetConfig, reads, body, writes=WRITES,
              whole_clip=lambda plan, track: track == "hand_arm", uses=(RetargetQCConfig,))
