"""Symbolic forward kinematics (casadi) built from a URDF joint tree.

The retargeter differentiates FK inside IPOPT, so FK is a casadi expression of the
actuated joint vector ``q`` whose column order is ``yourdfpy.URDF.actuated_joint_names``:
that order is the qpos column order of the whole project. Mimic joints are derived
(``multiplier * q[src] + offset``, or the polynomial of ``handedit.embodiments.linkage``
where the derived URDF carries one), never columns of qpos.

Joint limits: revolute/prismatic use the URDF <limit>; continuous joints get +-inf in
``lower``/``upper`` (the solver bound) and +-pi in ``sample_lower``/``sample_upper``.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from handedit.embodiments.errors import BrokenUrdf
from handedit.embodiments.linkage import poly_mimics
from handedit.embodiments.urdf import load_urdf
from handedit.setup_meter import metered

_MOVABLE = ("revolute", "continuous", "prismatic")


@dataclass(frozen=True)
class _Joint:
    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray  # (4,4) parent_from_joint at q=0
    axis: np.ndarray  # (3,)
    q_index: int  # column in q for actuated joints, -1 otherwise
    mimic: tuple[str, float, float] | None  # (source joint, multiplier, offset)


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=float)


class Kinematics:
    """FK of one URDF as casadi expressions / Functions (build once, call many times)."""

    def __init__(self, urdf_path: str | os.PathLike):
        self.urdf_path = Path(urdf_path).resolve()
        urdf = load_urdf(self.urdf_path, load_meshes=False)
        self.base_link: str = urdf.base_link
        self.joint_names: list[str] = list(urdf.actuated_joint_names)
        self.link_names: list[str] = [l.name for l in urdf.robot.links]
        self.dof = len(self.joint_names)
        idx = {n: i for i, n in enumerate(self.joint_names)}
        self._joints: dict[str, _Joint] = {}  # by child link
        lower, upper = np.full(self.dof, -np.inf), np.full(self.dof, np.inf)
        for j in urdf.robot.joints:
            if j.type not in _MOVABLE + ("fixed",):
                raise BrokenUrdf(f"URDF {self.urdf_path}: joint '{j.name}' has unsupported type '{j.type}'.")
            axis = np.array([1.0, 0, 0]) if j.axis is None else np.asarray(j.axis, float)
            mimic = (j.mimic.joint, float(j.mimic.multiplier or 1.0), float(j.mimic.offset or 0.0)) if j.mimic else None
            origin = np.eye(4) if j.origin is None else np.asarray(j.origin, float)
            self._joints[j.child] = _Joint(j.name, j.type, j.parent, j.child, origin, axis, idx.get(j.name, -1), mimic)
            if j.name in idx and j.type != "continuous" and j.limit is not None:
                lo, hi = j.limit.lower, j.limit.upper
                lower[idx[j.name]] = -np.inf if lo is None else float(lo)
                upper[idx[j.name]] = np.inf if hi is None else float(hi)
        self._by_name = {j.name: j for j in self._joints.values()}
        self._polys = poly_mimics(self.urdf_path)
        self.lower, self.upper = lower, upper
        self.sample_lower = np.where(np.isfinite(lower), lower, -np.pi)
        self.sample_upper = np.where(np.isfinite(upper), upper, np.pi)
        self._q = ca.SX.sym("q", self.dof)
        self._memo: dict[str, ca.SX] = {self.base_link: ca.SX.eye(4)}
        self._fns: dict[tuple, ca.Function] = {}

    # -- symbolic -------------------------------------------------------------------
    def _joint_value(self, j: _Joint, q: ca.SX, depth: int = 0) -> ca.SX:
        if j.mimic is not None:
            src = self._by_name.get(j.mimic[0])
            if src is None or depth > 16:
                return ca.SX(j.mimic[2])  # yourdfpy: non-actuated source -> 0 + offset
            if j.name in self._polys:
                return self._polys[j.name](self._joint_value(src, q, depth + 1))
            return j.mimic[1] * self._joint_value(src, q, depth + 1) + j.mimic[2]
        return q[j.q_index] if j.q_index >= 0 else ca.SX(0.0)

    def _local(self, j: _Joint, q: ca.SX) -> ca.SX:
        T = ca.SX(j.origin)
        if j.type == "fixed":
            return T
        v = self._joint_value(j, q)
        M = ca.SX.eye(4)
        if j.type == "prismatic":
            M[:3, 3] = v * ca.SX(j.axis)
        else:
            a = j.axis / np.linalg.norm(j.axis)
            K = ca.SX(_skew(a))
            M[:3, :3] = ca.SX.eye(3) + ca.sin(v) * K + (1 - ca.cos(v)) * (K @ K)
        return T @ M

    def fk_expr(self, link: str, q: ca.SX | None = None) -> ca.SX:
        """base_from_link (4x4) as an expression of ``q`` (the internal symbol by default)."""
        if link not in self.link_names:
            raise KeyError(f"link '{link}' not in {self.urdf_path.name}; links: {self.link_names}")
        if q is not None:
            return ca.substitute(self.fk_expr(link), self._q, q)
        if link not in self._memo:
            j = self._joints[link]
            self._memo[link] = self.fk_expr(j.parent) @ self._local(j, self._q)
        return self._memo[link]

    def chain(self, link: str) -> list[_Joint]:
        """Joints from the base link down to ``link`` (root first)."""
        if link not in self.link_names:
            raise KeyError(f"link '{link}' not in {self.urdf_path.name}; links: {self.link_names}")
        out = []
        while link != self.base_link:
            j = self._joints[link]
            out.append(j)
            link = j.parent
        return out[::-1]

    @property
    def q_sym(self) -> ca.SX:
        return self._q

    def fk_function(self, link: str) -> ca.Function:
        """casadi Function q -> base_from_link (4x4)."""
        key = ("fk", link)
        if key not in self._fns:
            self._fns[key] = ca.Function(f"fk_{_safe(link)}", [self._q], [self.fk_expr(link)])
        return self._fns[key]

    def points_expr(self, points: list[tuple[str, tuple[float, float, float]]], q: ca.SX | None = None) -> ca.SX:
        """(3,K) positions in the base frame of points given as (link, offset-in-link)."""
        cols = []
        for link, off in points:
            T = self.fk_expr(link)
            cols.append(T[:3, :3] @ ca.SX(np.asarray(off, float)) + T[:3, 3])
        P = ca.horzcat(*cols)
        return P if q is None else ca.substitute(P, self._q, q)

    def jacobian_function(self, link: str) -> ca.Function:
        """casadi Function q -> (6,dof) [d position; d rotation-vector] of the link in the base frame.

        The angular part is the body-to-base angular velocity map, i.e. the geometric
        Jacobian's lower block (from the rotation matrix derivative, vee(dR R^T)).
        """
        key = ("jac", link)
        if key not in self._fns:
            T = self.fk_expr(link)
            p, R = T[:3, 3], T[:3, :3]
            Jp = ca.jacobian(p, self._q)
            cols = []
            for i in range(self.dof):
                dR = ca.jacobian(ca.vec(R), self._q[i])
                W = ca.reshape(dR, 3, 3) @ R.T
                cols.append(ca.vertcat(W[2, 1], W[0, 2], W[1, 0]))
            Jw = ca.horzcat(*cols) if cols else ca.SX(3, 0)
            self._fns[key] = ca.Function(f"jac_{_safe(link)}", [self._q], [ca.vertcat(Jp, Jw)])
        return self._fns[key]

    def mimic_joints(self) -> dict[str, tuple[str, float, float]]:
        """Joints that follow another (name -> (source joint, multiplier, offset)): not in ``q``."""
        return {j.name: j.mimic for j in self._by_name.values() if j.mimic is not None}

    # -- numeric --------------------------------------------------------------------
    def fk(self, q: np.ndarray, link: str) -> np.ndarray:
        return np.asarray(self.fk_function(link)(np.asarray(q, float)), dtype=float)

    def clip(self, q: np.ndarray) -> np.ndarray:
        return np.clip(q, self.lower, self.upper)

    def neutral(self) -> np.ndarray:
        """Zero pose clipped into the limits (Allegro's zero is outside joint_12.0's)."""
        return self.clip(np.zeros(self.dof))

    def random_q(self, rng: np.random.Generator, n: int | None = None) -> np.ndarray:
        shape = (self.dof,) if n is None else (n, self.dof)
        return rng.uniform(self.sample_lower, self.sample_upper, size=shape)


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name)


@functools.lru_cache(maxsize=32)
@metered
def get_kinematics(urdf_path: str | os.PathLike) -> Kinematics:
    """Per-process cache of ``Kinematics`` by URDF path."""
    return Kinematics(urdf_path)
