"""Closed linkages that a URDF tree leaves open, solved once and written as data.

RoHand drives each finger with a linear actuator through two closed loops (a slider-crank
to the proximal phalanx, a four-bar to the distal one), but its URDF is an open tree: every
passive joint is free, so only the zero pose is right as shipped. The real hand has one
degree of freedom per actuator, so every passive joint is a function of its actuator.

The loops are data (``Loop``): the two links a pin joins, with the pin located at the zero
pose from the vendor's link lengths (the circle of radius ``ra`` about the origin of joint
``a_about`` meets the circle of radius ``rb`` about joint ``b_about``'s origin, in the plane
normal to the latter's axis; ``branch`` picks one of the two intersections). A ``rod`` loop
joins two points by a rigid bar that the URDF does not model (``length`` > 0). ``solve``
closes the loops over the actuator range by Gauss-Newton on the open tree's casadi FK,
``fit`` turns each passive joint's curve into a polynomial of its actuator, and the derived
URDF (``handedit.embodiments.derive``) writes it as a ``<mimic>`` whose ``multiplier`` and
``offset`` are the best straight line (for tools that only read URDF) and whose
``handedit_poly`` attribute holds the polynomial, which the project's kinematics and
renderer evaluate. So retargeting sees the actuators only, and rendering the full vector.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

POLY_ATTR = "handedit_poly"
POLY_DEGREE = 12


@dataclass(frozen=True)
class Loop:
    """One closure: a point on link ``a`` meets a point on link ``b`` (``length`` 0, a pin),
    or stays ``length`` metres from it (a rod the URDF does not model)."""

    a: str  # link
    a_about: str  # joint whose origin the point on ``a`` circles
    ra: float  # metres
    b: str
    b_about: str
    rb: float
    branch: int = 1
    length: float = 0.0
    b_point: tuple[float, float, float] | None = None  # the point on ``b`` given directly (link frame)


@dataclass(frozen=True)
class Linkage:
    """The passive joints one actuator drives, through ``loops``."""

    actuator: str
    passive: tuple[str, ...]
    loops: tuple[Loop, ...]


@dataclass(frozen=True)
class PolyMimic:
    """joint value = sum_k coeffs[k] u^k with u the actuator mapped from [lo, hi] to [-1, 1]."""

    source: str
    lo: float
    hi: float
    coeffs: tuple[float, ...]

    def __call__(self, x):
        """Works for floats, numpy arrays and casadi expressions alike (Horner)."""
        u = (2.0 * x - (self.lo + self.hi)) / (self.hi - self.lo)
        v = self.coeffs[-1] + 0.0 * u
        for c in self.coeffs[-2::-1]:
            v = v * u + c
        return v

    def attr(self) -> str:
        return " ".join(repr(float(v)) for v in (self.lo, self.hi, *self.coeffs))

    @classmethod
    def parse(cls, source: str, text: str) -> "PolyMimic":
        vals = [float(t) for t in text.split()]
        return cls(source, vals[0], vals[1], tuple(vals[2:]))


# ---------------------------------------------------------------------------------------
# solving (on the open tree, where every joint is a column of q)

def _circle_meet(c1, r1, c2, r2, normal, branch) -> np.ndarray:
    """The intersection of two circles in the plane through ``c2`` normal to ``normal``."""
    n = normal / np.linalg.norm(normal)
    c1 = c1 - np.dot(c1 - c2, n) * n
    d = np.linalg.norm(c1 - c2)
    ex = (c1 - c2) / d
    a = (r2**2 - r1**2 + d**2) / (2 * d)
    if a * a > r2 * r2:
        raise ValueError(f"circles of radius {r1} and {r2}, {d} apart, do not meet")
    return c2 + a * ex + branch * np.sqrt(r2**2 - a**2) * np.cross(n, ex)


def pin_points(kin, loop: Loop) -> tuple[np.ndarray, np.ndarray]:
    """The loop's points in the frames of links ``a`` and ``b``, located at the zero pose."""
    q0 = np.zeros(kin.dof)

    def joint_frame(name):
        j = kin._by_name[name]
        T = kin.fk(q0, j.parent) @ j.origin
        return T[:3, 3], T[:3, :3] @ j.axis

    def to_link(link, p):
        T = np.linalg.inv(kin.fk(q0, link))
        return T[:3, :3] @ p + T[:3, 3]

    ca_, _ = joint_frame(loop.a_about)
    cb, axis = joint_frame(loop.b_about)
    if loop.b_point is not None:
        Tb = kin.fk(q0, loop.b)
        pb_world = Tb[:3, :3] @ np.asarray(loop.b_point) + Tb[:3, 3]
        pa_world = _circle_meet(pb_world, loop.length, ca_, loop.ra, axis, loop.branch)
        return to_link(loop.a, pa_world), np.asarray(loop.b_point, float)
    p = _circle_meet(ca_, loop.ra, cb, loop.rb, axis, loop.branch)
    return to_link(loop.a, p), to_link(loop.b, p)


