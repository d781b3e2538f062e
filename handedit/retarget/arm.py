"""The arm of a hand-arm embodiment, seen from the retargeting side: which joints move the
hand's wrist link, its nominal reach L_r, a casadi IK solver and capsule geometry for
collision checks.

Built from the roster's composed hand-arm URDF (``handedit.embodiments.compose``: arm +
hand + fixed mount), or, for the ids in ``ASSEMBLIES``, from a dex-urdf ``assembly/`` URDF
loaded directly. The "human wrist -> robot wrist/TCP" SE(3) is fixed per embodiment: the
hand's ``wrist_from_root`` (roster) plus the hand URDF's own chain to its wrist keypoint
link, a link present in both URDFs (``name_map`` renames it in the composition). The arm
joints are the actuated joints on the path from the root to that link. That includes the
hand's own wrist joints (Shadow's WRJ1/WRJ2, ORCA's wrist), which the hand retargeter locks
(its free root pose does their job): here they are what lets the robot's forearm follow the
human's when the human wrist bends. Locked at 0, the forearm continued the palm, and on a
clip where the left hand works in front of the chest (EgoDex add_remove_lid) Panda+ORCA and
UR5+Shadow put their wrists inside the operator's torso in 75 and 50 of 94 frames, for
every base.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from handedit.embodiments.errors import AssetsMissing, EmbodimentError
from handedit.embodiments.kinematics import Kinematics, get_kinematics
from handedit.embodiments.roster import asset_dirs, get_embodiment, resolve_asset
from handedit.keypoints import JOINT_INDEX, WRIST
from handedit.retarget.newton import BoundedNewton, clamp
from handedit.setup_meter import metered

CM = 100.0
# A warm frame's projected Newton solution is taken when it converged this close (rad, every
# joint) to the previous frame's; otherwise IPOPT solves the frame as before. Unguarded, Newton
# sometimes followed the redundant arm's self-motion onto another IK branch (a joint step of
# 1.3-1.7 rad) where IPOPT did not, and that changed which virtual bases survived; guarded, 36
# searches (6 hand-arm embodiments, the demo and EgoDex clips) keep every candidate's verdict,
# the ranking and the choice, their joint tracks within 1.3e-6 rad of IPOPT's.
NEWTON_MAX_STEP = 0.25

# hand-arm embodiment id -> (assembly URDF relative to a dex-urdf root, hand embodiment id)
ASSEMBLIES: dict[str, tuple[str, str]] = {
    "ur5e_shadow": ("assembly/ur5e_shadow/ur5e_shadow_right_hand_glb.urdf", "shadow"),
    "xarm7_ability": ("assembly/xarm7_ability/xarm7_ability_right_hand_glb.urdf", "ability"),
    "rm75_inspire": ("assembly/rm75_inspire/rm75_inspire_right_hand.urdf", "inspire"),
}


@dataclass
class IKSolution:
    q: np.ndarray  # (dof,) full assembly vector
    pos_err_mm: float
    rot_err_deg: float
    ok: bool  # solver did not fail
    x: np.ndarray
    lam_x: np.ndarray


@dataclass(frozen=True)
class ArmSource:
    """Where an ArmModel comes from: the composed (or assembly) URDF and the hand's names in it."""

    embodiment_id: str
    urdf_path: Path
    hand_id: str  # embodiment id whose hand retargeter produces the wrist targets
    name_map: dict  # hand URDF link/joint name -> name in urdf_path (identity when absent)
    reach: float | None  # L_r from the roster/composition; None: computed here


