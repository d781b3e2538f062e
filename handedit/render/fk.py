"""The renderer's forward kinematics: every link's pose from the joint values in one pass.

yourdfpy's scene graph (``update_cfg``, then ``get_transform`` per link) took about 9 ms per
robot and frame on a hand-arm's thirty-odd links, a fifth of its render on EgoDex
(add_remove_lid, 960x540). The same transforms, each joint's matrix built as yourdfpy builds
it and composed once down the tree, take a fraction of a millisecond. Mimic joints follow
yourdfpy (``multiplier`` x source + ``offset``; a source that is not actuated reads 0), and
polynomial mimics (``linkage.PolyMimic``) replace their straight line, as ``linkage.update_cfg``
does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh.transformations as tra

from handedit.embodiments.linkage import PolyMimic


@dataclass(frozen=True)
class _Joint:
    child: str
    parent: str
    origin: np.ndarray  # (4,4) parent_from_joint
    axis: np.ndarray
    kind: str  # "revolute" (continuous too), "prismatic" or "fixed" (floating and planar: their origin)
    source: int  # index into q of the value's source; -1: none (fixed, or a mimic of an unactuated joint)
    multiplier: float
    offset: float
    poly: PolyMimic | None


class LinkFK:
    """base_from_link of every link of a yourdfpy URDF at an actuated configuration ``q``."""

    def __init__(self, urdf, polys: dict[str, PolyMimic] | None = None) -> None:
        polys = polys or {}
        names = list(urdf.actuated_joint_names)
        by_parent: dict[str, list] = {}
        for j in urdf.robot.joints:
            by_parent.setdefault(j.parent, []).append(j)
        self.base = urdf.base_link
        self._joints: list[_Joint] = []
        todo = [self.base]
        while todo:  # parents before children
            for j in by_parent.get(todo.pop(), ()):
                self._joints.append(self._joint(j, names, polys))
                todo.append(j.child)

    @staticmethod
    def _joint(j, names: list[str], polys: dict[str, PolyMimic]) -> _Joint:
        origin = np.eye(4) if j.origin is None else np.asarray(j.origin, float)
        kind = {"continuous": "revolute", "revolute": "revolute", "prismatic": "prismatic"}.get(j.type, "fixed")
        axis = np.asarray(j.axis if j.axis is not None else (1.0, 0.0, 0.0), float)
        poly = polys.get(j.name)
        if poly is not None:
            return _Joint(j.child, j.parent, origin, axis, kind, names.index(poly.source), 1.0, 0.0, poly)
        if j.mimic is not None:
            src = names.index(j.mimic.joint) if j.mimic.joint in names else -1
            mult = 1.0 if j.mimic.multiplier is None else float(j.mimic.multiplier)
            off = 0.0 if j.mimic.offset is None else float(j.mimic.offset)
            return _Joint(j.child, j.parent, origin, axis, kind, src, mult, off, None)
        return _Joint(j.child, j.parent, origin, axis, kind, names.index(j.name) if j.name in names else -1, 1.0, 0.0, None)

    def __call__(self, q: np.ndarray) -> dict[str, np.ndarray]:
        q = np.asarray(q, float)
        out = {self.base: np.eye(4)}
        for j in self._joints:
            if j.kind == "fixed":
                local = j.origin
            else:
                x = float(q[j.source]) if j.source >= 0 else 0.0
                v = float(j.poly(x)) if j.poly is not None else x * j.multiplier + j.offset
                if j.kind == "prismatic":
                    local = j.origin @ tra.translation_matrix(v * j.axis)
                else:
                    local = j.origin @ tra.rotation_matrix(v, j.axis)
            out[j.child] = out[j.parent] @ local
        return out
