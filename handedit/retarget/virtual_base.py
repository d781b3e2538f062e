"""Hand-arm virtual base: one camera-relative arm base per (sequence, embodiment).

The physical base is not visible in egocentric video, so (paper, appendix "Virtual-Base
Search and IK") a base is searched around an initial guess and then kept fixed for the
whole sequence:

* initial guess: from the shoulders (the right shoulder, facing along the horizontal
  direction from the shoulder midpoint to the wrist-trajectory centre): the source's
  where it tracks them, else shoulders placed under the head camera (``virtual_shoulders``);
  with neither (no valid frame) ``init_back * L_r`` behind the wrist-trajectory centre
  along the camera's horizontal viewing direction, ``init_up * L_r`` above it;
* a 3x3x3 grid: lateral {-0.10, 0, 0.10} L_r, forward/backward {-0.15, 0, 0.15} L_r, yaw
  {-15, 0, 15} degrees; height, roll and pitch stay upright (base z = world up);
* per candidate, per frame casadi IK of the robot wrist link onto the target (the human
  wrist mapped by the hand's fixed SE(3)), warm-started along the sequence; a yawed
  candidate of a six-joint arm whose first frame lands on the branch of the candidate
  before it takes that one's track with the first joint turned back (``_yaw_turned``);
* a frame fails on IK infeasibility, a joint-limit violation, self- or support-plane
  collision, or an arm link inside the operator's head and torso (a capsule from behind
  the head camera down along world up: ``body_distance``); a candidate is discarded when
  more than ``critical_tolerance`` of its critical frames fail (the paper does not say which
  frames are critical; the caller passes the frames where the hand is in view: see
  ``hand_arm.critical_frames``; the frames after the one that decides it are not solved),
  or when it keeps less than ``min_reachability`` of the sequence; failed frames of a kept
  candidate are rejected alone; a body collision never fails a critical frame, nor does a
  frame past a wrist flip (kept frames that jump: ``_split_flips`` keeps the longest run),
  and a candidate discarded for body collisions alone is a base of last resort
  (``_last_resort``) when no other survives;
* when none of the 27 survives, or the best survivor lies off the human arm or crosses its
  forearm (``_why_refine``), a second grid is centred where the arm's first joint sits
  ``refine_reach_frac`` L_r from the wrist targets (``reach_centre``: a long arm beside the
  human shoulder folds onto targets 0.3 L_r away and reaches no wrist orientation); the
  verdict counts of both grids and the targets' distance go to ``diagnosis``;
* survivors are ranked lexicographically by critical-frame success, plausibility (the
  share of the arm's footprint outside the human arm's corridor, ``plausibility``),
  reachability, forearm direction against the human forearm, mean end-effector error,
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
from handedit.retarget.arm import ArmModel, IKSolution, arm_model
from handedit.retarget.config import VirtualBaseConfig
from handedit.retarget.newton import clamp
from handedit.retarget.plausibility import BaseView, footprint_outside, forearm_angle, hand_hidden, silhouette, silhouette_outside

GRID_LATERAL = (-0.10, 0.0, 0.10)
GRID_FORWARD = (-0.15, 0.0, 0.15)
GRID_YAW_DEG = (-15.0, 0.0, 15.0)
REFINE_OUTWARD = (0.0, 0.15, 0.30)  # the second grid (refine_grid), in L_r
REFINE_DOWN = (0.0, 0.15, 0.30)
SETTLED_SLACK_M = 0.02  # a neighbour's settled branch is taken when it keeps this much less clearance at most
_UNREACHED = (Reason.OUT_OF_REACH, Reason.IK_INFEASIBLE)  # a first frame no seed reached: its closest miss is no hint


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
    off_corridor: float = 0.0  # mean share of the arm's footprint outside the human arm's corridor (0: not measured)
    forearm_deg: float = 0.0  # mean angle between the robot's and the human forearm (0: not measured)
    stage: str = "grid"  # "grid": the paper's 27; "refine": the reach-aware second grid
    down: float = 0.0  # refine: the base this far below the grid centre, in L_r
    screened_rate: float = 0.0  # share of the sampled frames composite's screens would drop (OFF_ARM or HAND_HIDDEN)
    hand_hidden: float = 0.0  # mean share of the human hand's footprint under the robot's own arm (0: not measured)
    last_resort: bool = False  # discarded for body collisions alone: a base when no candidate of either grid survives

    def key(self) -> tuple:
        """Lexicographic rank: the critical frames it keeps once composite's hand-arm screens
        have dropped the frames whose robot fills the view off the human arm or hides its own
        hand (critical-frame success x the sampled frames' share they keep), plausibility (footprint
        in tenths), reachability, forearm direction (15 degree steps), then the paper's
        end-effector error, joint margin and continuity."""
        off = round(self.off_corridor * 10) if np.isfinite(self.off_corridor) else 10
        fa = round(self.forearm_deg / 15) if np.isfinite(self.forearm_deg) else 12
        rate = self.screened_rate if np.isfinite(self.screened_rate) else 0.0
        return (-round(self.critical_success * (1.0 - rate), 3), off, -round(self.reachability, 3), fa,
                round(self.ee_error_mm), -round(self.joint_margin, 2), round(self.continuity, 2))

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
    diagnosis: dict = field(default_factory=dict)  # why candidates failed, the targets' distance in L_r, refinement

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


def virtual_shoulders(camera: np.ndarray, up: np.ndarray, cfg: VirtualBaseConfig) -> np.ndarray:
    """(2,3) (left, right) shoulders of the operator wearing the head camera ``camera`` (4,4, in
    the targets' frame) for sources that do not track them: ``virtual_shoulder_drop_m`` below
    it, ``virtual_shoulder_back_m`` behind it and ``virtual_shoulder_half_width_m`` to each
    side, horizontally. Without them the grid centre sat between the camera and the hands,
    and the robot's shoulder filled the top of the view."""
    up = np.asarray(up, float) / np.linalg.norm(up)

    def horizontal(v: np.ndarray) -> np.ndarray:
        h = v - (v @ up) * up
        return h / np.linalg.norm(h) if np.linalg.norm(h) > 1e-9 else h

    fwd, right = horizontal(camera[:3, 2]), horizontal(camera[:3, 0])
    centre = camera[:3, 3] - cfg.virtual_shoulder_drop_m * up - cfg.virtual_shoulder_back_m * fwd
    half = cfg.virtual_shoulder_half_width_m * right
    return np.stack([centre - half, centre + half])


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


def refine_grid(T1: np.ndarray, reach: float, outward: np.ndarray) -> list[tuple[float, float, float, np.ndarray]]:
    """The 27 second-chance candidates around ``T1`` (``reach_centre``): outward from the
    operator's body (horizontal ``outward``) {0, 0.15, 0.3} L_r, down {0, 0.15, 0.3} L_r,
    forward/backward {-0.15, 0, 0.15} L_r; upright, no yaw. A folded elbow that the paper's
    grid puts into the operator's head clears it lower or further out. Entries are
    (lateral, forward, yaw_deg, camera_from_base, down)."""
    up = T1[:3, 2]
    out = np.asarray(outward, float) - (np.asarray(outward, float) @ up) * up
    out = out / np.linalg.norm(out) if np.linalg.norm(out) > 1e-9 else T1[:3, 1]
    grid = []
    for lat in REFINE_OUTWARD:
        for down in REFINE_DOWN:
            for fwd in GRID_FORWARD:
                T = T1.copy()
                T[:3, 3] = T1[:3, 3] + (lat * out + fwd * T1[:3, 0] - down * up) * reach
                grid.append((lat, fwd, 0.0, T, down))
    return grid


def seg_dists(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Distances between segments [p1,q1] and [p2,q2], (m,3) each, all pairs at once (the closest
    points' parameters clamped to the segments, degenerate segments as points). The search asks
    for hundreds of thousands per hand-arm sequence: one at a time they were a fifth of its time."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, f = np.einsum("ij,ij->i", d1, d1), np.einsum("ij,ij->i", d2, d2), np.einsum("ij,ij->i", d2, r)
    b, c = np.einsum("ij,ij->i", d1, d2), np.einsum("ij,ij->i", d1, r)
    pa, pe = a < 1e-12, e < 1e-12  # a segment that is a point
    a1, e1 = np.where(pa, 1.0, a), np.where(pe, 1.0, e)
    den = a * e - b * b
    s = np.where(den > 1e-12, clamp((b * f - c * e) / np.where(den > 1e-12, den, 1.0), 0.0, 1.0), 0.0)
    t = (b * s + f) / e1
    s = np.where(t < 0, clamp(-c / a1, 0.0, 1.0), np.where(t > 1, clamp((b - c) / a1, 0.0, 1.0), s))
    t = clamp(t, 0.0, 1.0)
    s, t = np.where(pe, clamp(-c / a1, 0.0, 1.0), s), np.where(pe, 0.0, t)
    s, t = np.where(pa, 0.0, s), np.where(pa, np.where(pe, 0.0, clamp(f / e1, 0.0, 1.0)), t)
    return np.linalg.norm(r + d1 * s[:, None] - d2 * t[:, None], axis=1)


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
    pairs = [(i, j) for i in range(len(segs)) for j in range(i + 3, len(segs)) if d is None or not (d[i] and d[j])]
    if not pairs:
        return False
    i, j = np.array(pairs).T
    ends = np.asarray(segs, float)  # (n, 2, 3)
    return bool((seg_dists(ends[i, 0], ends[i, 1], ends[j, 0], ends[j, 1]) < 2 * radius).any())


def plane_clearance(chain_cam: np.ndarray, moving: np.ndarray, plane: np.ndarray) -> float:
    """Lowest signed height above the plane of the selected chain points (m)."""
    pts = chain_cam[:, moving]
    return float((plane[:3] @ pts + plane[3]).min())


def arms_collide(chain_a: np.ndarray, moving_a: np.ndarray, chain_b: np.ndarray, moving_b: np.ndarray, radius: float) -> bool:
    """Dual-arm check (both chains in the same frame): any pair of capsules closer than 2 r."""
    a, b = np.asarray(_segments(chain_a, moving_a), float), np.asarray(_segments(chain_b, moving_b), float)
    if not len(a) or not len(b):
        return False
    i, j = np.repeat(np.arange(len(a)), len(b)), np.tile(np.arange(len(b)), len(a))
    return bool((seg_dists(a[i, 0], a[i, 1], b[j, 0], b[j, 1]) < 2 * radius).any())


# ----------------------------------------------------------------------------------------
# evaluation


@dataclass
class _Track:
    arm_q: np.ndarray
    status: np.ndarray
    pos_err: np.ndarray
    chains: np.ndarray  # (T,3,P) in the camera frame
    settled: float | None = None  # every seed was tried on the first frame and none kept the full body clearance:
    # the clearance (m) of the branch it settled for (a neighbouring candidate may take the same branch as it is)
    stopped: int | None = None  # the frame after which it was not solved: by then it had failed too many critical frames


def body_distance(points: np.ndarray, frame_from_camera: np.ndarray, up: np.ndarray, head_back: float,
                  torso_length: float, torso_back: float = 0.0, neck: float = 0.25) -> float:
    """Distance (m) from the polyline ``points`` (P,3, the targets' frame) to the operator's
    body axis: the head's centre ``head_back`` behind the camera (horizontally), the neck
    ``neck`` below it, the hips ``torso_length`` below the head and ``torso_back`` further
    back (a person looking down at a table leans over it: the chest stays behind the eyes)."""
    up = np.asarray(up, float) / np.linalg.norm(up)
    fwd = frame_from_camera[:3, 2] - (frame_from_camera[:3, 2] @ up) * up
    n = np.linalg.norm(fwd)
    fwd = fwd / n if n > 1e-6 else np.zeros(3)
    head = frame_from_camera[:3, 3] - head_back * fwd
    axis = [head, head - neck * up, head - torso_back * fwd - torso_length * up]
    pts = np.asarray(points, float)
    if len(pts) < 2:
        return float("inf")
    axis = np.asarray(axis)
    i, j = np.repeat(np.arange(len(pts) - 1), len(axis) - 1), np.tile(np.arange(len(axis) - 1), len(pts) - 1)
    return float(seg_dists(pts[i], pts[i + 1], axis[j], axis[j + 1]).min())


def _evaluate(arm: ArmModel, camera_from_base: np.ndarray, targets: np.ndarray, valid: np.ndarray,
              plane: np.ndarray | None, cfg: VirtualBaseConfig, hint: np.ndarray | None = None,
              cameras: np.ndarray | None = None, up: np.ndarray | None = None, hint_settled: float | None = None,
              critical: np.ndarray | None = None, turned: _Track | None = None) -> _Track:
    """IK along the sequence for one base. ``hint``: first-frame arm joints of a neighbouring
    candidate (tried first: neighbours differ by a few cm, so it usually converges at once);
    ``hint_settled``: that neighbour's ``_Track.settled``; ``critical``: once more of these
    frames fail (other than for the operator's body) than ``critical_tolerance`` allows, the
    candidate is discarded whatever the rest does, so the rest is not solved (``NO_VALID_BASE``):
    a KUKA arm's 18 unreachable candidates on EgoDex add_remove_lid failed their first two
    frames, and their 92 others took 90 % of the search, each failed frame a cold IPOPT restart.
    ``turned``: the yaw mate's track turned to this base (``_yaw_turned``): when this base's first
    frame reaches its target on the mate's branch (no joint ``max_joint_step`` from the mate's, which
    reached it too), the rest is that track, not solved again; otherwise, on another branch, the
    candidate is solved on its own, as the grid's yaw meant."""
    T = len(targets)
    base_from_cam = np.linalg.inv(camera_from_base)
    shoulder_cam = camera_from_base[:3, :3] @ arm.shoulder + camera_from_base[:3, 3]
    arm_q = np.tile((arm.lo_s + arm.hi_s) / 2, (T, 1))
    status = np.full(T, Reason.NO_KEYPOINTS, dtype=STATUS_DTYPE)
    pos_err = np.full(T, np.nan)
    chains = np.zeros((T, 3, len(arm.moving)))
    body_pts = np.r_[max(int(np.argmax(arm.moving)) - 1, 0), np.flatnonzero(arm.proximal)]  # from the shoulder on

    def clearance(q: np.ndarray, i: int) -> float:
        pts = camera_from_base[:3, :3] @ arm.chain(q)[:, body_pts] + camera_from_base[:3, 3:4]
        return body_distance(pts.T, cameras[i], up, cfg.head_back_m, cfg.torso_length_m, cfg.torso_back_m)

    prev, settled, stopped = None, None, None
    crit = np.zeros(T, bool) if critical is None else np.asarray(critical, bool) & valid
    allowed, n_bad = _allowed_failures(crit, cfg), 0
    rng = np.random.default_rng(0)
    for i in np.flatnonzero(valid):
        target = base_from_cam @ targets[i]
        if prev is None:
            seeds = ([] if hint is None else [hint]) + [(arm.lo_s + arm.hi_s) / 2, np.zeros(arm.n)]
            seeds += [rng.uniform(arm.lo_s, arm.hi_s) for _ in range(max(cfg.n_seeds - len(seeds), 0))]
            hopeless = np.linalg.norm(targets[i][:3, 3] - shoulder_cam) > arm.max_reach
            sol, settled = _first_frame(arm, target, seeds[: 1 if hopeless else len(seeds)], cfg,
                                        None if cameras is None else (lambda q: clearance(q, i)),
                                        hinted=hint is not None, hint_settled=hint_settled)
            if turned is not None and turned.status[i] not in _UNREACHED and sol.pos_err_mm <= cfg.pos_tol_mm \
                    and sol.rot_err_deg <= cfg.rot_tol_deg and np.abs(sol.x - turned.arm_q[i]).max() <= cfg.max_joint_step:
                return turned
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
        elif cameras is not None and cfg.body_radius_m > 0 and \
                body_distance(chains[i][:, body_pts].T, cameras[i], up, cfg.head_back_m, cfg.torso_length_m, cfg.torso_back_m) \
                < cfg.body_radius_m + cfg.link_radius:
            status[i] = Reason.BODY_COLLISION
        else:
            status[i] = Reason.OK
        n_bad += bool(crit[i] and status[i] not in (Reason.OK, Reason.BODY_COLLISION))
        if n_bad > allowed:
            stopped = int(i)
            status[i + 1:][np.asarray(valid, bool)[i + 1:]] = Reason.NO_VALID_BASE
            break
    return _Track(arm_q, status, pos_err, chains, settled, stopped)


def _yaw_turned(arm: ArmModel, mate_entry, entry, mate: _Track) -> _Track | None:
    """``entry``'s track from ``mate``'s, the candidate before it, when the two differ by the base's
    yaw alone (the grid's yaw triples) and the arm's first joint turns about the base's z axis
    (``ArmModel.yaw_sign``): the mate's joints with that joint turned back by the yaw difference put
    every link where the mate's were, so every frame reaches and fails as the mate's does (an IK
    solution of this base whose joint-mid pull on that joint turned with it). ``_evaluate`` takes it
    once this base's own first frame lands on the same branch. None when the two are not yaw mates,
    the turned joint would leave its range in a solved frame, or the arm has more than six joints:
    along a redundant arm's self-motion the joint-mid pull picks the elbow's swing, and that pull
    turned with the base picks another one (xArm7 on insert_remove 0:96: a forearm 45 degrees off
    the human one where solving on its own found 30)."""
    same_place = len(mate_entry) == len(entry) and mate_entry[:2] == entry[:2] and mate_entry[4:] == entry[4:]
    if arm.yaw_sign == 0 or arm.n > 6 or not same_place or mate_entry[2] == entry[2]:
        return None
    solved = ~np.isin(mate.status, (Reason.NO_KEYPOINTS, Reason.NO_VALID_BASE))
    q = mate.arm_q.copy()
    q[solved, 0] -= arm.yaw_sign * np.radians(entry[2] - mate_entry[2])
    if np.any((q[solved, 0] < arm.lo_s[0]) | (q[solved, 0] > arm.hi_s[0])):
        return None
    return _Track(q, mate.status.copy(), mate.pos_err.copy(), mate.chains.copy(), mate.settled, mate.stopped)


def _allowed_failures(critical: np.ndarray, cfg: VirtualBaseConfig) -> int:
    """How many of these critical frames a candidate may fail and still be kept."""
    return int(np.floor(cfg.critical_tolerance * np.count_nonzero(critical)))


def _first_frame(arm: ArmModel, target: np.ndarray, seeds: list, cfg: VirtualBaseConfig, clearance=None,
                 hinted: bool = False, hint_settled: float | None = None) -> tuple[IKSolution, float | None]:
    """IK of a sequence's first frame: the warm start of every later frame, so it picks the
    arm's branch (elbow up or down, shoulder left or right). The first feasible seed wins when
    its links keep clear of the operator's body by ``body_radius_m`` + 5 cm (or there is no
    body to keep clear of); otherwise every seed is tried and the feasible one with the most
    clearance wins, ``body_seeds`` more random seeds included (an elbow-up branch of a UR-type
    arm passes the operator's neck) when some seed reached the target; with none feasible, the
    closest solution (which ``search_virtual_base`` gives no neighbour as a hint). On EgoDex
    add_remove_lid 0:94, 47 of KUKA+Sharpa's 108 first frames were reached by no seed: their body
    seeds were 470 of its 829 cold IPOPT solves, and none of them reached either.

    ``hinted``: the first seed is the neighbouring candidate's solution, solved by Newton when
    it converges near it (the bases differ by a few cm: most candidates need no cold IPOPT);
    when that neighbour tried every seed and settled for a branch with ``hint_settled``
    clearance, the same branch is taken here if it keeps about as much (``SETTLED_SLACK_M``)
    without the search again. Returns the solution and the clearance it settled for (None
    when it kept the full clearance or nothing was feasible)."""
    sols = []
    need = cfg.body_radius_m + cfg.link_radius + 0.05
    n_regular = len(seeds)
    if clearance is not None and cfg.body_radius_m > 0 and len(seeds) > 1:  # more branches to choose from
        rng = np.random.default_rng(1)
        seeds = list(seeds) + [rng.uniform(arm.lo_s, arm.hi_s) for _ in range(cfg.body_seeds)]
    for i, s0 in enumerate(seeds):
        if i == n_regular and not any(ok for _, ok, _ in sols):
            break  # the body seeds look for a clearer branch, not for reach: none of the seeds reached the target
        sol = arm.solve(target, s0, near=hinted and i == 0)
        sol_ok = sol.pos_err_mm <= cfg.pos_tol_mm and sol.rot_err_deg <= cfg.rot_tol_deg
        room = clearance(sol.x) if clearance is not None and sol_ok and cfg.body_radius_m > 0 else float("inf")
        sols.append((sol, sol_ok, room))
        if sol_ok and room >= need:
            return sol, None
        if i == 0 and hinted and sol_ok and hint_settled is not None and room >= hint_settled - SETTLED_SLACK_M:
            return sol, room
    feasible = [(room, sol) for sol, sol_ok, room in sols if sol_ok]
    if feasible:
        room, best = max(feasible, key=lambda x: x[0])
        return best, room
    return min((s for s, _, _ in sols), key=lambda s: s.pos_err_mm + 10 * s.rot_err_deg), None


def _score(idx: int, grid_entry, track: _Track, arm: ArmModel, valid: np.ndarray, critical: np.ndarray,
           cfg: VirtualBaseConfig) -> CandidateScore:
    lat, fwd, yaw, Tb = grid_entry[:4]
    _split_flips(track, cfg.max_joint_step)
    st = track.status
    ok = st == Reason.OK
    solved = st != Reason.NO_VALID_BASE  # frames after ``track.stopped`` were not
    crit = critical & valid
    crit_succ = float(ok[crit].mean()) if crit.any() else 1.0
    reach = float(ok[valid].mean()) if valid.any() else 0.0
    ee = float(np.nanmean(track.pos_err[ok])) if ok.any() else float("inf")
    q = track.arm_q[ok]
    rng_ = arm.hi_s - arm.lo_s
    margin = float(np.min(np.minimum(q - arm.lo_s, arm.hi_s - q) / rng_)) if len(q) else 0.0
    cont = _max_step(track.arm_q, ok)
    reason, detail, last_resort = Reason.OK, "", False
    # a body collision is the operator's keep-out, not the robot's limit: that frame alone is rejected;
    # so is a frame past a wrist flip (``_split_flips``: the arm follows it, on another branch)
    body = st == Reason.BODY_COLLISION
    bad_crit = crit & ~ok & ~body & (st != Reason.DISCONTINUITY) & solved
    allowed = _allowed_failures(crit, cfg)
    if bad_crit.sum() > allowed:
        r = Reason(int(np.bincount(st[bad_crit]).argmax()))  # the commonest frame-level cause names the rejection
        reason = r
        seen = "" if track.stopped is None else f" by frame {track.stopped}, where the search stopped"
        detail = (f"{int(bad_crit.sum())} of {int(crit.sum())} critical frame(s) fail{seen} ({_name(r)}; {allowed} "
                  f"allowed), first {int(np.flatnonzero(bad_crit)[0])}")
    elif reach < cfg.min_reachability:
        r = Reason(int(np.bincount(st[valid & ~ok]).argmax()))
        reason = r
        detail = f"keeps {int(ok.sum())} of {int(valid.sum())} frames ({_name(r)} in most of the others)"
        # the robot itself follows enough of the sequence, only the operator's body is in the way: a base of last resort
        robot_fail = valid & ~ok & ~body
        last_resort = bool(ok.any() and robot_fail.sum() <= (1.0 - cfg.min_reachability) * valid.sum())
    return CandidateScore(idx, lat, fwd, yaw, Tb, int(reason), detail, crit_succ, reach, ee, margin, cont,
                          down=grid_entry[4] if len(grid_entry) > 4 else 0.0, last_resort=last_resort)


def _max_step(arm_q: np.ndarray, ok: np.ndarray) -> float:
    """Largest joint change (rad) between consecutive kept frames (a rejected frame's pose is never shown)."""
    kept = np.flatnonzero(ok)
    return float(np.abs(np.diff(arm_q[kept], axis=0)).max()) if len(kept) > 1 else 0.0


def _split_flips(track: _Track, max_step: float) -> None:
    """A joint that jumps more than ``max_step`` between kept frames (the warm start ran into a
    joint limit and the restart found the other branch: Panda's wrist roll on add_remove_lid)
    splits the kept frames into runs; the longest run stays, the others are rejected as
    DISCONTINUITY, frame by frame, rather than the whole base."""
    kept = np.flatnonzero(track.status == Reason.OK)
    if len(kept) < 2:
        return
    jumps = np.flatnonzero(np.abs(np.diff(track.arm_q[kept], axis=0)).max(axis=1) > max_step)
    if not len(jumps):
        return
    runs = np.split(kept, jumps + 1)
    longest = max(runs, key=len)
    for run in runs:
        if run is not longest:
            track.status[run] = Reason.DISCONTINUITY


def _name(r: Reason) -> str:
    return r.name.lower().replace("_", " ")


def _plausibility(score: CandidateScore, track: _Track, arm: ArmModel, cameras: np.ndarray, view: BaseView,
                  cfg: VirtualBaseConfig) -> None:
    """Fill ``off_corridor``, ``forearm_deg``, ``hand_hidden`` and ``screened_rate`` from up to
    ``plausibility_frames`` kept frames."""
    kept = np.flatnonzero((track.status == Reason.OK) & np.isfinite(view.limbs[:, 1]).all(-1))
    if not len(kept) or cfg.plausibility_frames == 0:
        score.off_corridor = score.forearm_deg = score.screened_rate = score.hand_hidden = float("nan")
        return
    frames = kept[np.unique(np.linspace(0, len(kept) - 1, min(cfg.plausibility_frames, len(kept))).round().astype(int))]
    first = max(int(np.argmax(arm.moving)) - 1, 0)
    meshes = len(arm.hulls[0]) > 0
    offs, angles, hidden = [], [], []
    for i in frames:
        cam_from = np.linalg.inv(cameras[i])
        pts = (cam_from[:3, :3] @ track.chains[i][:, first:] + cam_from[:3, 3:4]).T
        corridor_mask = view.corridor(int(i))
        if meshes:  # what the image will show: every link's visual hull, the base's included
            links = arm.link_points(track.arm_q[i], cam_from @ score.camera_from_base)
            robot, arm_visible = silhouette(links, view, arm.hull_is_arm)
            offs.append(silhouette_outside(links, view, corridor_mask, robot))
            hidden.append(hand_hidden(arm_visible, view.hand[i], view) if view.hand is not None else float("nan"))
        else:
            offs.append(footprint_outside(pts, view.limbs[i], view, cfg.link_radius, corridor_mask=corridor_mask))
            hidden.append(float("nan"))
        angles.append(forearm_angle(pts[1:-1], view.limbs[i]))  # from the shoulder to the wrist (not the palm centre)
    offs, hidden = np.asarray(offs, float), np.asarray(hidden, float)
    score.off_corridor = float(np.nanmean(offs)) if np.isfinite(offs).any() else float("nan")
    screened = (np.nan_to_num(offs, nan=0.0) > cfg.max_off_arm) | (np.nan_to_num(hidden, nan=0.0) > cfg.max_hand_hidden)
    score.screened_rate = float(np.mean(screened))
    score.hand_hidden = float(np.nanmean(hidden)) if np.isfinite(hidden).any() else float("nan")
    score.forearm_deg = float(np.nanmean(angles)) if np.isfinite(angles).any() else float("nan")


def reach_centre(T0: np.ndarray, targets: np.ndarray, valid: np.ndarray, arm: ArmModel, frac: float) -> tuple[np.ndarray, float]:
    """``T0`` slid along its horizontal forward axis so the median distance from the arm's first
    joint to the valid wrist targets is ``frac`` L_r (a long arm next to the human shoulder folds
    onto targets 0.3 L_r away and finds no wrist orientation: it belongs further back); returns
    the new base and the distance, in L_r, it started from."""
    pts = targets[valid, :3, 3]

    def dist(shift: float) -> float:
        T = T0.copy()
        T[:3, 3] = T0[:3, 3] + shift * T0[:3, 0]
        return float(np.median(np.linalg.norm(pts - (T[:3, :3] @ arm.shoulder + T[:3, 3]), axis=1))) / arm.reach

    lo, hi = -arm.reach, arm.reach  # distance falls with the shift over the range that matters: bisect
    for _ in range(40):
        mid = (lo + hi) / 2
        lo, hi = (lo, mid) if dist(mid) < frac else (mid, hi)
    T = T0.copy()
    T[:3, 3] = T0[:3, 3] + lo * T0[:3, 0]
    return T, dist(0.0)


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
    view: BaseView | None = None,
) -> VirtualBaseResult:
    """Search the 27 bases for one sequence (and, when none survives, a reach-aware second
    grid) and pick one by the review policy.

    targets: (T,4,4) camera_from_wrist-link targets (``ArmModel.wrist_targets``);
    up: world up in the camera frame (default: image up, -y); support_plane: (4,) (n, d)
    in the camera frame or None (check not possible); shoulders: (2,3) left/right
    shoulder in the camera frame or None; critical: (T,) frames that must be reachable
    (default: every valid frame; ``critical_tolerance`` of them may fail); init_base:
    override the grid centre; cameras: (T,4,4) the camera pose per frame in the targets'
    frame (arm links must keep out of the operator's head and torso; None: no check);
    view: the image-side measures of plausibility (None: not ranked).
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
    tracks: list[_Track] = []
    scores: list[CandidateScore] = []

    def run(grid, stage: str) -> None:
        first = int(np.flatnonzero(valid)[0])
        for k, g in enumerate(grid):
            turned = _yaw_turned(arm, grid[k - 1], g, tracks[-1]) if k and cfg.share_yaw else None
            hint = tracks[-1].arm_q[first] if tracks and tracks[-1].status[first] not in _UNREACHED else None
            tr = _evaluate(arm, g[3], targets, valid, support_plane, cfg, hint, cameras, up,
                           tracks[-1].settled if hint is not None else None, critical, turned)
            sc = _score(len(tracks), g, tr, arm, valid, critical, cfg)
            sc.stage = stage
            if sc.reason == Reason.OK and view is not None and cameras is not None:
                _plausibility(sc, tr, arm, cameras, view, cfg)
            tracks.append(tr)
            scores.append(sc)

    run(candidate_grid(T0, arm.reach), "grid")
    T1, start_frac = reach_centre(T0, targets, valid, arm, cfg.refine_reach_frac)
    diagnosis = {"target_distance_Lr": round(start_frac, 3), "grid": _causes(scores), "refined": False,
                 "plausibility": "not ranked" if view is None else
                 ("tracked arm" if view.tracked_arm else "forearm continued from the hand (the source does not track the arm)")}
    why = _why_refine(scores, cfg)
    if why:
        head = np.zeros(3) if cameras is None else cameras[int(np.flatnonzero(valid)[0])][:3, 3]
        run(refine_grid(T1, arm.reach, T0[:3, 3] - head), "refine")
        diagnosis.update(refined=True, refined_for=why, refine=_causes(scores[27:]))
    if not any(c.reason == Reason.OK for c in scores):
        _last_resort(scores, tracks, arm, cameras, view, cfg, diagnosis)
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
                                 f"no valid base among {len(scores)} candidates (most common cause: {_name(cause)}; wrist "
                                 f"targets {start_frac:.2f} L_r from the arm's first joint)",
                                 None, None, None, st, trajectories, arm_tracks, frame_status, diagnosis)
    if cfg.review == "auto_top1":
        chosen, by = ranking[0], "auto:top1"
    else:
        chosen, by = ranking[0], "pending:manual"  # provisional until `handedit review` decides
    return _with_choice(VirtualBaseResult(embodiment_id, arm.reach, scores, ranking, None, by, int(Reason.OK), "",
                                          None, None, None, np.zeros(n, STATUS_DTYPE), trajectories, arm_tracks,
                                          frame_status, diagnosis),
                        chosen, tracks[chosen], arm)


def _why_refine(scores: list[CandidateScore], cfg: VirtualBaseConfig) -> str:
    """Why the second grid is searched ("" when it is not): no survivor among the 27, or the
    best survivor's robot lies off the human arm (``refine_off_corridor``) or its forearm
    crosses the human one (``refine_forearm_deg``). The 27 span +-0.1 L_r sideways and
    no height: on EgoDex add_remove_lid 0:94 every UR5+Shadow survivor for the right hand had
    its forearm 32-43 degrees off the human one and 22-28 % of its footprint off the arm,
    where the second grid's outward and lower bases measured 18 degrees and 10 %."""
    alive = [c for c in scores if c.reason == Reason.OK]
    if not alive:
        return "no valid base"
    best = min(alive, key=CandidateScore.key)
    if np.isfinite(best.off_corridor) and best.off_corridor > cfg.refine_off_corridor:
        return f"best survivor {best.index} lies {best.off_corridor:.2f} off the arm"
    if np.isfinite(best.forearm_deg) and best.forearm_deg > cfg.refine_forearm_deg:
        return f"best survivor {best.index}'s forearm is {best.forearm_deg:.0f} degrees off the human one"
    return ""


def _last_resort(scores: list[CandidateScore], tracks: list[_Track], arm: ArmModel, cameras: np.ndarray | None,
                 view: BaseView | None, cfg: VirtualBaseConfig, diagnosis: dict) -> None:
    """No candidate of either grid survives: those the operator's body alone discarded (the
    robot follows the sequence, its arm crosses the head or torso in some frames) survive
    after all, so the sequence keeps the frames that are clear and rejects the others as
    BODY_COLLISION rather than losing every frame to NO_VALID_BASE. Ranked as usual (the
    fewest body collisions first: critical-frame success leads the key)."""
    for c in scores:
        if c.last_resort:
            c.reason = int(Reason.OK)
            c.detail = f"last resort: {c.detail}"
            if view is not None and cameras is not None:
                _plausibility(c, tracks[c.index], arm, cameras, view, cfg)
    diagnosis["last_resort"] = sum(c.last_resort for c in scores)


def _causes(scores: list[CandidateScore]) -> dict[str, int]:
    """Candidates per verdict (``ok`` or the discarding cause)."""
    out: dict[str, int] = {}
    for c in scores:
        k = _name(Reason(c.reason))
        out[k] = out.get(k, 0) + 1
    return out


def _with_choice(res: VirtualBaseResult, chosen: int, track: _Track, arm: ArmModel) -> VirtualBaseResult:
    res.chosen = chosen
    res.camera_from_base = res.candidates[chosen].camera_from_base
    res.arm_q = track.arm_q
    res.qpos = np.stack([arm.full_q(q) for q in track.arm_q])
    res.status = track.status.copy()
    return res
