"""Camera placement that frames a robot, for reference views, benchmarks and tests."""

from __future__ import annotations

import numpy as np

from handedit.camera import Intrinsics


def frame_points(
    points_root: np.ndarray,
    rotation: np.ndarray,
    intrinsics: Intrinsics,
    fill: float = 0.6,
    distance: float | None = None,
) -> np.ndarray:
    """camera_from_root (4x4, OpenCV) with orientation ``rotation`` that puts the bounding-box
    centre of ``points_root`` on the optical axis, ``distance`` metres ahead if given, else as
    close as possible while every point stays within the central ``fill`` fraction of the image
    (assumes a roughly central principal point)."""
    R = np.asarray(rotation, float)
    p = np.asarray(points_root, float) @ R.T
    centre = (p.min(axis=0) + p.max(axis=0)) / 2
    p = p - centre
    # Perspective makes near parts larger, so bound per point: |f x / (z + pz)| <= fill * size / 2.
    if distance is not None:
        z = float(distance)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = np.array([0.0, 0.0, z]) - centre
        return T
    half_w, half_h = fill * intrinsics.width / 2, fill * intrinsics.height / 2
    z = max(
        np.max(intrinsics.fx * np.abs(p[:, 0]) / half_w - p[:, 2]),
        np.max(intrinsics.fy * np.abs(p[:, 1]) / half_h - p[:, 2]),
        np.max(0.05 - p[:, 2]),
    )
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.array([0.0, 0.0, z]) - centre
    return T


def rotation_from_euler(rx: float, ry: float, rz: float) -> np.ndarray:
    """R = Rz @ Ry @ Rx (radians)."""
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx
