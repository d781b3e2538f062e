"""Camera conventions every stage relies on (OpenCV: x right, y down, z forward)."""

from __future__ import annotations

import numpy as np

from handedit.camera import Intrinsics, look_at, project


def test_look_at_is_upright_and_points_at_target():
    T = look_at([0.0, -0.3, 0.42], [0.0, 0.02, 0.0])
    R = T[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(R), 1.0)
    assert R[:, 0] @ np.array([1.0, 0, 0]) > 0.99  # image right = world +x
    assert R[:, 1] @ np.array([0, 0, 1.0]) < 0  # image down points down in the world
    target_cam = np.linalg.inv(T) @ np.array([0.0, 0.02, 0.0, 1.0])
    assert np.allclose(target_cam[:2], 0, atol=1e-9) and target_cam[2] > 0


def test_project_centre_and_behind_camera():
    intr = Intrinsics.default_for(640, 480)
    uv = project(np.array([[0.0, 0.0, 1.0], [0.1, -0.05, 0.5], [0.0, 0.0, -1.0]]), intr)
    assert np.allclose(uv[0], [320, 240])
    assert uv[1, 0] > 320 and uv[1, 1] < 240  # right and up of centre
    assert np.isnan(uv[2]).all()
    assert np.allclose(Intrinsics.from_K(intr.K, 640, 480).K, intr.K)
