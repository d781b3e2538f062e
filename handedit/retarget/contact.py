"""Contacts in the hand-retargeting solve, where the source has an object mesh and per-frame pose.

Position retargeting alone matches the human fingertips as well as the robot's proportions
allow: a tip that lands 15 mm off a human tip resting on a cup is 15 mm off the cup, or inside
it, and the QC then rejects the frame (``CONTACT_LOSS``, ``PENETRATION``). Two terms in the
solve keep the contact instead (``solver.Retargeter``'s contact problem):

- touch: a human fingertip within ``contact_mm`` of the surface pins the robot's tip to the
  tangent plane at the human tip's closest surface point, at the human tip's own distance: the
  tip may slide along the surface (the position term decides where), not leave or enter it;
- push-out: after a solve, a link whose surface samples lie more than ``push_depth_mm`` inside
  the object has its deepest samples pushed back towards the tangent planes at their closest
  surface points, to 1 mm less deep than that, and the frame is solved again from its own
  solution (``contact_rounds`` times at most). A re-solve that would take the fingertips or the
  wrist past the QC's error thresholds is not kept: it trades one rejection for another. Where
  the hand stays deeper than the QC allows, the frame is also solved without the touch terms
  (they may be what pulled it in) and the shallower solution kept (``api.retarget``).

Planes are fixed per solve (linearised contact), so the problem keeps its variables and a cost
that is once differentiable everywhere (the push-out term is a squared hinge);
``retarget_qc`` still judges the result against the mesh with the paper's thresholds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

PUSH_BACK_M = 0.001  # a pushed point goes this much less deep than allowed (the plane is a linearisation)
PUSH_SLOTS = 3  # points per link: one point pushed out lets the link turn about it and sink elsewhere


@dataclass
class ContactParams:
    """One frame's contact terms, in the camera frame (metres), rows as the solver's slots."""

    tip_normal: np.ndarray  # (n_tips,3) outward surface normal at each touching tip's closest point
    tip_offset: np.ndarray  # (n_tips,) the plane n . p = offset the robot tip keeps
    tip_weight: np.ndarray  # (n_tips,) 0 where the human tip does not touch
    push_point: np.ndarray  # (n_links*PUSH_SLOTS,3) samples of each link inside the object, in the link's frame
    push_normal: np.ndarray  # (n_links*PUSH_SLOTS,3)
    push_offset: np.ndarray  # (n_links*PUSH_SLOTS,) n . p >= offset
    push_weight: np.ndarray  # (n_links*PUSH_SLOTS,) 0 where the slot is unused

    @classmethod
    def empty(cls, n_tips: int, n_links: int) -> "ContactParams":
        m = n_links * PUSH_SLOTS
        return cls(np.zeros((n_tips, 3)), np.zeros(n_tips), np.zeros(n_tips), np.zeros((m, 3)), np.zeros((m, 3)),
                   np.zeros(m), np.zeros(m))

    def vector(self) -> np.ndarray:
        """The solver's parameter layout: casadi's ``vec`` of each 3 x n block is column-major, i.e. these (n,3) rows."""
        return np.concatenate([self.tip_normal.ravel(), self.tip_offset, self.tip_weight, self.push_point.ravel(),
                               self.push_normal.ravel(), self.push_offset, self.push_weight])

    @property
    def active(self) -> bool:
        return bool(self.tip_weight.any() or self.push_weight.any())


class ObjectTrack:
    """The object's mesh and its camera_from_object per frame; closest points and signed
    distances of camera-frame points (trimesh: > 0 inside)."""

    def __init__(self, mesh: tuple[np.ndarray, np.ndarray], camera_from_object: np.ndarray):
        self.mesh = trimesh.Trimesh(np.asarray(mesh[0], float), np.asarray(mesh[1], int), process=False)
        self.pose = np.asarray(camera_from_object, float)
        self.lo, self.hi = self.mesh.bounds[0], self.mesh.bounds[1]
        # a convex object (a box, a cylinder) is the intersection of its faces' half-spaces: depth
        # inside it is exact from the face planes, with no closest-point query (~0.1 ms a point)
        self.convex = bool(self.mesh.is_convex)
        self.face_n = np.asarray(self.mesh.face_normals, float)
        self.face_o = np.einsum("ij,ij->i", self.face_n, np.asarray(self.mesh.triangles[:, 0], float))

    def _to_object(self, i: int, pts: np.ndarray) -> np.ndarray:
        inv = np.linalg.inv(self.pose[i])
        return pts @ inv[:3, :3].T + inv[:3, 3]

    def near(self, i: int, pts: np.ndarray, margin: float) -> np.ndarray:
        """(N,) bool: inside the object's box grown by ``margin`` (cheap; only these can touch)."""
        p = self._to_object(i, np.asarray(pts, float))
        return np.all((p > self.lo - margin) & (p < self.hi + margin), axis=1)

    def planes(self, i: int, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Signed distance (m, > 0 inside), closest surface point and outward normal, camera frame.
        The sign is the closest face's side (one closest-point query; trimesh's signed_distance
        runs that query again and casts rays): the QC measures depth its own way."""
        p = self._to_object(i, np.asarray(pts, float))
        closest, dist, tri = trimesh.proximity.closest_point(self.mesh, p)
        face_n = np.asarray(self.mesh.face_normals[tri], float)
        away = p - closest
        inside = np.einsum("ij,ij->i", away, face_n) < 0
        sd = np.where(inside, dist, -dist)
        # outside, the direction to the point is the surface's normal there (edges and corners too)
        normal = np.where((~inside & (dist > 1e-6))[:, None], away / np.maximum(dist, 1e-12)[:, None], face_n)
        R, t = self.pose[i][:3, :3], self.pose[i][:3, 3]
        return sd, closest @ R.T + t, normal @ R.T


    def depths(self, i: int, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As ``planes`` where it matters for pushing out, points inside: exact there; outside,
        only the sign is (the distance is a lower bound). Convex objects take the face planes."""
        if not self.convex:
            return self.planes(i, pts)
        p = self._to_object(i, np.asarray(pts, float))
        d = p @ self.face_n.T - self.face_o  # (N,F) signed distance to each face's plane, > 0 outside it
        f = np.argmax(d, axis=1)
        out = d[np.arange(len(p)), f]
        normal = self.face_n[f]
        R, t = self.pose[i][:3, :3], self.pose[i][:3, 3]
        return -out, (p - out[:, None] * normal) @ R.T + t, normal @ R.T


