"""Hand-arm retargeting of a whole sequence: hand retargeting, virtual base, arm IK.

1. the hand (fingers + 6-DoF wrist) is retargeted as for the hand-only track;
2. its wrist link poses are the arm's IK targets (the fixed per-embodiment human-wrist ->
   robot-wrist SE(3) of ``handedit.retarget.arm``);
3. the virtual base is searched once for the sequence (``virtual_base``) and the chosen
   candidate's IK trajectory becomes the arm joints; finger joints come from step 1.

Reference frame: when the source gives camera poses in a world (``ClipInfo.world``: its up
direction and, where known, its support plane, e.g. the synthetic table's z = 0), the base
is fixed in that world, upright along its up, and the support-plane check runs where the
plane is known; without a world (identity camera poses) the base is fixed in the camera
frame, "up" is image up and the support-plane check is recorded as not possible. Shoulder
keypoints (EgoDex tracks them) initialise the search (the paper's first branch).

Outputs follow the composed URDF: qpos columns in its joint order, ``root_pose`` is
camera_from_base per frame. The curate flow runs this once per (clip, embodiment): the
hand-arm retarget unit is sequence-level (one node per clip: ``tasks/retarget.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from handedit.camera import Intrinsics, project
from handedit.reasons import STATUS_DTYPE, Reason
from handedit.retarget.api import RetargetResult, retarget
from handedit.retarget.arm import arm_model
from handedit.retarget.config import RetargetConfig
from handedit.retarget.plausibility import BaseView
from handedit.retarget.virtual_base import VirtualBaseConfig, VirtualBaseResult, search_virtual_base, virtual_shoulders


@dataclass
class HandArmResult:
    qpos: np.ndarray  # (T,dof) composed joint order
    root_pose: np.ndarray  # (T,4,4) camera_from_base
    fingertip_error_mm: np.ndarray
    wrist_error_mm: np.ndarray
    status: np.ndarray  # (T,) int16
    details: dict[int, str]
    virtual_base: VirtualBaseResult
    joint_names: list[str]
    notes: list[str] = field(default_factory=list)
    hand: "RetargetResult | None" = None  # the hand-only result the arm follows (for QC)

    def summary(self) -> dict:
        """JSON-safe sequence-level record: every candidate's scores (27, 54 after a refinement), ranking,
        choice, policy, diagnosis."""
        vb = self.virtual_base
        return {"embodiment": vb.embodiment_id, "reach_m": vb.reach_m, "chosen": vb.chosen, "selected_by": vb.selected_by,
                "ranking": vb.ranking, "reason": int(vb.reason), "detail": vb.detail, "notes": self.notes,
                "diagnosis": vb.diagnosis,
                "camera_or_world_from_base": None if vb.camera_from_base is None else np.round(vb.camera_from_base, 6).tolist(),
                "candidates": vb.scores_json()}


def known_world(world: dict | None, world_from_camera: np.ndarray | None) -> bool:
    return world is not None and world_from_camera is not None


def retarget_hand_arm(keypoints: np.ndarray, keypoints_valid: np.ndarray, embodiment_id: str, cfg: RetargetConfig,
                      vb_cfg: VirtualBaseConfig | None = None, world_from_camera: np.ndarray | None = None,
                      choice: int | None = None, world: dict | None = None,
                      shoulders: np.ndarray | None = None, view: BaseView | None = None,
                      object_mesh: tuple[np.ndarray, np.ndarray] | None = None,
                      object_pose: np.ndarray | None = None) -> HandArmResult:
    """Whole-sequence hand-arm retargeting (see module doc). ``choice``: an operator's
    candidate index (``handedit review``), -1 to drop the sequence, None for the policy.
    ``world``: ``ClipInfo.world`` (None: no world frame); ``shoulders`` (2,3): the
    (left, right) shoulder joints in the camera frame of the first frame, or None;
    ``view``: the camera and the human arm, for plausibility ranking and critical frames;
    ``object_mesh``/``object_pose``: the hand's contact terms (``api.retarget``)."""
    kp = np.ascontiguousarray(keypoints, dtype=np.float32)
    va = np.ascontiguousarray(keypoints_valid, dtype=bool)
    wfc = None if world_from_camera is None else np.ascontiguousarray(world_from_camera, dtype=np.float64)
    return _solve(embodiment_id, cfg, vb_cfg or cfg.virtual_base, choice, kp, va, wfc, world, shoulders, view,
                  object_mesh, object_pose)


def critical_frames(kp: np.ndarray, va: np.ndarray, ok: np.ndarray, intr: Intrinsics | None) -> np.ndarray:
    """The frames a base must reach: the hand retargeted and, with a camera, in view (a tracked
    keypoint inside the image: the wrist itself is often below the frame's edge)."""
    crit = np.asarray(ok, bool)
    if intr is not None:
        uv = project(np.asarray(kp, float), intr)
        inside = np.isfinite(uv).all(-1) & (uv[..., 0] >= 0) & (uv[..., 0] < intr.width) & (uv[..., 1] >= 0) \
            & (uv[..., 1] < intr.height)
        crit &= (inside & np.asarray(va, bool)).any(axis=1)
    return crit


