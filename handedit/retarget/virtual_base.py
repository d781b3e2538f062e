"""Hand-arm virtual base: one camera-relative arm base per (sequence, embodiment).

The physical base is not visible in egocentric video, so (paper, appendix "Virtual-Base
Search and IK") a base is searched around an initial guess and then kept fixed for the
whole sequence:

* initial guess: from the shoulders when the source has them (the right shoulder, facing
  along the horizontal direction from the shoulder midpoint to the wrist-trajectory
  centre), else ``init_back * L_r`` behind the wrist-trajectory centre along the camera's
  horizontal viewing direction, ``init_up * L_r`` above it;
* a 3x3x3 grid: lateral {-0.10, 0, 0.10} L_r, forward/backward {-0.15, 0, 0.15} L_r, yaw
  {-15, 0, 15} degrees; height, roll and pitch stay upright (base z = world up);
* per candidate, per frame casadi IK of the robot wrist link onto the target (the human
  wrist mapped by the hand's fixed SE(3)), warm-started along the sequence;
* candidates with an infeasible critical frame, a joint-limit violation, self- or
  support-plane collision, an arm link through the head (closer than
  ``camera_clearance_m`` to the camera) or a trajectory jump are discarded; survivors are ranked
  lexicographically by critical-frame success, reachability, mean end-effector error,
  joint margin, continuity (each quantised, so a later key can break ties);
* every candidate's score is returned; the top three get previews; a review policy picks
  one (``auto_top1`` records that choice as automatic).

Collision geometry is a capsule chain through the moving arm links' origins and the palm
centre (radius ``link_radius``): conservative and cheap, no mesh queries per frame.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from handedit.reasons import STATUS_DTYPE, Reason
from handedit.retarget.arm import ArmModel, arm_model
from handedit.retarget.config import VirtualBaseConfig

GRID_LATERAL = (-0.10, 0.0, 0.10)
GRID_FORWARD = (-0.15, 0.0, 0.15)
GRID_YAW_DEG = (-15.0, 0.0, 15.0)


@dataclass
class CandidateScore:
    index: int
    lateral: float  # offsets in units of L_r, yaw in degrees
    forward: float
    yaw_deg: float
    camera_from_base: np.ndarray
    reason: int  # Reason.OK if it survived
    detail: str
    critical_success: float
    reachability: float
    ee_error_mm: float
    joint_margin: float
    continuity: float  # max joint step (rad) between consecutive solved frames
    rank: int = -1  # 0 = best survivor, -1 = discarded

    def key(self) -> tuple:
        return (-round(self.critical_success, 3), -round(self.reachability, 3), round(self.ee_error_mm),
                -round(self.joint_margin, 2), round(self.continuity, 2))

    def to_json(self) -> dict:
        d = asdict(self)
        d["camera_from_base"] = np.asarray(self.camera_from_base).round(6).tolist()
        d["reason_name"] = Reason(self.reason).name
        for k, v in d.items():  # JSON has no inf/nan
            if isinstance(v, float) and not np.isfinite(v):
                d[k] = None
        return d


@dataclass
class VirtualBaseResult:
    embodiment_id: str
    reach_m: float
    candidates: list[CandidateScore]  # all 27, in grid order
    ranking: list[int]  # candidate indices of survivors, best first
    chosen: int | None  # candidate index, None if the sequence is rejected
    selected_by: str  # "auto:top1" | "pending:manual" | "none"
    reason: int  # Reason.OK or NO_VALID_BASE
    detail: str
    camera_from_base: np.ndarray | None
    arm_q: np.ndarray | None  # (T, n_arm) of the chosen candidate
    qpos: np.ndarray | None  # (T, dof) full assembly vector of the chosen candidate
    status: np.ndarray  # (T,) per-frame status of the chosen candidate
    trajectories: dict[int, np.ndarray] = field(default_factory=dict)  # top-k candidate -> (T,dof)
    arm_tracks: np.ndarray | None = None  # (27,T,n_arm) every candidate's IK solution
    frame_status: np.ndarray | None = None  # (27,T) every candidate's per-frame status

    @property
    def top(self) -> list[int]:
        return self.ranking[:3]

    def scores_json(self) -> list[dict]:
        return [c.to_json() for c in self.candidates]


# ----------------------------------------------------------------------------------------
# geometry helpers


def upright_frame(position: np.ndarray, up: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """camera_from_base with z = up and x = ``forward`` made horizontal."""
    z = np.asarray(up, float) / np.linalg.norm(up)
    x = np.asarray(forward, float) - (np.asarray(forward, float) @ z) * z
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, position
    return T


def support_plane_from_world(world_from_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(up, plane) in the camera frame for a world whose z=0 plane is the support surface
    (the synthetic source's table); plane = (n, d) with n.p + d = signed height."""
    cam_from_world = np.linalg.inv(world_from_camera)
    n = cam_from_world[:3, 2]
    d = -n @ cam_from_world[:3, 3]
    return n, np.concatenate([n, [d]])


