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

A warm-started frame (``method="newton"``, the default) is solved by a projected Newton
method on the bound-constrained problem (Bertsekas 1982): the exact gradient and Hessian
come from one casadi function (called through its buffer), variables at a bound whose
gradient pushes outward are held, the Newton step of the others is damped until the
Hessian is positive definite, and an Armijo search runs along the projected arc. A few
iterations of a 20-30 variable dense system replace IPOPT, which spent most of its ~4 ms
per frame in its own machinery (the function evaluations were ~0.7 ms). A cold frame
(and the vector-mode stage) is far from its solution: there a pure projected Newton lands on
the first joint limits it meets and settles in worse minima (Leap: cost 38.5 against
IPOPT's 28.3), so it first follows a primal log-barrier path (two barrier weights, a few
damped Newton steps each, kept inside the bounds by the fraction-to-boundary rule), which is
what let IPOPT's interior-point method find the lower minima, without its per-iteration
overhead (~0.5 ms). IPOPT continues from the Newton point wherever Newton does not converge.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs

from handedit.embodiments.kinematics import get_kinematics
from handedit.embodiments.roster import UrdfAsset
from handedit.keypoints import FINGERTIPS, JOINT_INDEX, PARENT, WRIST
from handedit.retarget.config import RetargetConfig

CM = 100.0  # metres -> centimetres inside the cost
_FAIL = {
    "Infeasible_Problem_Detected", "Restoration_Failed", "Error_In_Step_Computation",
    "Invalid_Number_Detected", "Internal_Error", "Invalid_Problem_Definition",
    "Invalid_Option", "Not_Enough_Degrees_Of_Freedom", "Insufficient_Memory",
    "NonIpopt_Exception_Thrown", "Unrecoverable_Exception",
}


