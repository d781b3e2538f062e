"""Articulated right-hand model for the synthetic source: MANO-order joints + skin meshes.

The hand is a set of rigid parts (palm, 15 phalanges, 5 nails, forearm) whose meshes are
built once in their own local frames; a pose only moves those frames. This keeps the
per-frame cost to node-pose updates, and makes the 21 keypoints exact by construction
(they are the joints the parts hang from, fingertips lie on the skin surface).

Hand frame (metres): origin at the wrist joint, x towards the fingers, y towards the
thumb (radial side), z out of the back of the hand (dorsal). For a right hand this is
right-handed: the palm faces -z and fingers flex towards -z.

Every finger is a planar chain: a base direction ``d0``, a bend direction ``u0`` and
three flexion angles; rotating about ``a = d0 x u0`` by a positive angle turns a bone
towards ``u0``. The thumb uses the same chain with its base direction set by an
opposition angle, so one closing routine serves all five digits.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import trimesh

from handedit.keypoints import FINGERS

CM = 0.01
DIGITS: tuple[str, ...] = ("thumb", "index", "middle", "ring", "pinky")
SdfFn = Callable[[np.ndarray], np.ndarray]  # (N,3) hand-frame points -> signed distance (N,)


@dataclass(frozen=True)
class DigitGeom:
    """Fixed geometry of one digit: root joint, bone lengths, skin radii, joint limits."""

    name: str
    root: np.ndarray  # (3,) root joint (MCP, or CMC for the thumb) in the hand frame
    lengths: tuple[float, float, float]  # root->j1, j1->j2, j2->tip (tip on the skin)
    radii: tuple[float, float, float, float]  # skin radius at root, j1, j2, tip
    lo: tuple[float, float, float]  # flexion limits (rad)
    hi: tuple[float, float, float]


@dataclass(frozen=True)
class DigitPose:
    """Base direction, bend direction and three flexion angles of one digit."""

    d0: np.ndarray
    u0: np.ndarray
    flex: tuple[float, float, float]


@dataclass(frozen=True)
class HandGeom:
    digits: tuple[DigitGeom, ...]  # thumb, index, middle, ring, pinky
    palm_spheres: np.ndarray  # (k,4) centre xyz + radius, hand frame
    forearm_length: float
    forearm_wrist_radii: tuple[float, float]  # half width (radial-ulnar), half thickness
    forearm_elbow_radii: tuple[float, float]
    scale: float

    def digit(self, name: str) -> DigitGeom:
        return self.digits[DIGITS.index(name)]


def make_hand_geom(scale: float = 1.0) -> HandGeom:
    """An adult right hand, wrist to middle fingertip ~18.5 cm x ``scale`` (MANO-like bones)."""
    s = scale * CM
    d = np.deg2rad

    def digit(name, root, lengths, radii, lo, hi):
        return DigitGeom(name, np.array(root) * s, tuple(x * s for x in lengths), tuple(r * s for r in radii),
                         tuple(d(lo)), tuple(d(hi)))

    digits = (
        digit("thumb", (2.1, 2.3, -1.1), (3.7, 3.1, 2.7), (1.35, 1.12, 0.98, 0.86), (-10, -5, -10), (50, 65, 85)),
        digit("index", (8.6, 2.45, 0.0), (4.1, 2.5, 2.1), (1.0, 0.9, 0.8, 0.72), (-15, 0, 0), (90, 105, 90)),
        digit("middle", (9.0, 0.45, 0.0), (4.5, 2.8, 2.2), (1.02, 0.92, 0.82, 0.74), (-15, 0, 0), (90, 105, 90)),
        digit("ring", (8.5, -1.5, -0.2), (4.2, 2.7, 2.2), (0.97, 0.87, 0.78, 0.7), (-15, 0, 0), (90, 105, 90)),
        digit("pinky", (7.7, -3.2, -0.45), (3.4, 2.0, 2.0), (0.85, 0.76, 0.68, 0.62), (-15, 0, 0), (90, 105, 90)),
    )
    palm = [
        (0.6, 1.6, 0.0, 1.45), (0.6, -1.8, 0.0, 1.45),  # wrist, radial and ulnar
        (3.0, 2.4, -0.7, 1.4), (4.6, -3.0, -0.35, 1.3),  # thenar and hypothenar
        (5.0, -0.3, 0.0, 1.45), (3.0, 0.0, 0.0, 1.45),  # mid palm (thickness)
    ]
    for g in digits[1:]:
        r = g.radii[0] / s * 1.12
        palm.append((g.root[0] / s - 0.35, g.root[1] / s, g.root[2] / s, r))
    palm_spheres = np.array(palm, float)
    palm_spheres *= s
    return HandGeom(digits, palm_spheres, 30.0 * s, (2.8 * s, 1.9 * s), (4.1 * s, 3.4 * s), scale)


# ----------------------------------------------------------------------------- kinematics


def rot_axis(axis: np.ndarray, angle: np.ndarray | float) -> np.ndarray:
    """Rodrigues rotation matrices (...,3,3) about a unit ``axis`` by ``angle`` (broadcast)."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    ang = np.asarray(angle, float)[..., None, None]
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * (K @ K)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def finger_pose(spread: float, flex: tuple[float, float, float]) -> DigitPose:
    """Long finger: base direction spread in the palm plane, flexion towards the palm (-z)."""
    d0 = np.array([np.cos(spread), np.sin(spread), 0.0])
    return DigitPose(d0, np.array([0.0, 0.0, -1.0]), flex)