def initial_base(targets: np.ndarray, valid: np.ndarray, up: np.ndarray, reach: float, cfg: VirtualBaseConfig,
                 shoulders: np.ndarray | None = None, shoulder_offset: np.ndarray | None = None) -> np.ndarray:
    """camera_from_base of the grid centre (see module doc)."""
    up = up / np.linalg.norm(up)
    centre = targets[valid, :3, 3].mean(axis=0)
    if shoulders is not None and np.all(np.isfinite(shoulders)):
        left, right = np.asarray(shoulders[0], float), np.asarray(shoulders[1], float)
        mid = (left + right) / 2
        fwd = centre - mid
        T = upright_frame(right - cfg.init_shoulder_drop * reach * up, up, fwd)
    else:
        fwd = centre - (centre @ up) * up  # horizontal viewing direction (camera at the origin)
        pos = centre - cfg.init_back * reach * fwd / np.linalg.norm(fwd) + cfg.init_up * reach * up
        T = upright_frame(pos, up, fwd)
    if shoulder_offset is not None:  # put the arm's first joint, not its base plate, at that point
        T[:3, 3] -= T[:3, :3] @ shoulder_offset
    return T


def candidate_grid(T0: np.ndarray, reach: float) -> list[tuple[float, float, float, np.ndarray]]:
    """The 27 (lateral, forward, yaw_deg, camera_from_base) candidates around ``T0``."""
    out = []
    for lat in GRID_LATERAL:
        for fwd in GRID_FORWARD:
            for yaw in GRID_YAW_DEG:
                T = T0.copy()
                T[:3, 3] = T0[:3, 3] + T0[:3, 0] * fwd * reach + T0[:3, 1] * lat * reach
                a = np.radians(yaw)
                Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
                T[:3, :3] = T0[:3, :3] @ Rz
                out.append((lat, fwd, yaw, T))
    return out


def _seg_dist(p1, q1, p2, q2) -> float:
    """Distance between segments [p1,q1] and [p2,q2]."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, f = d1 @ d1, d2 @ d2, d2 @ r
    if a < 1e-12 and e < 1e-12:
        return float(np.linalg.norm(r))
    if a < 1e-12:
        s, t = 0.0, np.clip(f / e, 0, 1)
    else:
        c = d1 @ r
        if e < 1e-12:
            t, s = 0.0, np.clip(-c / a, 0, 1)
        else:
            b = d1 @ d2
            den = a * e - b * b
            s = np.clip((b * f - c * e) / den, 0, 1) if den > 1e-12 else 0.0
            t = (b * s + f) / e
            if t < 0:
                t, s = 0.0, np.clip(-c / a, 0, 1)
            elif t > 1:
                t, s = 1.0, np.clip((b - c) / a, 0, 1)
    return float(np.linalg.norm(p1 + d1 * s - p2 - d2 * t))


def _segments(chain: np.ndarray, moving: np.ndarray, labels: np.ndarray | None = None):
    """Capsule axes between consecutive distinct chain points, starting at the last fixed
    point; with ``labels`` (per point) also each segment's end-point label."""
    pts = chain.T
    first = max(int(np.argmax(moving)) - 1, 0)
    keep, lab = [pts[first]], [None if labels is None else labels[first]]
    for k in range(first + 1, len(pts)):
        if np.linalg.norm(pts[k] - keep[-1]) > 1e-3:
            keep.append(pts[k])
            lab.append(None if labels is None else labels[k])
    segs = list(zip(keep[:-1], keep[1:]))
    return segs if labels is None else (segs, lab[1:])