def touch_terms(obj: ObjectTrack, i: int, human_tips: np.ndarray, valid: np.ndarray, contact_mm: float,
                weight: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(normal, offset, weight) per tip: the tangent plane at the closest point of each human tip
    within ``contact_mm`` of the surface, at the human tip's distance outside it."""
    n = len(human_tips)
    normal, offset, w = np.zeros((n, 3)), np.zeros(n), np.zeros(n)
    cand = np.asarray(valid, bool) & obj.near(i, human_tips, contact_mm / 1000.0)
    if cand.any():
        sd, c, nrm = obj.planes(i, human_tips[cand])
        touching = np.abs(sd) * 1000.0 < contact_mm
        rows = np.flatnonzero(cand)[touching]
        normal[rows] = nrm[touching]
        offset[rows] = np.einsum("ij,ij->i", nrm[touching], c[touching]) + np.maximum(-sd[touching], 0.0)
        w[rows] = weight
    return normal, offset, w


def push_terms(obj: ObjectTrack, i: int, link_points: list[np.ndarray], link_local: list[np.ndarray],
               depth_mm: float, weight: float, prev: ContactParams) -> tuple[ContactParams, float]:
    """``prev`` with push-out planes for every link whose deepest sample is more than ``depth_mm``
    inside the object (each plane ``depth_mm`` less 1 mm inside the surface): its deepest sample and the inside samples farthest from those already
    taken (``PUSH_SLOTS``; camera-frame samples ``link_points``, the same in the link frame
    ``link_local``). A link now clear keeps its planes. Also the deepest penetration found (mm)."""
    out = ContactParams(prev.tip_normal, prev.tip_offset, prev.tip_weight, prev.push_point.copy(),
                        prev.push_normal.copy(), prev.push_offset.copy(), prev.push_weight.copy())
    deepest = 0.0
    near = [np.flatnonzero(obj.near(i, pts, 0.0)) for pts in link_points]
    if not any(k.size for k in near):
        return out, deepest
    # one closest-point query for every link's candidates (a query per link costs ~6 ms of overhead)
    sd_all, c_all, n_all = obj.depths(i, np.concatenate([pts[k] for pts, k in zip(link_points, near)]))
    bounds = np.cumsum([0] + [k.size for k in near])
    for j, (pts, local, k_near) in enumerate(zip(link_points, link_local, near)):
        if not k_near.size:
            continue
        part = slice(bounds[j], bounds[j + 1])
        sd, c, nrm = sd_all[part], c_all[part], n_all[part]
        deepest = max(deepest, float(sd.max()) * 1000.0)
        if sd.max() * 1000.0 <= depth_mm:
            continue
        inside = np.flatnonzero(sd > 0)
        at = pts[k_near][inside]
        taken = [int(np.argmax(sd[inside]))]
        while len(taken) < min(PUSH_SLOTS, inside.size):  # farthest-point: spread over the part that sank
            gap = np.min(np.linalg.norm(at[:, None] - at[taken][None], axis=2), axis=1)
            taken.append(int(np.argmax(gap)))
        rows = slice(j * PUSH_SLOTS, (j + 1) * PUSH_SLOTS)
        out.push_weight[rows] = 0.0
        for slot, k in zip(range(j * PUSH_SLOTS, (j + 1) * PUSH_SLOTS), inside[taken]):
            out.push_point[slot] = local[k_near[k]]
            out.push_normal[slot] = nrm[k]
            out.push_offset[slot] = float(nrm[k] @ c[k]) - max(depth_mm / 1000.0 - PUSH_BACK_M, 0.0)
            out.push_weight[slot] = weight
    return out, deepest
