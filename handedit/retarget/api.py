"""Retarget a chunk of MANO-order keypoints onto one embodiment.

Hybrid mode (``cfg.hybrid``): a cold frame (the first of a chunk, or every frame without
warm starts) is first aligned by vector retargeting (bone vectors, scaled to the robot),
then refined by position retargeting under the joint limits (the palm-frame guess is
refined too and the lower objective kept). Frames are solved in order; each warm-starts from the last solved frame (primal and
bound multipliers) and is pulled towards it by the smoothness term. A frame whose
required keypoints (wrist, index/middle/pinky MCP: the palm frame) are invalid gets
``Reason.NO_KEYPOINTS`` and the pose of the nearest solved frame; the chunk never aborts.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from handedit.embodiments.roster import get_embodiment, resolve_asset
from handedit.keypoints import FINGERTIPS
from handedit.reasons import STATUS_DTYPE, Reason
from handedit.retarget.config import RetargetConfig
from handedit.retarget.contact import ContactParams, ObjectTrack, push_terms, touch_terms
from handedit.retarget.palm import keypoint_palm_frame
from handedit.retarget.solver import Retargeter
from handedit.setup_meter import metered


NEAR_M = 0.05  # a hand keypoint this close to the object's box: the frame gets the contact terms


@dataclass
class RetargetResult:
    qpos: np.ndarray  # (n,dof) float32, columns = joint_names
    root_pose: np.ndarray  # (n,4,4) float64 camera_from_root_link
    fingertip_error_mm: np.ndarray  # (n,) float32, mean over the robot's (valid) fingertips
    wrist_error_mm: np.ndarray  # (n,) float32
    status: np.ndarray  # (n,) int16 Reason codes
    joint_names: list[str] = field(default_factory=list)
    solver_status: list[str] = field(default_factory=list)  # solver status per frame, IPOPT's names ("" if skipped)

    def slice(self, a: int, b: int) -> "RetargetResult":
        """Frames [a, b) (a chunk of a whole-sequence result)."""
        return RetargetResult(self.qpos[a:b], self.root_pose[a:b], self.fingertip_error_mm[a:b], self.wrist_error_mm[a:b],
                              self.status[a:b], list(self.joint_names), list(self.solver_status[a:b]))


def get_retargeter(embodiment_id: str, cfg: RetargetConfig) -> Retargeter:
    """The per-process solver for (embodiment, config), built on first use."""
    ra = resolve_asset(get_embodiment(embodiment_id))
    return _build(str(ra.path), embodiment_id, cfg)


@functools.lru_cache(maxsize=32)
@metered
def _build(path: str, embodiment_id: str, cfg: RetargetConfig) -> Retargeter:
    ra = resolve_asset(get_embodiment(embodiment_id))
    return Retargeter(ra.path, ra.asset, cfg)


def _clip_f32(q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """float32 qpos that is within the float64 limits exactly (rounding can step outside)."""
    lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
    lo32 = np.where(lo32.astype(np.float64) < lo, np.nextafter(lo32, np.float32(np.inf)), lo32)
    hi32 = np.where(hi32.astype(np.float64) > hi, np.nextafter(hi32, np.float32(-np.inf)), hi32)
    return np.clip(q.astype(np.float32), lo32, hi32)


def _cold_solve(rt: Retargeter, cfg: RetargetConfig, targets, w, q0, pose0, q_prev=None, prev_pose=None, contact=None):
    """Hybrid cold start: position-refine both the vector-mode alignment and the palm-frame
    guess, keep the lower objective (vector mode alone can settle in a worse basin)."""
    sol = rt.solve(targets, w, q0, pose0, q_prev=q_prev, prev_pose=prev_pose, contact=contact)
    if cfg.hybrid:
        qv, pv = rt.vector_init(targets, w, q0, pose0)
        alt = rt.solve(targets, w, qv, pv, q_prev=q_prev, prev_pose=prev_pose, contact=contact)
        if alt.cost < sol.cost:
            sol = alt
    return sol


def _push_out(rt: Retargeter, cfg: RetargetConfig, obj: ObjectTrack, i: int, sol, targets, w, seen, q_prev, prev_pose,
              contact: ContactParams):
    """Re-solve a frame whose links sit inside the object, with push-out planes (``contact``),
    from its own solution; the last solve that did not fail and kept the fingertip and wrist
    errors within the QC's thresholds is kept. Also its deepest penetration (mm)."""
    for k in range(cfg.contact_rounds + 1):
        cam, local = rt.link_samples(sol.q, sol.camera_from_root)
        pushed, deepest = push_terms(obj, i, cam, local, cfg.push_depth_mm, cfg.push_weight, contact)
        if deepest <= cfg.push_depth_mm or k == cfg.contact_rounds:
            break
        again = rt.solve(targets, w, sol.q, sol.camera_from_root, q_prev=q_prev, prev_pose=prev_pose, warm=sol,
                         contact=pushed)
        if not again.ok or _status(rt, cfg, again, targets, seen)[0] != Reason.OK:
            break
        sol, contact = again, pushed
    return sol, deepest


def _status(rt: Retargeter, cfg: RetargetConfig, sol, targets: np.ndarray, seen: np.ndarray) -> tuple[int, float, float]:
    """(status, mean fingertip error, wrist error in mm) of a solved frame against the thresholds."""
    d = np.linalg.norm(rt.robot_points(sol.q, sol.camera_from_root) - targets, axis=1) * 1000.0
    tip, wrist = float(d[rt.tip_rows[seen[rt.tip_rows]]].mean()), float(d[rt.wrist_row])
    if tip > cfg.fingertip_reject_mm:
        return Reason.FINGERTIP_ERROR, tip, wrist
    return (Reason.WRIST_ERROR if wrist > cfg.wrist_reject_mm else Reason.OK), tip, wrist


