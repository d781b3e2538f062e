"""The canonical camera rig of the reference bank (and of bench/render.py's hand-arm views).

Why fixed: the benchmark's identity metric compares an edit with these references, so every
run, machine and editor must see the same images. The robot stands at its neutral pose (zero
clipped into the limits; ``seed`` > 0 adds a seeded in-limit perturbation for extra views),
its root z axis up in the image (hands: fingers up; arms: upright), and V cameras sit on a
ring around it at a fixed elevation, evenly spaced in azimuth starting in front of +x, each
framed so the robot fills ``fill`` of the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from handedit.camera import Intrinsics, look_at
from handedit.render.framing import frame_points

ELEVATION_DEG = 20.0
HFOV_DEG = 50.0
FILL = 0.8


@dataclass(frozen=True)
class ViewRig:
    qpos: np.ndarray  # (V, dof)
    camera_from_root: np.ndarray  # (V, 4, 4) OpenCV
    intrinsics: Intrinsics


def view_rotations(n_views: int, elevation_deg: float = ELEVATION_DEG) -> np.ndarray:
    """(V,3,3) camera_from_root rotations on a ring around the root z axis."""
    el = np.deg2rad(elevation_deg)
    out = []
    for k in range(n_views):
        az = 2 * np.pi * k / n_views
        eye = np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        world_from_cam = look_at(eye, np.zeros(3), up=np.array([0.0, 0.0, 1.0]))
        out.append(world_from_cam[:3, :3].T)
    return np.stack(out)


def canonical_views(renderer, n_views: int, seed: int = 0, fill: float = FILL) -> ViewRig:
    """V canonical views of ``renderer``'s robot (a RobotRenderer) at its own image size."""
    from handedit.render.model import joint_limits

    intr = Intrinsics.default_for(renderer.width, renderer.height, hfov_deg=HFOV_DEG)
    lo, hi = joint_limits(renderer.urdf)
    q0 = np.clip(np.zeros(len(lo)), lo, hi)
    if seed:
        q0 = q0 + 0.15 * np.random.default_rng(seed).uniform(lo, hi) - 0.15 * q0
        q0 = np.clip(q0, lo, hi)
    pts = renderer.points(q0)
    rots = view_rotations(n_views)
    poses = np.stack([frame_points(pts, R, intr, fill=fill) for R in rots])
    return ViewRig(np.repeat(q0[None], n_views, axis=0), poses, intr)