_POSITION, _VECTOR = ("_fgh", "_f"), ("_vec_fgh", "_vec_f")  # the two problems' evaluators (``_newton``)


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
        self.base_w = np.array([cfg.weight(k.kind) for k in kps], dtype=float)
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
        self.solver = ca.nlpsol("retarget", "ipopt", {"x": x, "p": p, "f": cost}, opts)
        hess, grad = ca.hessian(cost, x)
        self._f = ca.Function("f", [x, p], [cost])
        self._fgh = ca.Function("fgh", [x, p], [cost, grad, ca.densify(hess)])
        self._evaluators: dict = {}
        self._build_vector_solver(qf, t, c, P_root, R_ref, Y, W, kps, cfg)
        inf = 1e20
        lo = np.where(np.isfinite(self.lower[self.free]), self.lower[self.free], -inf)
        hi = np.where(np.isfinite(self.upper[self.free]), self.upper[self.free], inf)
        self.lbx = np.concatenate([lo, np.full(6, -inf)])
        self.ubx = np.concatenate([hi, np.full(6, inf)])
        self.nf, self.K = nf, K

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
        hess, grad = ca.hessian(cost, x)
        self._vec_f = ca.Function("vec_f", [x, p], [cost])
        self._vec_fgh = ca.Function("vec_fgh", [x, p], [cost, grad, ca.densify(hess)])
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
            xs, _, converged = self._newton(self._barrier(x0, p, _VECTOR), p, _VECTOR)
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
        P = self._evaluator("_points_fn")(q)[0].reshape(3, -1, order="F")  # (3,K)
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
    ) -> FrameSolution:
        """Solve one frame. ``q_prev`` / ``prev_pose`` switch the smoothness terms on."""
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
        if self.cfg.method == "newton":  # cold frames first follow the barrier path (module doc)
            xs, f, converged = self._newton(x0 if warm is not None else self._barrier(x0, p, _POSITION), p, _POSITION)
            if converged:
                return self._solution(xs, R_ref, np.zeros_like(xs), "Solve_Succeeded", f, True)
            x0 = xs  # IPOPT from the Newton point
        args = dict(x0=x0, p=p, lbx=self.lbx, ubx=self.ubx)
        if warm is not None and self.cfg.warm_start:
            args["lam_x0"] = warm.lam_x
        try:
            sol = self.solver(**args)
            st = self.solver.stats()
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

    def _solution(self, xs: np.ndarray, R_ref: np.ndarray, lam: np.ndarray, status: str, f: float, ok: bool) -> FrameSolution:
        q = self.q_locked.copy()
        q[self.free] = np.clip(xs[: self.nf], self.lower[self.free], self.upper[self.free])
        pose = np.eye(4)
        pose[:3, :3] = R_ref @ _cayley_np(xs[self.nf + 3:])
        pose[:3, 3] = xs[self.nf: self.nf + 3]
        return FrameSolution(q, pose, ok, xs, lam, status, f if ok else float("inf"))

    def _evaluator(self, name: str) -> "_Evaluator":
        key = (name, threading.get_ident())  # a buffer is one call's memory: one per thread
        if key not in self._evaluators:
            self._evaluators[key] = _Evaluator(getattr(self, name))
        return self._evaluators[key]

    def _barrier(self, x0: np.ndarray, p: np.ndarray, fns: tuple[str, str], mus: tuple[float, ...] = (1.0, 0.03),
                 steps: int = 6) -> np.ndarray:
        """A point near the end of the log-barrier path from x0 (module doc): for each barrier
        weight mu, up to ``steps`` damped Newton steps on cost - mu sum(log(x - lo) + log(hi - x)),
        each kept 1 % short of the bounds, until the barrier gradient is below 10 mu. Weights
        are in the cost's units (cm^2): mu = 1 keeps the joints clear of their limits while the
        root turns into place; 0.03 is close enough for the projected Newton to finish."""
        lo, hi = self.lbx, self.ubx
        fgh, cost = self._evaluator(fns[0]), self._evaluator(fns[1])
        bl, bh = lo > -1e19, hi < 1e19
        n = len(x0)
        push = 0.01 * np.where(bl & bh, hi - lo, 1.0)  # IPOPT's bound_push, relative to the range
        x = np.clip(x0, np.where(bl, lo + push, -np.inf), np.where(bh, hi - push, np.inf))

        def log_barrier(z: np.ndarray) -> float:
            return float(np.log(z[bl] - lo[bl]).sum() + np.log(hi[bh] - z[bh]).sum())

        for mu in mus:
            for _ in range(steps):
                fv, gv, hv = fgh(x, p)
                dl, dh = np.where(bl, x - lo, np.inf), np.where(bh, hi - x, np.inf)
                g = gv - mu / dl + mu / dh
                H = hv.reshape(n, n) + np.diag(mu / dl**2 + mu / dh**2)
                if not np.isfinite(fv[0] + g.sum() + H.sum()):
                    return x
                if np.abs(g).max() <= 10.0 * mu:
                    break
                d = -_damped_solve(H, g)
                with np.errstate(divide="ignore"):  # fraction to the boundary: 99 % of the way at most
                    t = min(1.0, float(np.min(np.where(d < 0, -0.99 * dl / d, np.inf))),
                            float(np.min(np.where(d > 0, 0.99 * dh / d, np.inf))))
                phi = float(fv[0]) - mu * log_barrier(x)
                while t > 1e-8:
                    xn = x + t * d
                    if float(cost(xn, p)[0][0]) - mu * log_barrier(xn) <= phi + 1e-4 * t * float(g @ d):
                        break
                    t *= 0.5
                else:
                    break  # no descent at this weight: on to the next
                x = xn
        return x

    def _newton(self, x0: np.ndarray, p: np.ndarray, fns: tuple[str, str] = _POSITION,
                max_iter: int = 40) -> tuple[np.ndarray, float, bool]:
        """(x, cost, converged): projected Newton from x0 (module doc) on the problem whose
        (cost+gradient+Hessian, cost) functions ``fns`` names. Converged: the projected
        gradient's largest entry is below ``tol`` x max(1, cost), or a step moves no variable
        by more than 1e-9 or gains less than 1e-10 of the cost."""
        lo, hi, tol = self.lbx, self.ubx, self.cfg.tol
        fgh, cost = self._evaluator(fns[0]), self._evaluator(fns[1])
        n = len(x0)
        x = np.clip(x0, lo, hi)
        for _ in range(max_iter):
            fv, gv, hv = fgh(x, p)
            f, g, H = float(fv[0]), gv.copy(), hv.reshape(n, n)
            held = ((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0))
            free = ~held
            if not np.isfinite(f + g.sum() + hv.sum()):  # a NaN or inf anywhere propagates into the sum
                return x, f, False
            if np.abs(g[free]).max(initial=0.0) <= tol * max(1.0, f):
                return x, f, True
            d = np.zeros_like(x)
            d[free] = -_damped_solve(H[np.ix_(free, free)], g[free])
            t = 1.0
            while t > 1e-6:
                xn = np.clip(x + t * d, lo, hi)
                fn = float(cost(xn, p)[0][0])
                if fn <= f + 1e-4 * float(g @ (xn - x)):
                    break
                t *= 0.5
            else:
                return x, f, False  # no descent along the arc
            step, gain = np.abs(xn - x).max(), f - fn
            x, f = xn, fn
            if step <= 1e-9 or gain <= 1e-10 * max(1.0, f):  # Newton's gains shrink quadratically: this is the floor
                return x, f, True
        return x, f, False


class _Evaluator:
    """Calls a casadi Function on float64 arrays through its buffer: no DM conversions (the
    Python call converts every argument and result, ~0.1 ms of a ~0.1 ms evaluation)."""

    def __init__(self, fn: ca.Function):
        self.args = [np.zeros(fn.nnz_in(i)) for i in range(fn.n_in())]
        self.res = [np.zeros(fn.nnz_out(i)) for i in range(fn.n_out())]
        self._buf, self._call = fn.buffer()
        for i, a in enumerate(self.args):
            self._buf.set_arg(i, memoryview(a))
        for i, r in enumerate(self.res):
            self._buf.set_res(i, memoryview(r))

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        for a, v in zip(self.args, args):
            a[:] = np.ravel(v)
        self._call()
        return self.res


def _damped_solve(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """H^-1 g with H + mu I made positive definite (mu grown from 0 until Cholesky succeeds;
    past 1e6 x the largest diagonal entry, the scaled gradient). LAPACK's potrf/potrs
    directly: numpy's cholesky and two solves cost ten times the arithmetic at this size."""
    mu, scale = 0.0, max(1e-8, float(np.abs(np.diag(H)).max(initial=0.0)))
    while mu <= 1e6 * scale:
        L, info = dpotrf(H + mu * np.eye(len(g)) if mu else H, lower=True, clean=False)
        if info == 0:
            return dpotrs(L, g, lower=True)[0]
        mu = max(2.0 * mu, 1e-6 * scale)
    return g / scale


def _cayley_np(c: np.ndarray) -> np.ndarray:
    from handedit.retarget.palm import cayley

    return cayley(c)