def retarget(
    keypoints: np.ndarray,
    keypoints_valid: np.ndarray,
    embodiment_id: str,
    cfg: RetargetConfig,
    init: np.ndarray | None = None,
    object_mesh: tuple[np.ndarray, np.ndarray] | None = None,
    object_pose: np.ndarray | None = None,
) -> RetargetResult:
    """Joint trajectory + camera_from_root poses reproducing the keypoints (see module doc).

    ``init``: qpos (dof,) to start from and stay close to on the first frame (e.g. the last
    frame of the previous chunk); None starts from the neutral pose. ``object_mesh`` (vertices,
    faces) and ``object_pose`` (n,4,4 camera_from_object): the contact terms (``contact``
    module; ``cfg.contact``), on frames where the hand is near the object.
    """
    kp = np.asarray(keypoints, dtype=np.float64)
    valid = np.asarray(keypoints_valid, dtype=bool) & np.all(np.isfinite(kp), axis=-1)
    n = kp.shape[0]
    rt = get_retargeter(embodiment_id, cfg)
    dof = len(rt.joint_names)
    qpos = np.zeros((n, dof))
    poses = np.tile(np.eye(4), (n, 1, 1))
    tip_err = np.full(n, np.nan)
    wrist_err = np.full(n, np.nan)
    status = np.full(n, Reason.NO_KEYPOINTS, dtype=STATUS_DTYPE)
    solver_status = [""] * n
    solved = np.zeros(n, dtype=bool)

    tips_present = np.isin(rt.mano_idx, FINGERTIPS)
    obj = ObjectTrack(object_mesh, object_pose) if cfg.contact and object_mesh is not None and object_pose is not None else None
    no_contact = ContactParams.empty(len(rt.tip_rows), 0)
    prev, prev_targets = None, None
    q_anchor = None if init is None else np.asarray(init, float)
    for i in range(n):
        vi = valid[i]
        if not vi[rt.required].all() or not vi[rt.mano_idx[tips_present]].any():
            continue
        targets = kp[i, rt.mano_idx]
        w = rt.base_w * vi[rt.mano_idx]
        contact, near = no_contact, False
        if obj is not None and (near := bool(obj.near(i, kp[i][vi], NEAR_M).any())):
            contact = ContactParams.empty(len(rt.tip_rows), len(rt.contact_links))
            contact.tip_normal, contact.tip_offset, contact.tip_weight = touch_terms(
                obj, i, targets[rt.tip_rows], vi[rt.mano_idx[rt.tip_rows]], cfg.contact_mm, cfg.contact_weight)
        q_prev = q_anchor if prev is None else prev.q
        prev_pose = None if prev is None else prev.camera_from_root

        def solve(contact: ContactParams):
            if prev is None:
                q0 = rt.q_neutral if q_anchor is None else q_anchor
                return _cold_solve(rt, cfg, targets, w, q0, rt.init_pose(keypoint_palm_frame(kp[i])), q_prev=q_anchor,
                                   contact=contact)
            if cfg.warm_start:  # the previous solution, its root moved with the human wrist
                pose0 = prev.camera_from_root.copy()
                pose0[:3, 3] += targets[rt.wrist_row] - prev_targets[rt.wrist_row]
                return rt.solve(targets, w, prev.q, pose0, q_prev=prev.q, prev_pose=prev.camera_from_root, warm=prev,
                                contact=contact)
            # cold: the palm-frame (and vector-mode) initialisation, neutral joints, no multipliers
            return _cold_solve(rt, cfg, targets, w, rt.q_neutral, rt.init_pose(keypoint_palm_frame(kp[i])),
                               q_prev=prev.q, prev_pose=prev.camera_from_root, contact=contact)

        sol = solve(contact)
        if near and sol.ok:
            sol, deepest = _push_out(rt, cfg, obj, i, sol, targets, w, vi[rt.mano_idx], q_prev, prev_pose, contact)
            if deepest > cfg.penetration_mm and contact.tip_weight.any():  # the touch terms may have pulled it in
                alt = solve(no_contact)
                if alt.ok:
                    alt, deep_alt = _push_out(rt, cfg, obj, i, alt, targets, w, vi[rt.mano_idx], q_prev, prev_pose,
                                              ContactParams.empty(len(rt.tip_rows), len(rt.contact_links)))
                    if deep_alt < deepest:
                        sol = alt
        solver_status[i] = sol.status
        if not sol.ok:
            status[i] = Reason.SOLVER_FAILED
            continue
        prev, prev_targets = sol, targets
        solved[i] = True
        qpos[i], poses[i] = sol.q, sol.camera_from_root
        status[i], tip_err[i], wrist_err[i] = _status(rt, cfg, sol, targets, vi[rt.mano_idx])

    # unsolved frames take the nearest solved frame's pose (or neutral/identity)
    idx = np.flatnonzero(solved)
    for i in np.flatnonzero(~solved):
        if idx.size:
            j = idx[np.argmin(np.abs(idx - i))]
            qpos[i], poses[i] = qpos[j], poses[j]
        else:
            qpos[i] = rt.q_neutral if init is None else init
    return RetargetResult(
        qpos=_clip_f32(qpos, rt.lower, rt.upper),
        root_pose=poses,
        fingertip_error_mm=tip_err.astype(np.float32),
        wrist_error_mm=wrist_err.astype(np.float32),
        status=status,
        joint_names=list(rt.joint_names),
        solver_status=solver_status,
    )