def self_collision(chain: np.ndarray, moving: np.ndarray, radius: float, distal: np.ndarray | None = None) -> bool:
    """Non-adjacent capsules (index gap >= 3) closer than 2 * radius. ``distal`` marks chain
    points of the compact wrist + hand group (its segments are never tested against each
    other: there the capsule-through-origins model folds back on itself by construction)."""
    if distal is None:
        segs, d = _segments(chain, moving), None
    else:
        segs, d = _segments(chain, moving, distal)
    for i in range(len(segs)):
        for j in range(i + 3, len(segs)):
            if d is not None and d[i] and d[j]:
                continue
            if _seg_dist(*segs[i], *segs[j]) < 2 * radius:
                return True
    return False


def plane_clearance(chain_cam: np.ndarray, moving: np.ndarray, plane: np.ndarray) -> float:
    """Lowest signed height above the plane of the selected chain points (m)."""
    pts = chain_cam[:, moving]
    return float((plane[:3] @ pts + plane[3]).min())


def arms_collide(chain_a: np.ndarray, moving_a: np.ndarray, chain_b: np.ndarray, moving_b: np.ndarray, radius: float) -> bool:
    """Dual-arm check (both chains in the same frame): any pair of capsules closer than 2 r."""
    return any(_seg_dist(*s, *t) < 2 * radius for s in _segments(chain_a, moving_a) for t in _segments(chain_b, moving_b))


# ----------------------------------------------------------------------------------------
# evaluation


@dataclass
class _Track:
    arm_q: np.ndarray
    status: np.ndarray
    pos_err: np.ndarray
    chains: np.ndarray  # (T,3,P) in the camera frame


def camera_distance(chain_cam: np.ndarray, points: np.ndarray, camera: np.ndarray) -> float:
    """Distance (m) from the camera centre to the capsule axes through the selected chain points."""
    pts = chain_cam[:, points].T
    if len(pts) < 2:
        return float("inf")
    return min(_seg_dist(a, b, camera, camera) for a, b in zip(pts[:-1], pts[1:]))


def _evaluate(arm: ArmModel, camera_from_base: np.ndarray, targets: np.ndarray, valid: np.ndarray,
              plane: np.ndarray | None, cfg: VirtualBaseConfig, hint: np.ndarray | None = None,
              cameras: np.ndarray | None = None) -> _Track:
    """IK along the sequence for one base. ``hint``: first-frame arm joints of a neighbouring
    candidate (tried first: neighbours differ by a few cm, so it usually converges at once)."""
    T = len(targets)
    base_from_cam = np.linalg.inv(camera_from_base)
    shoulder_cam = camera_from_base[:3, :3] @ arm.shoulder + camera_from_base[:3, 3]
    arm_q = np.tile((arm.lo_s + arm.hi_s) / 2, (T, 1))
    status = np.full(T, Reason.NO_KEYPOINTS, dtype=STATUS_DTYPE)
    pos_err = np.full(T, np.nan)
    chains = np.zeros((T, 3, len(arm.moving)))
    prev = None
    rng = np.random.default_rng(0)
    for i in np.flatnonzero(valid):
        target = base_from_cam @ targets[i]
        if prev is None:
            seeds = ([] if hint is None else [hint]) + [(arm.lo_s + arm.hi_s) / 2, np.zeros(arm.n)]
            seeds += [rng.uniform(arm.lo_s, arm.hi_s) for _ in range(max(cfg.n_seeds - len(seeds), 0))]
            sols = []
            hopeless = np.linalg.norm(targets[i][:3, 3] - shoulder_cam) > arm.max_reach
            for s0 in seeds[: 1 if hopeless else len(seeds)]:  # first feasible seed wins, else the closest
                sols.append(arm.solve(target, s0))
                if sols[-1].pos_err_mm <= cfg.pos_tol_mm and sols[-1].rot_err_deg <= cfg.rot_tol_deg:
                    break
            sol = min(sols, key=lambda s: s.pos_err_mm + 10 * s.rot_err_deg)
        else:
            sol = arm.solve(target, prev.x, q_prev=prev.x, smooth=cfg.smooth, warm=prev)
            if sol.pos_err_mm > cfg.pos_tol_mm or sol.rot_err_deg > cfg.rot_tol_deg:  # restart once from the seed
                alt = arm.solve(target, (arm.lo_s + arm.hi_s) / 2)
                sol = alt if alt.pos_err_mm + 10 * alt.rot_err_deg < sol.pos_err_mm + 10 * sol.rot_err_deg else sol
        prev = sol
        arm_q[i] = sol.x
        pos_err[i] = sol.pos_err_mm
        ch = arm.chain(sol.x)
        chains[i] = camera_from_base[:3, :3] @ ch + camera_from_base[:3, 3:4]
        q = sol.x
        if not sol.ok or sol.pos_err_mm > cfg.pos_tol_mm or sol.rot_err_deg > cfg.rot_tol_deg:
            far = np.linalg.norm(targets[i][:3, 3] - shoulder_cam) > arm.max_reach
            status[i] = Reason.OUT_OF_REACH if far else Reason.IK_INFEASIBLE
        elif np.any(q < arm.lower - cfg.joint_limit_tol) or np.any(q > arm.upper + cfg.joint_limit_tol):
            status[i] = Reason.JOINT_LIMIT
        elif self_collision(ch, arm.moving, cfg.link_radius, arm.distal):
            status[i] = Reason.COLLISION
        elif plane is not None and plane_clearance(chains[i], arm.arm_points, plane) < cfg.link_radius + cfg.plane_margin:
            status[i] = Reason.COLLISION
        elif cameras is not None and cfg.camera_clearance_m > 0 and \
                camera_distance(chains[i], arm.proximal, cameras[i]) < cfg.camera_clearance_m + cfg.link_radius:
            status[i] = Reason.COLLISION
        else:
            status[i] = Reason.OK
    return _Track(arm_q, status, pos_err, chains)


