"""Left hands by mirroring: the mirrored right Allegro against dex-urdf's real left Allegro,
and a left human hand retargeted onto the mirrored robot."""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import yourdfpy  # noqa: E402

from handedit.camera import Intrinsics  # noqa: E402
from handedit.embodiments.kinematics import get_kinematics  # noqa: E402
from handedit.embodiments.mirror import CAMERA_MIRROR, ROOT_MIRROR, left_pose, mirror_keypoints, mirror_urdf  # noqa: E402

RIGHT = "hands/allegro_hand/allegro_hand_right_glb.urdf"
LEFT = "hands/allegro_hand/allegro_hand_left_glb.urdf"
# dex-urdf's left Allegro keeps the finger modules and moves the thumb across: its link_0-3
# (the finger at +y) is the mirrored hand's link_8-11, its spread joints turn the other way.
PERM = {**{j: 8 + j for j in range(4)}, **{8 + j: j for j in range(4)}, **{4 + j: 4 + j for j in range(4)},
        **{12 + j: 12 + j for j in range(4)}}
SPREAD = (0, 4, 8)
THUMB_DISTAL = {"link_13.0", "link_14.0", "link_15.0", "link_15.0_tip"}


def _left_q(q: np.ndarray) -> np.ndarray:
    ql = np.zeros_like(q)
    for i, j in PERM.items():
        ql[j] = q[i]
    ql[list(SPREAD)] *= -1
    return ql


def _link(name: str) -> str:
    base, _, rest = name.partition("_")
    if base != "link" or not rest[0].isdigit():
        return name
    i = int(rest.split(".")[0])
    return name.replace(f"link_{i}.", f"link_{PERM[i]}.", 1)


@pytest.fixture(scope="module")
def urdfs(robots_dir):
    m = mirror_urdf(robots_dir / RIGHT)
    return (yourdfpy.URDF.load(str(m), load_meshes=False), yourdfpy.URDF.load(str(robots_dir / LEFT), load_meshes=False),
            yourdfpy.URDF.load(str(robots_dir / RIGHT), load_meshes=False), m)


def test_mirror_is_exact_reflection_of_the_right_hand(urdfs):
    mirrored, _, right, _ = urdfs
    assert mirrored.actuated_joint_names == right.actuated_joint_names
    rng = np.random.default_rng(0)
    kin = get_kinematics(urdfs[3])
    for q in kin.random_q(rng, 4):
        mirrored.update_cfg(q)
        right.update_cfg(q)
        for link in right.link_map:
            np.testing.assert_allclose(mirrored.get_transform(link, mirrored.base_link),
                                       ROOT_MIRROR @ right.get_transform(link, right.base_link) @ ROOT_MIRROR, atol=1e-12)


def test_mirror_matches_the_real_left_allegro(urdfs):
    mirrored, left, _, path = urdfs
    kin = get_kinematics(path)
    worst_thumb = 0.0
    for q in kin.random_q(np.random.default_rng(1), 6):
        mirrored.update_cfg(q)
        left.update_cfg(_left_q(q))
        for link in mirrored.link_map:
            a = mirrored.get_transform(link, mirrored.base_link)[:3, 3]
            b = left.get_transform(_link(link), left.base_link)[:3, 3]
            if link in THUMB_DISTAL:
                # the left file places the thumb's rotation joint 5 mm to the other side
                # (origin y +0.005 where the mirror gives -0.005): a modelling difference upstream
                worst_thumb = max(worst_thumb, float(np.linalg.norm(a - b)))
            else:
                np.testing.assert_allclose(a, b, atol=1e-9, err_msg=link)
    assert 0.003 < worst_thumb < 0.015


def test_mirror_renders_the_left_silhouette(urdfs, robots_dir):
    from handedit.render import RobotRenderer, frame_points, rotation_from_euler
    from handedit.render.model import joint_limits

    W, H = 240, 180
    intr = Intrinsics(190.0, 190.0, 118.0, 92.0, W, H)
    rm, rl = RobotRenderer(urdfs[3], W, H), RobotRenderer(robots_dir / LEFT, W, H)
    lo, hi = joint_limits(rm.urdf)
    ious = []
    for t in range(3):
        q = np.random.default_rng(10 + t).uniform(lo, hi)
        T = frame_points(rm.points(q), rotation_from_euler(0.4, 0.3 + t, 0.2), intr, fill=0.7)
        a, b = rm.render(q[None], T[None], intr).mask[0], rl.render(_left_q(q)[None], T[None], intr).mask[0]
        ious.append((a & b).sum() / (a | b).sum())
        # shading is not inside out: the mirrored hand is as bright as the real left one
        assert abs(float(rm.render(q[None], T[None], intr).rgba[0][a][:, :3].mean()) -
                   float(rl.render(_left_q(q)[None], T[None], intr).rgba[0][b][:, :3].mean())) < 12
    rm.close(), rl.close()
    assert min(ious) > 0.85 and np.mean(ious) > 0.9, ious


def test_left_hand_retargets_onto_the_mirrored_robot(monkeypatch, robots_dir):
    """A left hand (the synthetic right hand reflected) through retarget_sides: the mirrored
    robot's keypoint links land on the left keypoints as well as the right robot's on the right."""
    from handedit.retarget import RetargetConfig, get_retargeter
    from handedit.retarget.sides import retarget_sides
    from handedit.sources.synthetic import SyntheticSpec

    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))
    c = SyntheticSpec(n_frames=24, width=160, height=120).open().read(14, 18)
    right = c.keypoints[:, 0].astype(float)
    both = np.stack([mirror_keypoints(right), right], axis=1)
    valid = np.repeat(c.keypoints_valid, 2, axis=1)
    cfg = RetargetConfig()
    res = retarget_sides(both, valid, np.ones((4, 2), bool), ("left", "right"), "allegro", cfg)
    np.testing.assert_allclose(res.qpos[:, 0], res.qpos[:, 1], atol=1e-6)
    np.testing.assert_allclose(res.fingertip_error_mm[:, 0], res.fingertip_error_mm[:, 1], atol=1e-3)
    np.testing.assert_allclose(res.root_pose[:, 0], left_pose(res.root_pose[:, 1]), atol=1e-9)
    rt = get_retargeter("allegro", cfg)
    mk = get_kinematics(mirror_urdf(rt.kin.urdf_path))
    for i in range(4):
        T = res.root_pose[i, 0]
        for row, kp in enumerate(rt.asset.keypoints):
            L = T @ mk.fk(res.qpos[i, 0].astype(float), kp.link)
            p_left = L[:3, :3] @ np.asarray(kp.offset) + L[:3, 3]
            p_right = CAMERA_MIRROR[:3, :3] @ rt.robot_points(res.qpos[i, 1].astype(float), res.root_pose[i, 1])[row]
            np.testing.assert_allclose(p_left, p_right, atol=1e-6)