class ArmModel:
    """IK and geometry of one hand-arm robot (build once per process: ``arm_model``)."""

    def __init__(self, src: ArmSource):
        self.embodiment_id, self.assembly, self.hand_id = src.embodiment_id, Path(src.urdf_path), src.hand_id
        self.name_map = dict(src.name_map)
        ra = resolve_asset(get_embodiment(src.hand_id))
        self.hand_kin = get_kinematics(ra.path)
        self.hand_asset = ra.asset
        self.kin: Kinematics = get_kinematics(self.assembly)
        kps = {k.mano: k for k in ra.asset.keypoints}
        self.hand_wrist_link = kps[WRIST].link  # name in the hand URDF
        self.wrist_link = self._n(kps[WRIST].link)  # name in the composed URDF
        self.wrist_offset = np.asarray(kps[WRIST].offset, float)
        self.centre_link = self._n(kps.get(JOINT_INDEX["middle_mcp"], kps[WRIST]).link)  # palm centre, for capsules
        locked = {self._n(n): v for n, v in ra.asset.locked_joints}
        path = self._path_links(self.wrist_link)
        self.path_links = path
        on_path = [self.kin._joints[l].name for l in path[1:]]  # joints whose child is on the path
        names = self.kin.joint_names
        self.arm_idx = np.array([names.index(n) for n in on_path if n in names], dtype=int)
        self.arm_joint_names = [names[i] for i in self.arm_idx]
        self.q_fixed = self.kin.neutral()
        for n, v in locked.items():
            if n in names:
                self.q_fixed[names.index(n)] = v
        self.lower, self.upper = self.kin.lower[self.arm_idx], self.kin.upper[self.arm_idx]
        self.lo_s = np.where(np.isfinite(self.lower), self.lower, -2 * np.pi)
        self.hi_s = np.where(np.isfinite(self.upper), self.upper, 2 * np.pi)
        self.n = len(self.arm_idx)
        if self.n < 6:
            raise EmbodimentError(f"{self.assembly}: only {self.n} arm joints lead to '{self.wrist_link}'; need >= 6")

        # symbolic: full q with arm joints free, the rest fixed ---------------------------
        qa = ca.SX.sym("qa", self.n)
        q_full = ca.SX(self.q_fixed)
        for j, i in enumerate(self.arm_idx):
            q_full[int(i)] = qa[j]
        T = ca.substitute(self.kin.fk_expr(self.wrist_link), self.kin.q_sym, q_full)
        p = T[:3, :3] @ ca.SX(self.wrist_offset) + T[:3, 3]
        R = T[:3, :3]
        # capsule chain: origins of the moving path links + the palm centre
        pts = [ca.substitute(self.kin.fk_expr(l)[:3, 3], self.kin.q_sym, q_full) for l in path]
        pts.append(ca.substitute(self.kin.fk_expr(self.centre_link)[:3, 3], self.kin.q_sym, q_full))
        self._chain_fn = ca.Function("chain", [qa], [ca.horzcat(*pts)])
        self._pose_fn = ca.Function("wrist", [qa], [p, R])
        self.moving = self._moving_points()
        # support-plane points: moving arm links only (the hand sits where the human hand was,
        # which may touch the table; its contact is checked by retargeting QC)
        hand_links = {self._n(l) for l in self.hand_kin.link_names}
        self.arm_points = self.moving & np.array([l not in hand_links for l in path] + [False])
        # the wrist + hand group for self-collision: hand points, palm centre, last two arm points
        self.distal = self.moving & ~self.arm_points
        self.distal[np.flatnonzero(self.arm_points)[-2:]] = True
        # the arm without its wrist end (which must reach the hand wherever it is): what has
        # to keep clear of the head
        self.proximal = self.arm_points & ~self.distal

        p_t, R_t, q_prev = ca.SX.sym("p_t", 3), ca.SX.sym("R_t", 3, 3), ca.SX.sym("q_prev", self.n)
        w_s = ca.SX.sym("w_s")
        mid = ca.SX((self.lo_s + self.hi_s) / 2)
        cost = CM * CM * ca.sumsqr(p - p_t) + 100.0 * 0.5 * ca.sumsqr(R - R_t)
        cost += w_s * ca.sumsqr(qa - q_prev) + 1e-4 * ca.sumsqr(qa - mid)
        opts = {"print_time": False, "ipopt": {
            "print_level": 0, "sb": "yes", "max_iter": 150, "tol": 1e-8, "acceptable_tol": 1e-5,
            "warm_start_init_point": "yes", "warm_start_bound_push": 1e-6, "warm_start_mult_bound_push": 1e-6,
            "mu_strategy": "adaptive",
        }}
        params = ca.vertcat(p_t, ca.vec(R_t), q_prev, w_s)
        self.solver = ca.nlpsol("arm_ik", "ipopt", {"x": qa, "p": params, "f": cost}, opts)
        self.newton = BoundedNewton("arm_ik", cost, qa, params, self.lo_s, self.hi_s, 1e-8)  # warm frames (solve)
        self.reach = float(src.reach) if src.reach else self._nominal_reach()
        # beyond L_r plus the flange->wrist length no orientation reaches the target
        last = self.kin._by_name[[n for n in self.arm_joint_names if n not in locked][-1]].child
        wrist = self.wrist_pose((self.lo_s + self.hi_s) / 2)
        flange = self.kin.fk(self.full_q((self.lo_s + self.hi_s) / 2), last)[:3, 3]
        self.max_reach = self.reach + float(np.linalg.norm(wrist[:3, 3] - flange))

    def _n(self, name: str) -> str:
        return self.name_map.get(name, name)

    # -- structure --------------------------------------------------------------------
    def _path_links(self, link: str) -> list[str]:
        out = [link]
        while out[-1] != self.kin.base_link:
            out.append(self.kin._joints[out[-1]].parent)
        return out[::-1]

    def _moving_points(self) -> np.ndarray:
        """Which chain points move with q (the rest are bolted to the base)."""
        rng = np.random.default_rng(0)
        a = self.chain(rng.uniform(self.lo_s, self.hi_s))
        b = self.chain(rng.uniform(self.lo_s, self.hi_s))
        return np.linalg.norm(a - b, axis=0) > 1e-6

    def _nominal_reach(self) -> float:
        """L_r: length of the kinematic chain from the first arm joint to the wrist link
        (sum of joint-origin offsets along the path, URDF zero pose)."""
        first = self.kin._by_name[self.arm_joint_names[0]].child
        path = self.path_links[self.path_links.index(first):]
        total = sum(float(np.linalg.norm(self.kin._joints[l].origin[:3, 3])) for l in path[1:])
        return total + float(np.linalg.norm(self.wrist_offset))

    @property
    def shoulder(self) -> np.ndarray:
        """Base-frame position of the first arm joint (reach is measured from here)."""
        first = self.kin._by_name[self.arm_joint_names[0]].child
        return self.kin.fk(self.q_fixed, first)[:3, 3]

    @functools.cached_property
    @metered
    def hulls(self) -> tuple[list[str], np.ndarray, np.ndarray]:
        """The robot's visual geometry for its footprint in the image: (links, link index per
        point, link-frame points), each mesh part's convex-hull vertices (loaded on first use)."""
        from handedit.render.model import build_model, hull_points

        model = build_model(self.assembly)
        links = model.links
        index, points = hull_points(model, links) if links else (np.zeros(0, int), np.zeros((0, 3)))
        return links, index, points

    @functools.cached_property
    def hull_is_arm(self) -> np.ndarray:
        """Per link of ``hulls``: an arm link (not part of the hand), as the renderer tags them."""
        hand = {self._n(l) for l in self.hand_kin.link_names}
        return np.array([l not in hand for l in self.hulls[0]], bool)

    @functools.cached_property
    @metered
    def _hull_links(self) -> tuple[ca.Function, list[np.ndarray]]:
        """Every hull link's base_from_link in one call (stacked side by side) and each link's
        points: ``link_points`` runs per sampled frame of every surviving candidate, and one FK
        call plus one mask per link was most of its time."""
        links, index, points = self.hulls
        fn = ca.Function("hull_links", [self.kin.q_sym], [ca.horzcat(*[self.kin.fk_expr(l) for l in links])])
        return fn, [points[index == k] for k in range(len(links))]

    def link_points(self, qa: np.ndarray, frame_from_base: np.ndarray) -> list[np.ndarray]:
        """Per link with geometry, its hull points in ``frame_from_base``'s frame at arm joints ``qa``."""
        links = self.hulls[0]
        if not links:
            return []
        fn, parts = self._hull_links
        Ts = np.asarray(fn(self.full_q(qa)), float)
        out = []
        for k, pts in enumerate(parts):
            T = frame_from_base @ Ts[:, 4 * k: 4 * k + 4]
            out.append(pts @ T[:3, :3].T + T[:3, 3])
        return out

    @functools.cached_property
    def yaw_sign(self) -> int:
        """+1 or -1 when the first arm joint turns about the base's z axis through its origin (as
        every arm of the roster but RM75's does), so that a base yawed by a turns every link the way
        that joint at q1 -/+ a does: ``chain(q) == Rz(a) chain(q - yaw_sign a e1)``; 0 otherwise.
        Checked numerically on the capsule chain (every link the search tests) at random joints."""
        rng = np.random.default_rng(0)
        qs = [rng.uniform(self.lo_s, self.hi_s) for _ in range(4)]
        a = 0.3
        Rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        for sign in (1, -1):
            shifted = [q - sign * a * np.eye(self.n)[0] for q in qs]
            if all(np.abs(Rz @ self.chain(q2) - self.chain(q)).max() < 1e-9 for q, q2 in zip(qs, shifted)):
                return sign
        return 0

    # -- numeric ----------------------------------------------------------------------
    def full_q(self, qa: np.ndarray) -> np.ndarray:
        q = self.q_fixed.copy()
        q[self.arm_idx] = qa
        return q

    def chain(self, qa: np.ndarray) -> np.ndarray:
        """(3,P) capsule-chain points in the base frame."""
        return np.asarray(self._chain_fn(np.asarray(qa, float)), float)

    def wrist_pose(self, qa: np.ndarray) -> np.ndarray:
        p, R = self._pose_fn(np.asarray(qa, float))
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = np.asarray(R, float), np.asarray(p, float).ravel()
        return T

    def solve(self, target: np.ndarray, q0: np.ndarray, q_prev: np.ndarray | None = None,
              smooth: float = 1e-2, warm: IKSolution | None = None, near: bool = False) -> IKSolution:
        """IK for base_from_wrist ``target`` (4x4) from ``q0`` (arm joints), bounded by limits.
        A warm frame (``warm``: the previous frame's solution) is solved by projected Newton
        when it stays near ``q0`` (``NEWTON_MAX_STEP``): a third of IPOPT's time on the demo
        and EgoDex clips; every other frame by IPOPT. ``near``: ``q0`` solves a neighbouring
        problem (the next base candidate's first frame): Newton is tried first there too."""
        q0 = clamp(q0, self.lo_s, self.hi_s)
        p = np.concatenate([target[:3, 3], target[:3, :3].reshape(-1, order="F"),
                            q0 if q_prev is None else q_prev, [0.0 if q_prev is None else smooth]])
        if warm is not None or near:
            xs, _, converged = self.newton.solve(q0, p)
            if converged and np.abs(xs - q0).max() <= NEWTON_MAX_STEP:
                return self._solution(target, xs, np.zeros_like(xs), True)  # no bound multipliers: IPOPT's next warm start pushes them
        args = dict(x0=q0, p=p, lbx=self.lo_s, ubx=self.hi_s)
        if warm is not None:
            args["lam_x0"] = warm.lam_x
        try:
            sol = self.solver(**args)
            status = str(self.solver.stats().get("return_status", ""))
            x = np.asarray(sol["x"], float).ravel()
            lam = np.asarray(sol["lam_x"], float).ravel()
            ok = bool(np.all(np.isfinite(x))) and status not in ("Infeasible_Problem_Detected", "Invalid_Number_Detected")
        except RuntimeError:
            x, lam, ok = q0, np.zeros_like(q0), False
        return self._solution(target, x, lam, ok)

    def _solution(self, target: np.ndarray, x: np.ndarray, lam: np.ndarray, ok: bool) -> IKSolution:
        x = clamp(x, self.lo_s, self.hi_s)
        T = self.wrist_pose(x)
        pe = float(np.linalg.norm(T[:3, 3] - target[:3, 3]) * 1000.0)
        c = min(max((np.trace(T[:3, :3].T @ target[:3, :3]) - 1) / 2, -1.0), 1.0)
        return IKSolution(self.full_q(x), pe, float(np.degrees(np.arccos(c))), ok, x, lam)

    def hand_root_from_wrist(self, hand_q: np.ndarray) -> np.ndarray:
        """hand-URDF root -> wrist link (with the wrist keypoint offset), at hand joints ``hand_q``."""
        T = self.hand_kin.fk(hand_q, self.hand_wrist_link).copy()
        T[:3, 3] = T[:3, :3] @ self.wrist_offset + T[:3, 3]
        return T

    def wrist_targets(self, root_pose: np.ndarray, hand_qpos: np.ndarray) -> np.ndarray:
        """camera_from_wrist-link (T,4,4) from a hand retargeting result (root poses + qpos)."""
        return np.stack([root_pose[i] @ self.hand_root_from_wrist(hand_qpos[i]) for i in range(len(root_pose))])

    def assembly_qpos(self, arm_q: np.ndarray, hand_qpos: np.ndarray, hand_joint_names: list[str]) -> np.ndarray:
        """Full assembly qpos (T,dof): arm joints from IK, finger joints by name from the hand;
        within the URDF's limits (the IK may end ``joint_limit_tol`` past them)."""
        names = self.kin.joint_names
        out = np.tile(self.q_fixed, (len(arm_q), 1))
        out[:, self.arm_idx] = arm_q
        arm = set(self.arm_idx.tolist())
        for j, n in enumerate(hand_joint_names):
            n = self._n(n)
            if n in names and names.index(n) not in arm:
                out[:, names.index(n)] = hand_qpos[:, j]
        lo, hi = self.kin.lower, self.kin.upper
        return np.clip(out, np.where(np.isfinite(lo), lo, -np.inf), np.where(np.isfinite(hi), hi, np.inf))