def _score(idx: int, grid_entry, track: _Track, arm: ArmModel, valid: np.ndarray, critical: np.ndarray,
           cfg: VirtualBaseConfig) -> CandidateScore:
    lat, fwd, yaw, Tb = grid_entry
    st = track.status
    ok = st == Reason.OK
    crit = critical & valid
    crit_succ = float(ok[crit].mean()) if crit.any() else 1.0
    reach = float(ok[valid].mean()) if valid.any() else 0.0
    ee = float(np.nanmean(track.pos_err[ok])) if ok.any() else float("inf")
    q = track.arm_q[ok]
    rng_ = arm.hi_s - arm.lo_s
    margin = float(np.min(np.minimum(q - arm.lo_s, arm.hi_s - q) / rng_)) if len(q) else 0.0
    solved = np.flatnonzero(valid)
    steps = np.abs(np.diff(track.arm_q[solved], axis=0)).max(axis=1) if len(solved) > 1 else np.zeros(0)
    cont = float(steps.max()) if steps.size else 0.0
    reason, detail = Reason.OK, ""
    bad_crit = crit & ~ok
    if bad_crit.any():
        codes = st[bad_crit]
        r = Reason(int(np.bincount(codes).argmax()))  # the commonest frame-level cause names the rejection
        reason = r
        detail = f"{int(bad_crit.sum())} critical frame(s) fail ({r.name.lower().replace('_', ' ')}), first {int(np.flatnonzero(bad_crit)[0])}"
    elif np.any(st == Reason.JOINT_LIMIT):
        reason, detail = Reason.JOINT_LIMIT, "joint-limit violation"
    elif np.any(st == Reason.COLLISION):
        reason, detail = Reason.COLLISION, f"collision in {int((st == Reason.COLLISION).sum())} frame(s)"
    elif cont > cfg.max_joint_step:
        reason, detail = Reason.DISCONTINUITY, f"joint step {cont:.2f} rad > {cfg.max_joint_step}"
    return CandidateScore(idx, lat, fwd, yaw, Tb, int(reason), detail, crit_succ, reach, ee, margin, cont)


