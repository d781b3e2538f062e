"""Bound-constrained Newton for the small dense problems of retargeting, on casadi's exact
derivatives (the per-frame hand fit, ``solver``).

Why not IPOPT for every solve: these problems have 20-30 variables, and IPOPT spends ~0.5 ms
of machinery per iteration on them where one cost+gradient+Hessian evaluation costs ~0.1 ms.

- ``solve``: projected Newton (Bertsekas 1982). Variables at a bound whose gradient pushes
  outward are held; the Newton step of the others is damped until the Hessian is positive
  definite; an Armijo search runs along the projected arc. From a warm start (the previous
  frame's solution) it converges in a few iterations.
- ``barrier``: from a cold start a pure projected Newton lands on the first bounds it meets
  and settles in worse minima (the Leap hand: cost 38.5 against IPOPT's 28.3), so cold
  starts first follow a primal log-barrier path (a few barrier weights, a few damped Newton
  steps each, kept inside the bounds by the fraction-to-boundary rule), which is what let
  IPOPT's interior-point method find the lower minima.

Callers keep IPOPT for whatever does not converge here. The arm IK (``arm.ArmModel.solve``)
uses it on warm frames only, and only where it stays near the previous frame's joints: from
cold seeds its straight steps crawl along a redundant arm's self-motion, and unguarded it
sometimes changed IK branch where IPOPT did not.
"""

from __future__ import annotations

import threading

import casadi as ca
import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs

from handedit.retarget.compiled import compiled

INF = 1e19  # |bound| at or beyond this: no bound (casadi/IPOPT's convention is 1e19-1e20)


class Evaluator:
    """Calls a casadi Function on float64 arrays through its buffer: no DM conversions (the
    Python call converts every argument and result, ~0.1 ms of a ~0.1 ms evaluation). A
    buffer is one call's memory: one Evaluator per thread (``per_thread``)."""

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


def per_thread(cache: dict, fn: ca.Function) -> Evaluator:
    """This thread's Evaluator of ``fn`` in ``cache``."""
    key = (id(fn), threading.get_ident())
    if key not in cache:
        cache[key] = Evaluator(fn)
    return cache[key]


def clamp(x: np.ndarray, lo, hi) -> np.ndarray:
    """``x`` clamped to [lo, hi], as np.clip gives it: np.clip's dispatch costs more than its work
    on the few joints and segments of the arm's search, where it runs hundreds of thousands of times."""
    return np.minimum(np.maximum(x, lo), hi)


def damped_solve(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """H^-1 g with H + mu I made positive definite (mu grown from 0 until Cholesky succeeds;
    past 1e6 x the largest diagonal entry, the scaled gradient). LAPACK's potrf/potrs
    directly: numpy's cholesky and two solves cost ten times the arithmetic at this size."""
    mu, scale = 0.0, max(1e-8, float(np.abs(np.diag(H)).max(initial=0.0)))
    while mu <= 1e6 * scale:
        A = H
        if mu:  # H + mu I, bit for bit, without building I (most calls are damped at least once)
            A = H + 0.0
            A.flat[:: len(g) + 1] += mu
        L, info = dpotrf(A, lower=True, clean=False)
        if info == 0:
            return dpotrs(L, g, lower=True)[0]
        mu = max(2.0 * mu, 1e-6 * scale)
    return g / scale


class BoundedNewton:
    """min_x f(x; p) subject to lo <= x <= hi, for one casadi cost expression (module doc)."""

    def __init__(self, name: str, cost: ca.SX, x: ca.SX, p: ca.SX, lo: np.ndarray, hi: np.ndarray, tol: float):
        hess, grad = ca.hessian(cost, x)
        f = compiled(ca.Function(f"{name}_f", [x, p], [cost]))
        fgh = compiled(ca.Function(f"{name}_fgh", [x, p], [cost, grad, ca.densify(hess)]))
        self._f, self._fgh, self.evaluation = f.fn, fgh.fn, fgh.how  # handedit.retarget.compiled
        self.lo, self.hi, self.tol = np.asarray(lo, float), np.asarray(hi, float), float(tol)
        self._evaluators: dict = {}

    def solve(self, x0: np.ndarray, p: np.ndarray, max_iter: int = 40) -> tuple[np.ndarray, float, bool]:
        """(x, cost, converged): projected Newton from x0. Converged: the projected gradient's
        largest entry is below ``tol`` x max(1, cost), or a step moves no variable by more
        than 1e-9 or gains less than 1e-10 of the cost."""
        lo, hi, tol = self.lo, self.hi, self.tol
        fgh, cost = per_thread(self._evaluators, self._fgh), per_thread(self._evaluators, self._f)
        n = len(x0)
        x = clamp(x0, lo, hi)
        for _ in range(max_iter):
            fv, gv, hv = fgh(x, p)
            f, g, H = float(fv[0]), gv.copy(), hv.reshape(n, n)
            if not np.isfinite(f + g.sum() + hv.sum()):  # a NaN or inf anywhere propagates into the sum
                return x, f, False
            free = ~(((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0)))
            if np.abs(g[free]).max(initial=0.0) <= tol * max(1.0, f):
                return x, f, True
            if free.all():  # the usual case: no np.ix_ copy (0.45 s of KUKA+Sharpa's 3.3 s of Newton per EgoDex clip)
                d = -damped_solve(H, g)
            else:
                d = np.zeros_like(x)
                d[free] = -damped_solve(H[np.ix_(free, free)], g[free])
            t = 1.0
            while t > 1e-6:
                xn = clamp(x + t * d, lo, hi)
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

    def barrier(self, x0: np.ndarray, p: np.ndarray, mus: tuple[float, ...], steps: int = 6) -> np.ndarray:
        """A point near the end of the log-barrier path from x0: for each barrier weight mu (in
        the cost's units), up to ``steps`` damped Newton steps on cost - mu sum(log(x - lo) +
        log(hi - x)), each kept 1 % short of the bounds, until the barrier gradient is below
        10 mu. Start ``solve`` from it."""
        lo, hi = self.lo, self.hi
        fgh, cost = per_thread(self._evaluators, self._fgh), per_thread(self._evaluators, self._f)
        bl, bh = lo > -INF, hi < INF
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
                d = -damped_solve(H, g)
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