THUMB_OPEN, THUMB_OPPOSED = np.deg2rad(20.0), np.deg2rad(90.0)


def thumb_pose(opposition: float, flex: tuple[float, float, float], azimuth: float = np.deg2rad(75)) -> DigitPose:
    """Thumb: ``opposition`` swings the metacarpal from radial (open hand) to palmar.

    Open, the thumb bends towards the palm (ulnar-palmar); opposed, it bends towards the
    fingers (+x), so it wraps the near side of a held object while the fingers wrap the far side.
    """
    d0 = np.array([np.cos(azimuth), np.sin(azimuth) * np.cos(opposition), -np.sin(azimuth) * np.sin(opposition)])
    w = float(np.clip((opposition - THUMB_OPEN) / (THUMB_OPPOSED - THUMB_OPEN), 0.0, 1.0))
    g = (1 - w) * _unit(np.array([0.15, -0.75, -0.65])) + w * _unit(np.array([1.0, -0.25, 0.0]))
    u0 = _unit(g - (g @ d0) * d0)
    return DigitPose(d0, u0, flex)


def chain(geom: DigitGeom, pose: DigitPose) -> tuple[np.ndarray, np.ndarray]:
    """Joint positions (4,3) root..tip and segment frames (3,4,4): origin at the proximal
    joint, z along the bone, x the flexion axis, y dorsal."""
    d0, u0 = pose.d0, _unit(pose.u0 - (pose.u0 @ pose.d0) * pose.d0)
    axis = _unit(np.cross(d0, u0))
    angles = np.cumsum(pose.flex)
    joints = [geom.root]
    frames = []
    for k in range(3):
        d = rot_axis(axis, angles[k]) @ d0
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = axis, np.cross(d, axis), d, joints[-1]
        frames.append(T)
        joints.append(joints[-1] + geom.lengths[k] * d)
    return np.array(joints), np.array(frames)


def chain_batch(geom: DigitGeom, d0: np.ndarray, u0: np.ndarray, flex: np.ndarray) -> np.ndarray:
    """Joint positions (n,4,3) for n flexion triples (n,3) at once (used by grasp closing)."""
    u0 = _unit(u0 - (u0 @ d0) * d0)
    axis = _unit(np.cross(d0, u0))
    angles = np.cumsum(flex, axis=1)
    n = flex.shape[0]
    joints = np.empty((n, 4, 3))
    joints[:, 0] = geom.root
    for k in range(3):
        d = rot_axis(axis, angles[:, k]) @ d0
        joints[:, k + 1] = joints[:, k] + geom.lengths[k] * d
    return joints


@dataclass(frozen=True)
class HandPose:
    digits: tuple[DigitPose, ...]  # thumb, index, middle, ring, pinky


def hand_keypoints(geom: HandGeom, pose: HandPose) -> tuple[np.ndarray, np.ndarray]:
    """21 MANO-order joints (21,3) and the 15 segment frames (15,4,4), hand frame."""
    kp = np.zeros((21, 3))
    frames = []
    for name, g, p in zip(DIGITS, geom.digits, pose.digits):
        joints, fr = chain(g, p)
        kp[list(FINGERS[name])] = joints
        frames.append(fr)
    return kp, np.concatenate(frames)