def search_virtual_base(
    targets: np.ndarray,
    valid: np.ndarray,
    embodiment_id: str,
    cfg: VirtualBaseConfig,
    up: np.ndarray | None = None,
    support_plane: np.ndarray | None = None,
    shoulders: np.ndarray | None = None,
    critical: np.ndarray | None = None,
    init_base: np.ndarray | None = None,
    cameras: np.ndarray | None = None,
) -> VirtualBaseResult:
    """Search the 27 bases for one sequence and pick one by the review policy.

    targets: (T,4,4) camera_from_wrist-link targets (``ArmModel.wrist_targets``);
    up: world up in the camera frame (default: image up, -y); support_plane: (4,) (n, d)
    in the camera frame or None (check not possible); shoulders: (2,3) left/right
    shoulder in the camera frame or None; critical: (T,) frames that must be reachable
    (default: every valid frame); init_base: override the grid centre; cameras: (T,3) the
    camera centre per frame in the targets' frame (arm links must keep clear of the head).
    """
    arm = arm_model(embodiment_id)
    targets = np.asarray(targets, float)
    valid = np.asarray(valid, bool) & np.all(np.isfinite(targets.reshape(len(targets), -1)), axis=1)
    n = len(targets)
    up = np.array([0.0, -1.0, 0.0]) if up is None else np.asarray(up, float)
    critical = valid.copy() if critical is None else np.asarray(critical, bool)
    if not valid.any():
        return VirtualBaseResult(embodiment_id, arm.reach, [], [], None, "none", int(Reason.NO_VALID_BASE),
                                 "no frame with a valid wrist", None, None, None,
                                 np.full(n, Reason.NO_KEYPOINTS, dtype=STATUS_DTYPE))
    T0 = init_base if init_base is not None else initial_base(targets, valid, up, arm.reach, cfg, shoulders, arm.shoulder)
    grid = candidate_grid(T0, arm.reach)
    tracks, scores = [], []
    first = int(np.flatnonzero(valid)[0])
    for k, g in enumerate(grid):
        hint = tracks[-1].arm_q[first] if tracks and tracks[-1].status[first] != Reason.OUT_OF_REACH else None
        tr = _evaluate(arm, g[3], targets, valid, support_plane, cfg, hint, cameras)
        tracks.append(tr)
        scores.append(_score(k, g, tr, arm, valid, critical, cfg))
    ranking = sorted((c.index for c in scores if c.reason == Reason.OK), key=lambda i: scores[i].key())
    for r, i in enumerate(ranking):
        scores[i].rank = r
    trajectories = {i: np.stack([arm.full_q(q) for q in tracks[i].arm_q]) for i in ranking[: cfg.top_k]}
    arm_tracks = np.stack([t.arm_q for t in tracks])
    frame_status = np.stack([t.status for t in tracks])
    if not ranking:
        causes = np.bincount([c.reason for c in scores])
        cause = Reason(int(causes.argmax()))
        # per-frame status: the frame-level cause of the candidate that got furthest
        best = max(range(len(scores)), key=lambda i: (scores[i].reachability, -scores[i].ee_error_mm))
        st = tracks[best].status.copy()
        st[st == Reason.OK] = Reason.NO_VALID_BASE
        return VirtualBaseResult(embodiment_id, arm.reach, scores, [], None, "none", int(Reason.NO_VALID_BASE),
                                 f"no valid base among {len(scores)} candidates (most common cause: {cause.name.lower().replace('_', ' ')})",
                                 None, None, None, st, trajectories, arm_tracks, frame_status)
    if cfg.review == "auto_top1":
        chosen, by = ranking[0], "auto:top1"
    else:
        chosen, by = ranking[0], "pending:manual"  # provisional until `handedit review` decides
    return _with_choice(VirtualBaseResult(embodiment_id, arm.reach, scores, ranking, None, by, int(Reason.OK), "",
                                          None, None, None, np.zeros(n, STATUS_DTYPE), trajectories, arm_tracks, frame_status),
                        chosen, tracks[chosen], arm)


def _with_choice(res: VirtualBaseResult, chosen: int, track: _Track, arm: ArmModel) -> VirtualBaseResult:
    res.chosen = chosen
    res.camera_from_base = res.candidates[chosen].camera_from_base
    res.arm_q = track.arm_q
    res.qpos = np.stack([arm.full_q(q) for q in track.arm_q])
    res.status = track.status.copy()
    return res
