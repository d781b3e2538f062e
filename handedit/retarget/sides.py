"""Retargeting every tracked hand of a clip: a left human hand drives a left robot hand.

Each side is solved on its own with the embodiment's (right-hand) solver; a left hand is
solved in the mirrored view (``handedit.embodiments.mirror``): its keypoints, camera world
and object reflected, the result mapped back (same qpos, pose ``left_pose(T)``) so that
the mirrored URDF renders it. Absent sides (not in view) are ``ABSENT``.

Hand-arm embodiments get one virtual base per side (each from its own shoulder when the
source tracks shoulders), and the chosen pair is checked for dual-arm collision. Where it
collides, the pair of each side's best ``dual_arm_candidates`` that keeps the most frames
(both arms valid, clear of each other) is taken instead, and its colliding frames are
rejected (``COLLISION``) on both sides. Not only the top 3: yaw variants of one base often
fill a side's top 3 with the same arm motion (EgoDex add_remove_lid, Panda+ORCA: every top-3
pair collides in 50 of 94 frames).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from handedit.camera import Intrinsics
from handedit.embodiments.mirror import CAMERA_MIRROR, left_pose, mirror_keypoints, mirror_world
from handedit.keypoints import SHOULDER
from handedit.reasons import STATUS_DTYPE, Reason
from handedit.retarget.config import RetargetConfig
from handedit.retarget.plausibility import BaseView, human_limbs

_MX = CAMERA_MIRROR[:3, :3]


@dataclass
class SidesResult:
    """Per-hand outputs of a clip's chunk (or whole sequence for hand-arm)."""

    qpos: np.ndarray  # (n,S,dof)
    root_pose: np.ndarray  # (n,S,4,4) camera_from_root (left sides: of the mirrored URDF)
    fingertip_error_mm: np.ndarray  # (n,S)
    wrist_error_mm: np.ndarray  # (n,S)
    hand_status: np.ndarray  # (n,S)
    details: dict[tuple[int, int], str]  # (frame, side index) -> text
    joint_names: list[str]
    contact_checked: bool = False
    notes: list[str] = field(default_factory=list)
    virtual_base: dict[str, dict] = field(default_factory=dict)  # side -> sequence-level summary (hand-arm)
    arm_results: dict[int, object] = field(default_factory=dict)  # side index -> HandArmResult (previews)
    hand_qc: dict[int, object] = field(default_factory=dict)  # side index -> the hand's QC (a re-chosen base re-merges it)


def _mirror_mesh(mesh):
    if mesh is None:
        return None
    v, f = mesh
    v = np.array(v, float, copy=True)
    v[:, 0] *= -1.0
    return v, np.asarray(f)[:, ::-1]


def _mirror_pose(pose):
    return None if pose is None else CAMERA_MIRROR @ np.asarray(pose, float) @ CAMERA_MIRROR


def _side_inputs(side: str, kp: np.ndarray, mesh, pose):
    if side != "left":
        return kp, mesh, pose
    return mirror_keypoints(kp), _mirror_mesh(mesh), _mirror_pose(pose)


def retarget_sides(keypoints: np.ndarray, keypoints_valid: np.ndarray, present: np.ndarray, sides: tuple[str, ...],
                   embodiment_id: str, cfg: RetargetConfig, object_mesh=None, object_pose=None) -> SidesResult:
    """Hand-only track: every present side of a chunk (keypoints (n,S,21,3))."""
    from handedit.retarget.api import retarget
    from handedit.retarget.qc import RetargetQCConfig, retarget_qc

    kp = np.asarray(keypoints, np.float64)
    n, S = kp.shape[:2]
    present = np.asarray(present, bool)
    out = None
    for k, side in enumerate(sides):
        valid = np.asarray(keypoints_valid, bool)[:, k] & present[:, k, None]
        kpk, mesh, pose = _side_inputs(side, kp[:, k], object_mesh, object_pose)
        res = retarget(kpk, valid, embodiment_id, cfg, object_mesh=mesh, object_pose=pose)
        qc = retarget_qc(res, kpk, valid, embodiment_id, RetargetQCConfig.from_retarget(cfg), cfg,
                         object_mesh=mesh, object_pose=pose)
        if out is None:
            out = _empty(n, S, res.joint_names)
            out.contact_checked, out.notes = qc.contact_checked, list(qc.notes)
        out.qpos[:, k] = res.qpos
        out.root_pose[:, k] = left_pose(res.root_pose) if side == "left" else res.root_pose
        out.fingertip_error_mm[:, k], out.wrist_error_mm[:, k] = res.fingertip_error_mm, res.wrist_error_mm
        out.hand_status[:, k] = np.where(present[:, k], qc.status, Reason.ABSENT)
        out.details.update({(i, k): d for i, d in qc.details.items()})
    return out


