"""One embodiment's per-frame position-retargeting NLP, built once and re-solved.

Decision variables: the free joints ``q`` (box-bounded by the URDF limits) and the root
pose in the camera frame, ``camera_from_root = [R_ref * cayley(c) | t]``. ``R_ref`` is a
parameter (the initial guess's rotation), so c starts at 0 and the rotation stays well
conditioned (Cayley has no singularity below 180 degrees).

Cost (positions in cm): sum_k w_k |R p_k(q) + t - y_k|^2 + smooth_q |q - q_prev|^2
+ smooth_t |t - t_prev|^2 + smooth_r |R - R_prev|_F^2 / 2 + reg_q |q - q_neutral|^2, where
the per-point weights w_k are parameters (0 for invalid keypoints) and the smoothness
terms are switched by parameters (off on the first frame of a chunk). Building the casadi/IPOPT solver
takes ~0.1-1 s; warm-started re-solves take a few ms, hence the cache in ``api``.

A frame is solved (``method="newton"``, the default) by ``newton.BoundedNewton``: projected
Newton from a warm start, after a log-barrier path from a cold one (the first frame of a
chunk, and the vector-mode stage). IPOPT continues from the Newton point wherever Newton
does not converge; ``method="ipopt"`` uses IPOPT alone.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from handedit.embodiments.kinematics import get_kinematics
from handedit.embodiments.roster import UrdfAsset
from handedit.keypoints import FINGERTIPS, JOINT_INDEX, PARENT, WRIST
from handedit.retarget.config import RetargetConfig
from handedit.retarget.contact import PUSH_SLOTS, ContactParams
from handedit.retarget.newton import BoundedNewton, per_thread

CM = 100.0  # metres -> centimetres inside the cost
BARRIER_MUS = (1.0, 0.03)  # cm^2: 1 keeps the joints clear of their limits while the root turns into place
_FAIL = {
    "Infeasible_Problem_Detected", "Restoration_Failed", "Error_In_Step_Computation",
    "Invalid_Number_Detected", "Internal_Error", "Invalid_Problem_Definition",
    "Invalid_Option", "Not_Enough_Degrees_Of_Freedom", "Insufficient_Memory",
    "NonIpopt_Exception_Thrown", "Unrecoverable_Exception",
}


@dataclass
class FrameSolution:
    q: np.ndarray  # (dof,) full actuated vector (locked joints included)
    camera_from_root: np.ndarray  # (4,4)
    ok: bool  # solver did not fail
    x: np.ndarray  # raw decision vector (warm start)
    lam_x: np.ndarray  # bound multipliers (warm start)
    status: str
    cost: float = float("inf")


def _cayley_sx(c: ca.SX) -> ca.SX:
    K = ca.skew(c)
    return ca.SX.eye(3) + 2.0 * (K + K @ K) / (1.0 + ca.dot(c, c))


class Retargeter:
    """Position retargeting for one (URDF asset, config); see module doc."""

    def __init__(self, urdf_path: Path, asset: UrdfAsset, cfg: RetargetConfig):
        self.cfg = cfg
        self.asset = asset
        self.kin = kin = get_kinematics(urdf_path)
        self.joint_names = kin.joint_names
        locked = dict(asset.locked_joints)
        self.free = np.array([i for i, n in enumerate(kin.joint_names) if n not in locked], dtype=int)
        self.q_locked = kin.neutral()
        for n, v in locked.items():
            self.q_locked[kin.joint_names.index(n)] = v
        self.lower, self.upper = kin.lower, kin.upper
        self.q_neutral = kin.neutral()
        self.wrist_from_root = asset.wrist_from_root_matrix

        kps = asset.keypoints
        self.mano_idx = np.array([k.mano for k in kps], dtype=int)
        self.base_w = np.array([asset.weight(k.kind, cfg.weight(k.kind)) for k in kps], dtype=float)
        self.tip_rows = np.array([i for i, k in enumerate(kps) if k.mano in FINGERTIPS], dtype=int)
        self.wrist_row = next(i for i, k in enumerate(kps) if k.mano == WRIST)
        self.required = sorted({WRIST, 5, 9, 17})  # palm frame of the human keypoints
        K, nf = len(kps), len(self.free)

        # symbolic problem -------------------------------------------------------------
        qf = ca.SX.sym("qf", nf)
        t = ca.SX.sym("t", 3)
        c = ca.SX.sym("c", 3)
        q_full = ca.SX(self.q_locked)
        for j, i in enumerate(self.free):
            q_full[int(i)] = qf[j]
        P_root = kin.points_expr([(k.link, k.offset) for k in kps], q_full)  # (3,K)
        self._points_fn = ca.Function("points", [kin.q_sym], [kin.points_expr([(k.link, k.offset) for k in kps])])

        Y = ca.SX.sym("Y", 3, K)  # targets, camera frame (m)
        W = ca.SX.sym("W", K)  # per-point weights
        q_prev = ca.SX.sym("q_prev", nf)
        t_prev = ca.SX.sym("t_prev", 3)
        R_ref = ca.SX.sym("R_ref", 3, 3)  # rotation about which c is parameterised
        R_prev = ca.SX.sym("R_prev", 3, 3)
        s_q = ca.SX.sym("s_q")  # joint smoothness on/off
        s_pose = ca.SX.sym("s_pose")  # root pose smoothness on/off
        R = R_ref @ _cayley_sx(c)
        E = (R @ P_root + ca.repmat(t, 1, K) - Y) * CM
        cost = ca.sum1(W * ca.sum2((E * E).T)) if K else 0
        qn = ca.SX(self.q_neutral[self.free])
        cost += s_q * cfg.smooth_q * ca.sumsqr(qf - q_prev)
        # |R - R_prev|_F^2 / 2 ~ angle^2 for small angles
        cost += s_pose * (cfg.smooth_t * ca.sumsqr((t - t_prev) * CM) + 0.5 * cfg.smooth_r * ca.sumsqr(R - R_prev))
        cost += cfg.reg_q * ca.sumsqr(qf - qn)
        x = ca.vertcat(qf, t, c)
        p = ca.vertcat(ca.vec(Y), W, q_prev, t_prev, ca.vec(R_ref), ca.vec(R_prev), s_q, s_pose)
        self._urdf_path = str(urdf_path)
        self._sym = (q_full, R, t, P_root, cost, x, p)  # the contact problem extends this one (``_contact_problem``)
        self._contact: tuple | None = None
        opts = {
            "print_time": False,
            "ipopt": {
                "print_level": 0, "sb": "yes", "max_iter": cfg.max_iter, "tol": cfg.tol,
                "acceptable_tol": 1e-4, "hessian_approximation": "exact",
                "mu_strategy": "adaptive",
            },
        }
        if cfg.warm_start:
            opts["ipopt"].update({
                "warm_start_init_point": "yes", "warm_start_bound_push": 1e-6,
                "warm_start_mult_bound_push": 1e-6, "mu_init": 1e-4,
            })
        self._ipopt_opts = opts
        self.solver = ca.nlpsol("retarget", "ipopt", {"x": x, "p": p, "f": cost}, opts)
        self._evaluators: dict = {}
        inf = 1e20
        lo = np.where(np.isfinite(self.lower[self.free]), self.lower[self.free], -inf)
        hi = np.where(np.isfinite(self.upper[self.free]), self.upper[self.free], inf)
        self.lbx = np.concatenate([lo, np.full(6, -inf)])
        self.ubx = np.concatenate([hi, np.full(6, inf)])
        self.nf, self.K = nf, K
        self.newton = BoundedNewton("retarget", cost, x, p, self.lbx, self.ubx, cfg.tol)
        self._build_vector_solver(qf, t, c, P_root, R_ref, Y, W, kps, cfg)

    def _build_vector_solver(self, qf, t, c, P_root, R_ref, Y, W, kps, cfg: RetargetConfig) -> None:
        """Vector mode (hybrid stage 1): match bone directions/lengths, scaled to the robot.

        Each correspondence k is paired with its nearest MANO ancestor the robot also has
        (the wrist otherwise); the cost is sum_k w_k |R (P_k - P_a) - s (Y_k - Y_a)|^2 with s
        the robot/human palm-length ratio. Translation does not enter it (a tiny pull keeps
        it at its start), so the result is a kinematic-tree-aware coarse pose that the
        position stage then refines without having to unfold a bad local minimum.
        """
        present = {k.mano: i for i, k in enumerate(kps)}
        pairs = []
        for i, k in enumerate(kps):
            if k.mano == WRIST:
                continue
            a = PARENT[k.mano]
            while a != WRIST and a not in present:
                a = PARENT[a]
            if a in present:
                pairs.append((i, present[a]))
            if k.mano in FINGERTIPS and a != WRIST and WRIST in present:  # whole-finger vector too
                pairs.append((i, present[WRIST]))
        self._vec_pairs = pairs
        s_ = ca.SX.sym("s")
        t0 = ca.SX.sym("t0", 3)
        R = R_ref @ _cayley_sx(c)
        cost = 0
        for i, a in pairs:
            e = (R @ (P_root[:, i] - P_root[:, a]) - s_ * (Y[:, i] - Y[:, a])) * CM
            cost += W[i] * ca.sumsqr(e)
        cost += 1e-6 * ca.sumsqr((t - t0) * CM) + cfg.reg_q * ca.sumsqr(qf - ca.SX(self.q_neutral[self.free]))
        x = ca.vertcat(qf, t, c)
        p = ca.vertcat(ca.vec(Y), W, ca.vec(R_ref), s_, t0)
        opts = {"print_time": False, "ipopt": {"print_level": 0, "sb": "yes", "max_iter": 60, "tol": 1e-4,
                                               "acceptable_tol": 1e-3, "mu_strategy": "adaptive"}}
        self.vec_solver = ca.nlpsol("retarget_vec", "ipopt", {"x": x, "p": p, "f": cost}, opts)
        self.vec_newton = BoundedNewton("retarget_vec", cost, x, p, self.lbx, self.ubx, cfg.tol)
        mid, wr = present.get(JOINT_INDEX["middle_mcp"]), present.get(WRIST)
        P0 = np.asarray(self._points_fn(self.q_neutral), float)
        self._robot_palm_len = float(np.linalg.norm(P0[:, mid] - P0[:, wr])) if mid is not None and wr is not None else 0.0

    def vector_init(self, targets: np.ndarray, weights: np.ndarray, q0: np.ndarray, pose0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Coarse (q, camera_from_root) from vector mode; the wrist is then put on its target."""
        mid, wr = JOINT_INDEX["middle_mcp"], WRIST
        rows = {int(m): i for i, m in enumerate(self.mano_idx)}
        if mid not in rows or wr not in rows or not self._robot_palm_len:
            return q0, pose0
        human = float(np.linalg.norm(targets[rows[mid]] - targets[rows[wr]]))
        scale = self._robot_palm_len / human if human > 1e-4 else 1.0
        qf0 = np.clip(q0[self.free], self.lower[self.free], self.upper[self.free])
        x0 = np.concatenate([qf0, pose0[:3, 3], np.zeros(3)])
        p = np.concatenate([targets.T.reshape(-1, order="F"), weights, pose0[:3, :3].reshape(-1, order="F"), [scale], pose0[:3, 3]])
        xs, converged = x0, False
        if self.cfg.method == "newton":
            xs, _, converged = self.vec_newton.solve(self.vec_newton.barrier(x0, p, BARRIER_MUS), p)
        if not converged:
            try:
                sol = self.vec_solver(x0=x0, p=p, lbx=self.lbx, ubx=self.ubx)
                xs = np.asarray(sol["x"], float).ravel()
            except RuntimeError:
                return q0, pose0
        if not np.all(np.isfinite(xs)):
            return q0, pose0
        q = self.q_locked.copy()
        q[self.free] = np.clip(xs[: self.nf], self.lower[self.free], self.upper[self.free])
        pose = np.eye(4)
        pose[:3, :3] = pose0[:3, :3] @ _cayley_np(xs[self.nf + 3:])
        P = np.asarray(self._points_fn(q), float)
        pose[:3, 3] = targets[rows[wr]] - pose[:3, :3] @ P[:, rows[wr]]
        return q, pose

    # -- numeric helpers ------------------------------------------------------------------
    def robot_points(self, q: np.ndarray, camera_from_root: np.ndarray) -> np.ndarray:
        """(K,3) correspondence points of the robot in the camera frame."""
        P = per_thread(self._evaluators, self._points_fn)(q)[0].reshape(3, -1, order="F")  # (3,K)
        return (camera_from_root[:3, :3] @ P + camera_from_root[:3, 3:4]).T

    def init_pose(self, camera_from_wrist: np.ndarray) -> np.ndarray:
        return camera_from_wrist @ self.wrist_from_root

    def solve(
        self,
        targets: np.ndarray,  # (K,3) camera frame
        weights: np.ndarray,  # (K,)
        q0: np.ndarray,  # (dof,) initial guess
        pose0: np.ndarray,  # (4,4) initial guess (its rotation becomes R_ref)
        q_prev: np.ndarray | None = None,
        prev_pose: np.ndarray | None = None,
        warm: FrameSolution | None = None,
        contact: ContactParams | None = None,
    ) -> FrameSolution:
        """Solve one frame. ``q_prev`` / ``prev_pose`` switch the smoothness terms on; an active
        ``contact`` solves the contact problem (``contact`` module) instead."""
        qf0 = np.clip(q0[self.free], self.lower[self.free], self.upper[self.free])
        R_ref = pose0[:3, :3]
        x0 = np.concatenate([qf0, pose0[:3, 3], np.zeros(3)])
        p = np.concatenate([
            targets.T.reshape(-1, order="F"), weights,
            qf0 if q_prev is None else q_prev[self.free],
            pose0[:3, 3] if prev_pose is None else prev_pose[:3, 3],
            R_ref.reshape(-1, order="F"),
            (R_ref if prev_pose is None else prev_pose[:3, :3]).reshape(-1, order="F"),
            [0.0 if q_prev is None else 1.0, 0.0 if prev_pose is None else 1.0],
        ])
        newton, solver = self.newton, self.solver
        if contact is not None and contact.active:
            newton, solver = self._contact_problem()
            p = np.concatenate([p, contact.vector()])
        if self.cfg.method == "newton":  # cold frames first follow the barrier path (module doc)
            xs, f, converged = newton.solve(x0 if warm is not None else newton.barrier(x0, p, BARRIER_MUS), p)
            if converged:
                return self._solution(xs, R_ref, np.zeros_like(xs), "Solve_Succeeded", f, True)
            x0 = xs  # IPOPT from the Newton point
        args = dict(x0=x0, p=p, lbx=self.lbx, ubx=self.ubx)
        if warm is not None and self.cfg.warm_start:
            args["lam_x0"] = warm.lam_x
        try:
            sol = solver(**args)
            st = solver.stats()
            status = str(st.get("return_status", ""))
            xs = np.asarray(sol["x"], float).ravel()
            lam = np.asarray(sol["lam_x"], float).ravel()
            f = float(sol["f"])
        except RuntimeError as e:  # casadi raises on hard IPOPT errors
            status, xs, lam, f = f"exception: {e}", x0, np.zeros_like(x0), float("inf")
        ok = status not in _FAIL and not status.startswith("exception") and bool(np.all(np.isfinite(xs)))
        if not ok:
            xs = x0
        return self._solution(xs, R_ref, lam, status, f, ok)

    @functools.cached_property
    def contact_links(self) -> list[str]:
        """The links with visual surface samples: the contact problem's push-out slots, in order."""
        from handedit.retarget.qc import surface_samples

        return [name for name in surface_samples(self._urdf_path, 64) if name in self.kin.link_names]

    def link_samples(self, q: np.ndarray, camera_from_root: np.ndarray, n: int = 64) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Per contact link: its surface samples in the camera frame and in its own frame."""
        from handedit.retarget.qc import surface_samples

        samples = surface_samples(self._urdf_path, n)
        cam, local = [], []
        for name in self.contact_links:
            T = camera_from_root @ self.kin.fk(q, name)
            cam.append(samples[name] @ T[:3, :3].T + T[:3, 3])
            local.append(samples[name])
        return cam, local

    def _contact_problem(self):
        """(Newton, IPOPT) of the cost with the contact terms (built on first use: most frames of
        most clips are far from any object, and these terms cost an FK per link)."""
        if self._contact is None:
            q_full, R, t, P_root, cost, x, p = self._sym
            n_t, n_l = len(self.tip_rows), len(self.contact_links) * PUSH_SLOTS
            tn, to, tw = ca.SX.sym("tn", 3, n_t), ca.SX.sym("to", n_t), ca.SX.sym("tw", n_t)
            pp, pn = ca.SX.sym("pp", 3, n_l), ca.SX.sym("pn", 3, n_l)
            po, pw = ca.SX.sym("po", n_l), ca.SX.sym("pw", n_l)
            for j, r in enumerate(self.tip_rows):  # touch: the robot tip on the human tip's tangent plane
                tip = R @ P_root[:, int(r)] + t
                cost += tw[j] * ((ca.dot(tn[:, j], tip) - to[j]) * CM) ** 2
            for li, name in enumerate(self.contact_links):  # push-out: samples that sank back outside their planes
                T = self.kin.fk_expr(name, q_full)
                for j in range(li * PUSH_SLOTS, (li + 1) * PUSH_SLOTS):
                    pt = R @ (T[:3, :3] @ pp[:, j] + T[:3, 3]) + t
                    cost += pw[j] * ca.fmax(0, (po[j] - ca.dot(pn[:, j], pt)) * CM) ** 2
            p_c = ca.vertcat(p, ca.vec(tn), to, tw, ca.vec(pp), ca.vec(pn), po, pw)
            self._contact = (BoundedNewton("retarget_contact", cost, x, p_c, self.lbx, self.ubx, self.cfg.tol),
                             ca.nlpsol("retarget_contact", "ipopt", {"x": x, "p": p_c, "f": cost}, self._ipopt_opts))
        return self._contact

    def _solution(self, xs: np.ndarray, R_ref: np.ndarray, lam: np.ndarray, status: str, f: float, ok: bool) -> FrameSolution:
        q = self.q_locked.copy()
        q[self.free] = np.clip(xs[: self.nf], self.lower[self.free], self.upper[self.free])
        pose = np.eye(4)
        pose[:3, :3] = R_ref @ _cayley_np(xs[self.nf + 3:])
        pose[:3, 3] = xs[self.nf: self.nf + 3]
        return FrameSolution(q, pose, ok, xs, lam, status, f if ok else float("inf"))


def _cayley_np(c: np.ndarray) -> np.ndarray:
    from handedit.retarget.palm import cayley

    return cayley(c)
