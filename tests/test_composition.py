"""Hand-arm composition: arm + hand + mount, checked against the dex-urdf assemblies."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from handedit.embodiments import EmbodimentError, roster
from handedit.embodiments.compose import (
    MOUNT_JOINT,
    compose_embodiment,
    compose_urdf,
    mount_transform,
    nominal_reach,
)
from handedit.embodiments.kinematics import get_kinematics
from handedit.embodiments.urdf import load_urdf, matrix_to_xyz_rpy

# (arm key, hand key): each file's first (dex-urdf) URDF candidate, which carries the exact mount
ASSEMBLIES = {
    "ur5e_shadow": (roster.arm_spec("ur5").assets[0], roster.hand_spec("shadow").assets[0]),
    "xarm7_ability": (roster.arm_spec("xarm7").assets[0], roster.hand_spec("ability").assets[0]),
    "rm75_inspire": (roster.arm_spec("rm75").assets[0], roster.hand_spec("inspire").assets[0]),
}


@pytest.fixture(autouse=True)
def _env(monkeypatch, robots_dir, tmp_path_factory):
    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))
    monkeypatch.setenv("HANDEDIT_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "cache"))


def _edited_links(arm, asm) -> set[str]:
    """Links below a joint whose origin the assembly changed w.r.t. the stand-alone arm."""
    edited = {j.child for j in asm.robot.joints
              if j.name in arm.joint_map and j.child == arm.joint_map[j.name].child
              and not np.allclose(j.origin, arm.joint_map[j.name].origin, atol=1e-12)}
    out, frontier = set(), set(edited)
    while frontier:
        out |= frontier
        frontier = {j.child for j in asm.robot.joints if j.parent in frontier} - out
    return out


@pytest.mark.parametrize("key", sorted(ASSEMBLIES))
def test_composition_matches_dex_urdf_assembly(robots_dir, key):
    arm_asset, hand_asset = ASSEMBLIES[key]
    asm_path = next((robots_dir / "assembly" / key).glob("*.urdf"))
    T = mount_transform(arm_asset, hand_asset, np.eye(4))
    path, names = compose_urdf(robots_dir / arm_asset.path, robots_dir / hand_asset.path, arm_asset.ee_link, T)
    kin = get_kinematics(path)
    asm = load_urdf(asm_path, load_meshes=False)
    arm = load_urdf(robots_dir / arm_asset.path, load_meshes=False)
    assert kin.joint_names == list(asm.actuated_joint_names)
    skip = _edited_links(arm, asm)
    common = [l for l in kin.link_names if l in asm.link_map and l not in skip]
    hand = load_urdf(robots_dir / hand_asset.path, load_meshes=False)
    hand_links = [names[l.name] for l in hand.robot.links]
    assert len(set(hand_links) & set(common)) >= len(hand_links) - 2  # the assembly drops the hand's root (+ee) link
    for q in kin.random_q(np.random.default_rng(0), 3):
        asm.update_cfg(q)
        for link in common:
            np.testing.assert_allclose(kin.fk(q, link), asm.get_transform(link, asm.base_link), atol=1e-9,
                                       err_msg=f"{key}:{link}")


def test_name_clashes_are_prefixed_and_assets_untouched(robots_dir):
    arm, hand = robots_dir / "arms/ur5e/ur5e_glb.urdf", robots_dir / "hands/inspire_hand/inspire_hand_right.urdf"
    before = (arm.read_bytes(), hand.read_bytes())
    path, names = compose_urdf(arm, hand, "wrist_3_link", np.eye(4))
    assert names["base"] == "hand_base" and names["index_tip"] == "index_tip"  # ur5e has a 'base' link too
    assert (arm.read_bytes(), hand.read_bytes()) == before
    kin = get_kinematics(path)
    assert kin.chain("hand_base")[-1].name == MOUNT_JOINT
    assert all(Path(m).is_absolute() for m in re.findall(r'filename="([^"]+)"', path.read_text()))


def test_panda_gripper_is_pruned(robots_dir):
    c = compose_embodiment("panda_allegro")
    kin = c.kinematics()
    assert not any(l.startswith("panda_hand") or "finger" in l for l in kin.link_names)
    assert list(c.arm_joint_names) == [f"panda_joint{i}" for i in range(1, 8)]
    assert kin.joint_names[c.hand_slice] == list(c.hand_joint_names) and len(c.hand_joint_names) == 16


def test_mount_places_hand_root_on_flange(robots_dir):
    c = compose_embodiment("xarm_leap")
    kin = c.kinematics()
    q = kin.random_q(np.random.default_rng(1))
    np.testing.assert_allclose(np.linalg.inv(kin.fk(q, c.ee_link)) @ kin.fk(q, c.hand_root), c.ee_from_hand_root, atol=1e-12)
    # generic mount: the MANO wrist frame sits on the tool z axis, its z along the flange normal
    wrist_in_ee = c.ee_from_hand_root @ np.linalg.inv(c.wrist_from_root)
    np.testing.assert_allclose(wrist_in_ee[:3, 2], [0, 0, 1], atol=1e-9)
    assert {k.link for k in c.keypoints} <= set(kin.link_names)


def test_nominal_reach_from_chain(robots_dir):
    ur5e = nominal_reach(robots_dir / "arms/ur5e/ur5e_glb.urdf", "wrist_3_link")
    xarm = nominal_reach(robots_dir / "arms/xarm7/xarm7_glb.urdf", "link7")
    # a sampled maximum: never above the straight-chain bound, and near the datasheet reach
    kin = get_kinematics(robots_dir / "arms/ur5e/ur5e_glb.urdf")
    bound = sum(np.linalg.norm(j.origin[:3, 3]) for j in kin.chain("wrist_3_link")[1:])
    assert 0.8 < ur5e <= bound and 0.6 < xarm < ur5e
    assert compose_embodiment("ur5_shadow").nominal_reach_m == pytest.approx(ur5e)


def test_composed_jacobian_matches_finite_differences():
    kin = compose_embodiment("ur5_schunk_svh").kinematics()
    q = kin.random_q(np.random.default_rng(2))
    J = np.asarray(kin.jacobian_function("fftip")(q))
    eps = 1e-6
    for i in range(kin.dof):
        dq = np.zeros(kin.dof)
        dq[i] = eps
        np.testing.assert_allclose((kin.fk(q + dq, "fftip")[:3, 3] - kin.fk(q, "fftip")[:3, 3]) / eps, J[:3, i], atol=1e-5)


def test_xyz_rpy_roundtrip():
    from handedit.render.framing import rotation_from_euler

    for rpy in [(0.3, -1.2, 2.0), (0.0, np.pi / 2, 0.4), (1.0, -np.pi / 2, -0.3)]:
        T = np.eye(4)
        T[:3, :3] = rotation_from_euler(*rpy)
        xyz, out = matrix_to_xyz_rpy(T)
        np.testing.assert_allclose(rotation_from_euler(*out), T[:3, :3], atol=1e-12)


def test_bad_ee_link_is_clear(robots_dir):
    with pytest.raises(EmbodimentError, match="ur5e_glb.urdf.*no link 'nope'"):
        compose_urdf(robots_dir / "arms/ur5e/ur5e_glb.urdf", robots_dir / "hands/leap_hand/leap_hand_right.urdf",
                     "nope", np.eye(4))
    with pytest.raises(EmbodimentError, match="hand-only"):
        compose_embodiment("leap")


@pytest.mark.parametrize("emb_id", ["panda_orca", "kuka_sharpa", "ur5_wuji", "jaka_zu7_dexhand021", "rm65_brainco",
                                    "rm75_rohand"])
def test_new_compositions_mount_the_hand_out_of_the_flange(emb_id):
    """The flange-to-hand transform of each composition on the newer assets: the composed tree
    carries it exactly, it is the documented rule (tool frame, adapter length along it, the
    hand's own wrist calibration; a hand with its own wrist module meets the flange with its
    root), and the hand points out of the flange: its fingertips lie ahead of the flange face."""
    from handedit.keypoints import FINGERTIPS

    emb = roster.get_embodiment(emb_id)
    c = compose_embodiment(emb_id)
    kin = c.kinematics()
    q = kin.random_q(np.random.default_rng(2))
    np.testing.assert_allclose(np.linalg.inv(kin.fk(q, c.ee_link)) @ kin.fk(q, c.hand_root), c.ee_from_hand_root, atol=1e-12)
    arm_asset, hand_asset = roster.resolve_arm(emb).asset, roster.resolve_asset(emb).asset
    ee_from_wrist = arm_asset.ee_from_tool_matrix @ emb.arm.tool_from_wrist_matrix
    expected = ee_from_wrist @ hand_asset.wrist_from_root_matrix
    if hand_asset.mount_at_root:
        expected[:3, 3] = ee_from_wrist[:3, 3]
    np.testing.assert_allclose(c.ee_from_hand_root, expected, atol=1e-12)
    q[c.hand_slice] = get_kinematics(c.hand_urdf).neutral()
    tool_from_ee = np.linalg.inv(arm_asset.ee_from_tool_matrix)
    for kp in c.keypoints:
        if kp.mano in FINGERTIPS:
            T = tool_from_ee @ np.linalg.inv(kin.fk(q, c.ee_link)) @ kin.fk(q, kp.link)
            assert (T[:3, :3] @ np.asarray(kp.offset) + T[:3, 3])[2] > 0.04, (emb_id, kp.link)