def arm_source(embodiment_id: str) -> ArmSource:
    """The roster's composition (``handedit.embodiments.compose``) for a hand-arm embodiment;
    for the legacy dex-urdf assembly ids in ``ASSEMBLIES`` the assembly URDF itself."""
    if embodiment_id not in ASSEMBLIES:
        emb = get_embodiment(embodiment_id)  # raises for unknown ids, naming the known ones
        if emb.arm is None:
            raise EmbodimentError(f"embodiment {embodiment_id!r} is hand-only: it has no arm for a virtual base")
        from handedit.embodiments.compose import compose_embodiment

        c = compose_embodiment(embodiment_id)
        return ArmSource(embodiment_id, c.urdf_path, embodiment_id, dict(c.link_map), c.nominal_reach_m)
    rel, hand_id = ASSEMBLIES[embodiment_id]
    for d in asset_dirs():
        if (d / rel).is_file():
            return ArmSource(embodiment_id, (d / rel).resolve(), hand_id, {}, None)
    raise AssetsMissing(f"hand-arm embodiment {embodiment_id!r} needs '{rel}' under a dex-urdf directory "
                        f"listed in $HANDEDIT_ASSET_DIRS (searched {[str(d) for d in asset_dirs()]}).")


@functools.lru_cache(maxsize=16)
@metered
def _build(src_key: tuple) -> ArmModel:
    emb, path, hand_id, names, reach = src_key
    return ArmModel(ArmSource(emb, Path(path), hand_id, dict(names), reach))


def arm_model(embodiment_id: str) -> ArmModel:
    """Per-process cached ``ArmModel`` of a hand-arm embodiment."""
    s = arm_source(embodiment_id)
    return _build((s.embodiment_id, str(s.urdf_path), s.hand_id, tuple(sorted(s.name_map.items())), s.reach))
