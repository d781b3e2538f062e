"""Pinhole camera in the OpenCV convention (x right, y down, z forward), metres.

Intrinsics are fixed per clip; extrinsics are per frame as ``world_from_camera``
(4x4, the camera pose in the world). Keypoints and robot poses live in the camera
frame, so most stages never need the extrinsics; the virtual-base search does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int) -> "Intrinsics":
        K = np.asarray(K, dtype=float)
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height))

    @classmethod
    def default_for(cls, width: int, height: int, hfov_deg: float = 70.0) -> "Intrinsics":
        """A plausible head-camera guess when a video comes without calibration."""
        f = 0.5 * width / np.tan(np.deg2rad(hfov_deg) / 2.0)
        return cls(float(f), float(f), width / 2.0, height / 2.0, int(width), int(height))

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """The same camera for an image resized to (width, height): pixel centres map
        consistently (u' + 0.5 = (u + 0.5) * sx), so projected points land on the same content."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5,
                          int(width), int(height))

    def to_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "width": self.width, "height": self.height}


def project(points: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Camera-frame points (..., 3) -> pixel coordinates (..., 2); NaN behind the camera."""
    p = np.asarray(points, dtype=np.float64)
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * p[..., 0] / z + intr.cx
        v = intr.fy * p[..., 1] / z + intr.cy
    uv = np.stack([u, v], axis=-1)
    uv[z <= 1e-6] = np.nan
    return uv


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """world_from_camera for an OpenCV camera at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))  # image right
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # image down
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


# pyrender/OpenGL cameras look down -z with y up; OpenCV looks down +z with y down.
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