def _residual(kin, loops: tuple[Loop, ...]):
    import casadi as ca

    q = kin.q_sym
    res = []
    for loop in loops:
        pa, pb = pin_points(kin, loop)
        Ta, Tb = kin.fk_expr(loop.a), kin.fk_expr(loop.b)
        gap = Ta[:3, :3] @ ca.DM(pa) + Ta[:3, 3] - Tb[:3, :3] @ ca.DM(pb) - Tb[:3, 3]
        res.append(gap if loop.length == 0 else ca.sqrt(ca.sumsqr(gap)) - loop.length)
    return q, ca.vertcat(*res)


def closure_gaps(kin, linkage: Linkage, q: np.ndarray) -> np.ndarray:
    """Per loop, how far the loop is from closed at ``q`` (metres): pin gap, rod length error."""
    out = []
    for loop in linkage.loops:
        pa, pb = pin_points(kin, loop)
        Ta, Tb = kin.fk(q, loop.a), kin.fk(q, loop.b)
        gap = np.linalg.norm(Ta[:3, :3] @ pa + Ta[:3, 3] - Tb[:3, :3] @ pb - Tb[:3, 3])
        out.append(gap if loop.length == 0 else abs(gap - loop.length))
    return np.asarray(out)


def solve(kin, linkage: Linkage, values: np.ndarray, tol: float = 1e-12) -> np.ndarray:
    """(len(values), len(passive)) passive joint values closing the loops for each actuator
    value, by Gauss-Newton continued outwards from the zero pose (where the loops close by
    construction), so each curve stays on the assembled branch of the mechanism."""
    import casadi as ca

    idx = [kin.joint_names.index(j) for j in linkage.passive]
    a = kin.joint_names.index(linkage.actuator)
    q, r = _residual(kin, linkage.loops)
    f = ca.Function("closure", [q], [r, ca.jacobian(r, q)[:, idx]])
    values = np.asarray(values, float)
    out = np.zeros((len(values), len(idx)))
    order = np.argsort(np.abs(values))
    for side in (values >= 0, values < 0):
        x = np.zeros(len(idx))
        for i in order[side[order]]:
            qv = np.zeros(kin.dof)
            qv[a] = values[i]
            for _ in range(50):
                qv[idx] = x
                rv, J = (np.asarray(m, float) for m in f(qv))
                step = np.linalg.lstsq(J, -rv.ravel(), rcond=None)[0]
                x = x + step
                if np.linalg.norm(step) < tol:
                    break
            out[i] = x
    return out


def fit(kin, linkage: Linkage, samples: int = 97) -> dict[str, tuple[PolyMimic, float, float]]:
    """Per passive joint: (its polynomial of the actuator over the actuator's limits, and the
    straight line's multiplier and offset)."""
    a = kin.joint_names.index(linkage.actuator)
    lo, hi = float(kin.lower[a]), float(kin.upper[a])
    xs = np.linspace(lo, hi, samples)
    ys = solve(kin, linkage, xs)
    u = (2 * xs - (lo + hi)) / (hi - lo)
    out = {}
    for k, joint in enumerate(linkage.passive):
        coeffs = np.polynomial.polynomial.polyfit(u, ys[:, k], POLY_DEGREE)
        slope, intercept = np.polyfit(xs, ys[:, k], 1)
        out[joint] = (PolyMimic(linkage.actuator, lo, hi, tuple(float(c) for c in coeffs)), float(slope), float(intercept))
    return out


# ---------------------------------------------------------------------------------------
# reading them back

@functools.lru_cache(maxsize=64)
def _poly_mimics(path: str, mtime_ns: int) -> dict[str, PolyMimic]:
    from lxml import etree

    out = {}
    for j in etree.parse(path).getroot().findall("joint"):
        m = j.find("mimic")
        if m is not None and m.get(POLY_ATTR):
            out[j.get("name")] = PolyMimic.parse(m.get("joint"), m.get(POLY_ATTR))
    return out


def poly_mimics(urdf_path: str | Path) -> dict[str, PolyMimic]:
    """{joint: PolyMimic} of a URDF's polynomial mimic joints (empty for ordinary URDFs)."""
    p = Path(urdf_path).resolve()
    return _poly_mimics(str(p), p.stat().st_mtime_ns)


def update_cfg(urdf, q: np.ndarray, polys: dict[str, PolyMimic]) -> None:
    """yourdfpy ``update_cfg`` that evaluates polynomial mimics (yourdfpy itself applies only
    their straight-line multiplier and offset)."""
    import trimesh.transformations as tra

    q = np.asarray(q, dtype=float)
    urdf.update_cfg(q)
    if not polys:
        return
    names = urdf.actuated_joint_names
    for name, pm in polys.items():
        j = urdf.joint_map[name]
        v = float(pm(q[names.index(pm.source)]))
        origin = np.eye(4) if j.origin is None else j.origin
        if j.type == "prismatic":
            m = origin @ tra.translation_matrix(v * np.asarray(j.axis))
        else:
            m = origin @ tra.rotation_matrix(v, j.axis)
        urdf.scene.graph.update(frame_from=j.parent, frame_to=j.child, matrix=m)