def blend_pose(a: HandPose, b: HandPose, w: float) -> HandPose:
    """Per-digit interpolation of directions and angles (w=0 -> a, w=1 -> b)."""
    out = []
    for pa, pb in zip(a.digits, b.digits):
        d0 = _unit((1 - w) * pa.d0 + w * pb.d0)
        u0 = (1 - w) * pa.u0 + w * pb.u0
        flex = tuple((1 - w) * x + w * y for x, y in zip(pa.flex, pb.flex))
        out.append(DigitPose(d0, u0, flex))
    return HandPose(tuple(out))


# ----------------------------------------------------------------------------- grasp closing


def _segment_samples(joints: np.ndarray, radii: tuple[float, ...], first: int, n: int = 7):
    """Points and skin radii sampled along segments ``first``..2 of a batch of chains (m,4,3)."""
    pts, rad = [], []
    for k in range(first, 3):
        t = np.linspace(0.0, 1.0, n)
        p0, p1 = joints[:, k], joints[:, k + 1]
        r0, r1 = radii[k], radii[k + 1]
        if k == 2:  # the distal capsule ends at the tip keypoint: its cap centre sits r1 back
            d = p1 - p0
            p1 = p1 - r1 * d / np.linalg.norm(d, axis=1, keepdims=True)
        pts.append(p0[:, None] + t[None, :, None] * (p1 - p0)[:, None])
        rad.append(r0 + t * (r1 - r0))
    return np.concatenate(pts, axis=1), np.concatenate(rad)


def close_digit(geom: DigitGeom, d0: np.ndarray, u0: np.ndarray, flex0: tuple[float, float, float],
                sdf: SdfFn, margin: float = 0.0015, steps: int = 90) -> tuple[float, float, float]:
    """Close a digit on the object with coupled joints that break away on contact.

    All free joints flex together towards their limits (a natural curl); when a segment
    comes within ``margin`` of the surface, it and the joints proximal to it freeze and the
    distal joints keep curling, so the digit wraps the object and the tip ends on it.
    """
    flex = np.array(flex0, float)
    hi = np.array(geom.hi)
    first = 0
    while first < 3:
        s = np.linspace(0.0, 1.0, steps + 1)[1:, None]
        batch = np.repeat(flex[None], steps, axis=0)
        batch[:, first:] = flex[first:] + s * (np.maximum(hi[first:], flex[first:]) - flex[first:])
        joints = chain_batch(geom, d0, u0, batch)
        pts, rad = _segment_samples(joints, geom.radii, first)
        clear = (sdf(pts.reshape(-1, 3)).reshape(pts.shape[:2]) - rad[None]).reshape(steps, 3 - first, -1).min(axis=2)
        hit = np.nonzero((clear < margin).any(axis=1))[0]
        if hit.size == 0:
            return tuple(float(x) for x in batch[-1])
        i = hit[0]
        if i > 0:
            flex = batch[i - 1]
        seg = first + int(np.nonzero(clear[i] < margin)[0][0])  # most proximal segment in contact
        first = seg + 1
    return tuple(float(x) for x in flex)


def digit_clearance(geom: DigitGeom, pose: DigitPose, sdf: SdfFn) -> float:
    """Smallest skin-to-surface distance of a digit (negative = penetration)."""
    joints, _ = chain(geom, pose)
    pts, rad = _segment_samples(joints[None], geom.radii, 0)
    return float((sdf(pts[0]) - rad).min())


def palm_clearance(geom: HandGeom, sdf: SdfFn) -> float:
    return float((sdf(geom.palm_spheres[:, :3]) - geom.palm_spheres[:, 3]).min())


# ----------------------------------------------------------------------------- meshes


def _sphere_points(subdiv: int = 2) -> np.ndarray:
    return trimesh.creation.icosphere(subdivisions=subdiv).vertices


def hull_of_spheres(centres: np.ndarray, radii: np.ndarray, subdiv: int = 2) -> trimesh.Trimesh:
    """Convex hull of spheres: a smooth rounded solid (tapered capsule, palm slab)."""
    unit = _sphere_points(subdiv)
    pts = np.concatenate([c + r * unit for c, r in zip(centres, radii)])
    return trimesh.convex.convex_hull(pts)