def _empty(n: int, S: int, joint_names: list[str]) -> SidesResult:
    dof = len(joint_names)
    return SidesResult(np.zeros((n, S, dof), np.float32), np.tile(np.eye(4), (n, S, 1, 1)), np.full((n, S), np.nan, np.float32),
                       np.full((n, S), np.nan, np.float32), np.full((n, S), Reason.ABSENT, STATUS_DTYPE), {}, list(joint_names))


def retarget_hand_arm_sides(keypoints: np.ndarray, keypoints_valid: np.ndarray, present: np.ndarray, sides: tuple[str, ...],
                            embodiment_id: str, cfg: RetargetConfig, world_from_camera: np.ndarray | None,
                            world: dict | None, arm_keypoints: np.ndarray | None = None, arm_valid: np.ndarray | None = None,
                            choices: dict[str, int] | None = None, object_mesh=None, object_pose=None,
                            intr: Intrinsics | None = None) -> SidesResult:
    """Hand-arm track, whole sequence: one virtual base per side, then the dual-arm check.
    ``intr`` (the working resolution's camera): base plausibility is ranked in the image."""
    from handedit.retarget.hand_arm import merge_hand_qc, retarget_hand_arm
    from handedit.retarget.qc import RetargetQCConfig, retarget_qc

    kp = np.asarray(keypoints, np.float64)
    n, S = kp.shape[:2]
    present = np.asarray(present, bool)
    shoulders = _shoulders(arm_keypoints, arm_valid, sides)
    out = None
    for k, side in enumerate(sides):
        valid = np.asarray(keypoints_valid, bool)[:, k] & present[:, k, None]
        kpk, mesh, pose = _side_inputs(side, kp[:, k], object_mesh, object_pose)
        wfc, sh = world_from_camera, shoulders
        if side == "left":
            wfc = None if wfc is None else mirror_world(wfc)
            sh = None if sh is None else mirror_keypoints(sh[::-1])  # the mirrored view's right shoulder is the left one
        choice = (choices or {}).get(side)
        view = None
        if intr is not None:
            limbs, tracked_arm = human_limbs(kp[:, k], None if arm_keypoints is None else arm_keypoints[:, k],
                                             None if arm_valid is None else arm_valid[:, k])
            hand = np.where(valid[..., None], kpk, np.nan)  # the side's view (mirrored for a left hand)
            view = BaseView(preview_intrinsics(intr, side), mirror_keypoints(limbs) if side == "left" else limbs, tracked_arm,
                            hand)
        res = retarget_hand_arm(kpk, valid, embodiment_id, cfg, world_from_camera=wfc, choice=choice, world=world,
                                shoulders=sh, view=view, object_mesh=mesh, object_pose=pose)
        qc = retarget_qc(res.hand, kpk, valid, embodiment_id,
                         RetargetQCConfig.from_retarget(cfg), cfg, object_mesh=mesh, object_pose=pose)
        status, details = merge_hand_qc(res, qc)
        if out is None:
            out = _empty(n, S, res.joint_names)
            out.contact_checked, out.notes = qc.contact_checked, [*qc.notes, *res.notes]
        out.qpos[:, k] = res.qpos
        out.root_pose[:, k] = left_pose(res.root_pose) if side == "left" else res.root_pose
        out.fingertip_error_mm[:, k], out.wrist_error_mm[:, k] = res.fingertip_error_mm, res.wrist_error_mm
        out.hand_status[:, k] = np.where(present[:, k], status, Reason.ABSENT)
        out.details.update({(i, k): d for i, d in details.items()})
        out.virtual_base[side] = res.summary()
        out.arm_results[k] = res
        out.hand_qc[k] = qc
    if S > 1 and len(out.arm_results) > 1:
        _dual_arm(out, sides, embodiment_id, cfg, world_from_camera, world)
    else:
        out.notes.append("dual-arm check not applicable: one arm in this sequence")
    return out


def _shoulders(arm_keypoints, arm_valid, sides) -> np.ndarray | None:
    """(2,3) (left, right) shoulder joints of the first frame tracking both, camera frame."""
    if arm_keypoints is None or arm_valid is None or tuple(sides) != ("left", "right"):
        return None
    ok = np.asarray(arm_valid, bool)[:, :, SHOULDER].all(axis=1)
    if not ok.any():
        return None
    i = int(np.argmax(ok))
    return np.asarray(arm_keypoints, float)[i, :, SHOULDER]