def _solve(embodiment_id: str, cfg: RetargetConfig, vb_cfg: VirtualBaseConfig, choice,
           kp, va, wfc, world_desc: dict | None = None, shoulders: np.ndarray | None = None,
           view: BaseView | None = None, object_mesh=None, object_pose=None) -> HandArmResult:
    arm = arm_model(embodiment_id)
    n = len(kp)
    hand = retarget(kp, va, arm.hand_id, cfg, object_mesh=object_mesh, object_pose=object_pose)
    ok = hand.status == Reason.OK
    targets = arm.wrist_targets(hand.root_pose, hand.qpos.astype(float))
    notes: list[str] = []
    world = known_world(world_desc, wfc)
    if world:
        targets = np.einsum("tij,tjk->tik", wfc, targets)
        up = np.asarray(world_desc["up"], float)
        plane = None if world_desc.get("support_plane") is None else np.asarray(world_desc["support_plane"], float)
        if shoulders is not None:
            shoulders = np.asarray(shoulders, float) @ wfc[0][:3, :3].T + wfc[0][:3, 3]
        if plane is None:
            notes.append("support-plane check not possible: the source's world has no support plane")
    else:
        up, plane = np.array([0.0, -1.0, 0.0]), None
        notes.append("support-plane check not possible: the source gives no world frame; base fixed in the camera frame")
    cameras = wfc if world else np.tile(np.eye(4), (n, 1, 1))
    if shoulders is not None:
        notes.append("base initialised from the shoulders")
    elif ok.any():
        shoulders = virtual_shoulders(cameras[int(np.flatnonzero(ok)[0])], up, vb_cfg)
        notes.append("base initialised from shoulders placed under the head camera (the source does not track them)")
    critical = critical_frames(kp, va, ok, None if view is None else view.intr)
    vb = search_virtual_base(targets, ok, embodiment_id, vb_cfg, up=up, support_plane=plane, shoulders=shoulders,
                             cameras=cameras, critical=critical, view=view)
    if vb.diagnosis.get("refined"):
        notes.append(f"{vb.diagnosis['refined_for']} among the paper's 27 candidates; refined around a base "
                     f"{vb_cfg.refine_reach_frac} L_r from the wrist targets (they were "
                     f"{vb.diagnosis['target_distance_Lr']} L_r away)")
    if choice is not None and vb.reason == Reason.OK:
        try:
            vb = apply_review(vb, choice, arm)
        except ValueError as e:  # a stale decision (inputs changed since): keep the policy's choice
            notes.append(f"review ignored: {e}")
    status = np.asarray(hand.status, STATUS_DTYPE).copy()
    details: dict[int, str] = {}
    names = arm.kin.joint_names
    if vb.chosen is None:
        code = Reason.REVIEW_DROPPED if vb.selected_by.startswith("review:drop") else Reason.NO_VALID_BASE
        status[ok] = code
        for i in np.flatnonzero(ok):
            details[int(i)] = vb.detail
        qpos = np.tile(arm.q_fixed, (n, 1))
        base = np.eye(4)
    else:
        arm_q = vb.arm_tracks[vb.chosen]
        qpos = arm.assembly_qpos(arm_q, hand.qpos.astype(float), hand.joint_names)
        base = vb.candidates[vb.chosen].camera_from_base
        status, details = with_base(hand.status, vb, vb.chosen)
    if world:
        root = np.einsum("tij,jk->tik", np.linalg.inv(wfc), base)
    else:
        root = np.tile(base, (n, 1, 1))
    return HandArmResult(qpos.astype(np.float32), root, hand.fingertip_error_mm, hand.wrist_error_mm, status, details,
                         vb, list(names), notes, hand)


def with_base(hand_status: np.ndarray, vb: VirtualBaseResult, chosen: int) -> tuple[np.ndarray, dict[int, str]]:
    """A sequence's status with base ``chosen``: the hand's own rejections, then the frames
    where that base fails (with a detail naming it)."""
    status = np.asarray(hand_status, STATUS_DTYPE).copy()
    st = vb.frame_status[chosen]
    bad = (status == Reason.OK) & (st != Reason.OK)
    status[bad] = st[bad]
    return status, {int(i): f"{Reason(int(st[i])).name.lower().replace('_', ' ')} with base {chosen}"
                    for i in np.flatnonzero(bad)}


def merge_hand_qc(res: HandArmResult, qc) -> tuple[np.ndarray, dict[int, str]]:
    """Status of a hand-arm sequence with the hand's own QC (contact, penetration) folded
    in: a hand rejection comes first where the arm solution was otherwise OK."""
    status = res.status.copy()
    details = dict(res.details)
    hand_bad = (qc.status != res.hand.status) & (status == Reason.OK)
    status[hand_bad] = qc.status[hand_bad]
    details.update({int(i): qc.details[int(i)] for i in np.flatnonzero(hand_bad) if int(i) in qc.details})
    return status, details


def apply_review(vb: VirtualBaseResult, choice: int, arm=None) -> VirtualBaseResult:
    """An operator's sequence-level decision: a top-3 candidate index, or -1 to drop."""
    import dataclasses

    if choice == -1:
        return dataclasses.replace(vb, chosen=None, selected_by="review:drop", reason=int(Reason.REVIEW_DROPPED),
                                   detail="dropped at review: no plausible candidate", camera_from_base=None,
                                   arm_q=None, qpos=None)
    if choice not in vb.ranking[:3]:
        raise ValueError(f"candidate {choice} is not among the top-3 valid candidates {vb.ranking[:3]}")
    arm = arm or arm_model(vb.embodiment_id)
    arm_q = vb.arm_tracks[choice]
    return dataclasses.replace(vb, chosen=choice, selected_by=f"review:{choice}",
                               camera_from_base=vb.candidates[choice].camera_from_base, arm_q=arm_q,
                               qpos=np.stack([arm.full_q(q) for q in arm_q]), status=vb.frame_status[choice].copy())