def hull_of_ellipsoids(centres: np.ndarray, radii: np.ndarray, subdiv: int = 3) -> trimesh.Trimesh:
    unit = _sphere_points(subdiv)
    pts = np.concatenate([c + r[None] * unit for c, r in zip(centres, radii)])
    return trimesh.convex.convex_hull(pts)


def segment_meshes(geom: HandGeom) -> list[trimesh.Trimesh]:
    """15 phalanx meshes in their segment frames (bone along +z from the proximal joint)."""
    out = []
    for g in geom.digits:
        for k in range(3):
            L, r0, r1 = g.lengths[k], g.radii[k], g.radii[k + 1]
            end = L - r1 if k == 2 else L  # distal capsule surface ends at the tip keypoint
            out.append(hull_of_spheres(np.array([[0, 0, 0], [0, 0, end]], float), np.array([r0, r1])))
    return out


def nail_meshes(geom: HandGeom) -> list[trimesh.Trimesh]:
    """5 nails on the dorsal side of the distal phalanges (distal segment frames)."""
    out = []
    for g in geom.digits:
        r = g.radii[3]
        L = g.lengths[2]
        m = trimesh.creation.icosphere(subdivisions=2)
        m.apply_scale([0.78 * r, 0.3 * r, 1.05 * r])
        m.apply_translation([0.0, 0.72 * r, L - 1.75 * r])
        out.append(m)
    return out


def palm_mesh(geom: HandGeom) -> trimesh.Trimesh:
    return hull_of_spheres(geom.palm_spheres[:, :3], geom.palm_spheres[:, 3], subdiv=3)


def forearm_mesh(geom: HandGeom) -> trimesh.Trimesh:
    """Tapered elliptical forearm in its frame: wrist at the origin, elbow at +z, x across."""
    (w0, t0), (w1, t1) = geom.forearm_wrist_radii, geom.forearm_elbow_radii
    L = geom.forearm_length
    centres = np.array([[0, 0, 0], [0, 0, 0.55 * L], [0, 0, L]], float)
    radii = np.array([[w0, t0, t0], [0.5 * (w0 + w1) * 1.05, 0.5 * (t0 + t1) * 1.08, t1], [w1, t1, t1]])
    return hull_of_ellipsoids(centres, radii)


def sleeve_mesh(geom: HandGeom, start: float, ease: float = 1.15) -> trimesh.Trimesh:
    """A sleeve over the forearm (its frame): from ``start`` metres past the wrist to the
    elbow, ``ease`` times the forearm's radii (cloth stands off the skin)."""
    (w0, t0), (w1, t1) = geom.forearm_wrist_radii, geom.forearm_elbow_radii
    L = geom.forearm_length
    f = min(max(start / L, 0.0), 0.5)
    ws, ts = w0 + f * (w1 - w0), t0 + f * (t1 - t0)
    centres = np.array([[0, 0, start], [0, 0, 0.55 * L], [0, 0, L]], float)
    radii = ease * np.array([[ws, ts, ts], [0.5 * (w0 + w1) * 1.05, 0.5 * (t0 + t1) * 1.08, t1], [w1, t1, t1]])
    return hull_of_ellipsoids(centres, radii)


def skin_colors(mesh: trimesh.Trimesh, base: np.ndarray, dorsal: np.ndarray, rng: np.random.Generator,
                palmar_tint: np.ndarray = np.array([1.06, 0.98, 0.95])) -> np.ndarray:
    """Per-vertex RGBA: lighter, pinker palmar skin, darker dorsal skin, low-frequency blotches."""
    n = mesh.vertex_normals @ _unit(dorsal)
    w = np.clip(0.5 - 0.5 * n, 0.0, 1.0)[:, None]  # 1 on the palmar side
    freq = rng.uniform(40.0, 90.0, size=3)
    phase = rng.uniform(0, 2 * np.pi, size=3)
    blotch = 0.04 * np.sin(mesh.vertices * freq + phase).sum(axis=1, keepdims=True) / 3.0
    rgb = base[None] * (0.93 + 0.1 * w) * ((1 - w) + w * palmar_tint[None]) * (1.0 + blotch)
    rgba = np.concatenate([np.clip(rgb, 0, 1), np.ones((len(rgb), 1))], axis=1)
    return (rgba * 255).round().astype(np.uint8)