def _dual_arm(out: SidesResult, sides, embodiment_id: str, cfg: RetargetConfig, wfc, world) -> None:
    """Pick the best collision-free pair of bases (see module doc)."""
    from handedit.retarget.arm import arm_model
    from handedit.retarget.virtual_base import arms_collide

    arm = arm_model(embodiment_id)
    radius = cfg.virtual_base.link_radius
    res = {k: out.arm_results[k] for k in (0, 1)}
    vbs = {k: r.virtual_base for k, r in res.items()}
    if any(vb.chosen is None for vb in vbs.values()):
        out.notes.append("dual-arm check: one side has no valid base; nothing to check")
        return
    to_common = {k: (_MX if sides[k] == "left" else np.eye(3)) for k in (0, 1)}  # mirrored view -> real

    cache: dict[tuple[int, int], np.ndarray] = {}

    def chains(k: int, cand: int) -> np.ndarray:
        if (k, cand) not in cache:
            T = vbs[k].candidates[cand].camera_from_base
            ch = np.stack([T[:3, :3] @ arm.chain(q) + T[:3, 3:4] for q in vbs[k].arm_tracks[cand]])
            cache[k, cand] = np.einsum("ij,tjp->tip", to_common[k], ch)
        return cache[k, cand]

    def both_ok(p: tuple[int, int]) -> np.ndarray:
        return (vbs[0].frame_status[p[0]] == Reason.OK) & (vbs[1].frame_status[p[1]] == Reason.OK)

    def collisions(i: int, j: int) -> np.ndarray:
        a, b, both = chains(0, i), chains(1, j), both_ok((i, j))
        return np.array([both[t] and arms_collide(a[t], arm.moving, b[t], arm.moving, radius) for t in range(len(a))])

    pinned = {k: res[k].virtual_base.selected_by.startswith("review:") for k in (0, 1)}
    n_opts = cfg.virtual_base.dual_arm_candidates
    opts = {k: ([vbs[k].chosen] if pinned[k] else vbs[k].ranking[:n_opts]) for k in (0, 1)}
    rank = {(i, j): (opts[0].index(i) + opts[1].index(j), opts[0].index(i)) for i in opts[0] for j in opts[1]}
    valid = {p: both_ok(p) for p in rank}
    first = min(rank, key=rank.get)
    best, hit = first, collisions(*first)
    if hit.any():  # the pair that keeps the most frames clear of each other (ties: the better ranked)
        kept = int((valid[first] & ~hit).sum())
        for p in sorted(rank, key=lambda p: (-int(valid[p].sum()), rank[p])):
            if int(valid[p].sum()) <= kept:
                break  # none further on can keep more
            c = collisions(*p)
            if int((valid[p] & ~c).sum()) > kept:
                best, hit, kept = p, c, int((valid[p] & ~c).sum())
    i, j = best
    for k, cand in ((0, i), (1, j)):
        if cand != vbs[k].chosen:  # a lower-ranked base avoids the other arm: re-solve that side with it
            _rechoose(out, k, sides[k], cand, res[k], out.hand_qc[k], wfc, world)
    if hit.any():
        for t in np.flatnonzero(hit):
            for k in (0, 1):
                if out.hand_status[t, k] == Reason.OK:
                    out.hand_status[t, k] = Reason.COLLISION
                    out.details[(int(t), k)] = "dual-arm collision with the other arm"
        out.notes.append(f"dual-arm check: {int(hit.sum())} frame(s) of the pair that keeps the most frames "
                         f"(of each side's top {n_opts}) collide; rejected on both sides")
    else:
        out.notes.append(f"dual-arm check: bases ({i}, {j}) are collision-free")
    for k, side in enumerate(sides):
        out.virtual_base[side]["dual_arm_pair"] = [int(i), int(j)]


def _rechoose(out: SidesResult, k: int, side: str, cand: int, res, qc, wfc, world) -> None:
    """Side k takes candidate ``cand`` (dual-arm choice): its arm joints, base and frame
    statuses change (the first choice's failed frames are not this base's)."""
    from dataclasses import replace

    from handedit.retarget.arm import arm_model
    from handedit.retarget.hand_arm import known_world, merge_hand_qc, with_base

    vb = res.virtual_base
    arm = arm_model(vb.embodiment_id)
    q = arm.assembly_qpos(vb.arm_tracks[cand], res.hand.qpos.astype(float), res.hand.joint_names)
    base = vb.candidates[cand].camera_from_base
    w = None if wfc is None else (mirror_world(wfc) if side == "left" else wfc)
    root = np.einsum("tij,jk->tik", np.linalg.inv(w), base) if known_world(world, w) else np.tile(base, (len(q), 1, 1))
    out.qpos[:, k] = q
    out.root_pose[:, k] = left_pose(root) if side == "left" else root
    base_status, base_details = with_base(res.hand.status, vb, cand)
    status, details = merge_hand_qc(replace(res, status=base_status, details=base_details), qc)
    out.hand_status[:, k] = np.where(out.hand_status[:, k] == Reason.ABSENT, Reason.ABSENT, status)
    for key in [key for key in out.details if key[1] == k]:
        del out.details[key]
    out.details.update({(i, k): d for i, d in details.items()})
    out.virtual_base[side]["chosen"] = int(cand)
    out.virtual_base[side]["selected_by"] = f"dual-arm:{cand}"


def preview_intrinsics(intr: Intrinsics, side: str) -> Intrinsics:
    """Camera of the mirrored view (left sides): renders there, flipped left-right, are exact."""
    if side != "left":
        return intr
    return Intrinsics(intr.fx, intr.fy, intr.width - 1 - intr.cx, intr.cy, intr.width, intr.height)
