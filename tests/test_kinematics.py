"""Symbolic (casadi) FK agrees with yourdfpy; limits, mimic joints and the Jacobian."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from handedit.embodiments import get_embodiment, resolve_asset
from handedit.embodiments.kinematics import get_kinematics
from handedit.embodiments.urdf import load_urdf


def _erd_allegro(monkeypatch) -> Path:
    monkeypatch.delenv("HANDEDIT_ASSET_DIRS", raising=False)
    ra = resolve_asset(get_embodiment("allegro"))
    assert ra.asset.source == "package"
    return ra.path


def _hand_urdfs(robots_dir: Path) -> list[Path]:
    """Every hand URDF the shared assets' manifest lists (it grows as robots are added)."""
    manifest = json.loads((robots_dir / "manifest.json").read_text())
    urdfs = sorted(robots_dir / v["urdf"] for v in manifest.values() if v["kind"] == "hand")
    assert urdfs and all(p.is_file() for p in urdfs), urdfs
    return urdfs


def _check_fk(path: Path, n: int = 4, seed: int = 0) -> None:
    kin = get_kinematics(path)
    urdf = load_urdf(path, load_meshes=False)
    assert kin.joint_names == list(urdf.actuated_joint_names)
    rng = np.random.default_rng(seed)
    for q in kin.random_q(rng, n):
        assert np.all((q >= kin.lower) & (q <= kin.upper))
        urdf.update_cfg(q)
        for link in kin.link_names:
            np.testing.assert_allclose(
                kin.fk(q, link), urdf.get_transform(link, urdf.base_link), atol=1e-9, err_msg=f"{path.name}:{link}"
            )


def test_fk_matches_yourdfpy_dex_urdf_hands(robots_dir):
    for path in _hand_urdfs(robots_dir):
        _check_fk(path)


def test_fk_matches_yourdfpy_example_robot_data_allegro(monkeypatch):
    _check_fk(_erd_allegro(monkeypatch))


def test_limits_and_mimic(robots_dir):
    kin = get_kinematics(robots_dir / "hands/allegro_hand/allegro_hand_right_glb.urdf")
    i = kin.joint_names.index("joint_12.0")
    assert (kin.lower[i], kin.upper[i]) == (0.263, 1.396)
    assert kin.neutral()[i] == 0.263  # zero pose is outside this joint's limits
    inspire = get_kinematics(robots_dir / "hands/inspire_hand/inspire_hand_right.urdf")
    assert inspire.dof == 6 and "index_intermediate_joint" not in inspire.joint_names  # mimic is derived
    assert np.all(np.isfinite(inspire.lower))


def test_jacobian_matches_finite_differences(robots_dir):
    kin = get_kinematics(robots_dir / "hands/schunk_hand/schunk_svh_hand_right_glb.urdf")
    q = kin.random_q(np.random.default_rng(3))
    J = np.asarray(kin.jacobian_function("fftip")(q))
    assert J.shape == (6, kin.dof)
    eps = 1e-6
    T0 = kin.fk(q, "fftip")
    for i in range(kin.dof):
        dq = np.zeros(kin.dof)
        dq[i] = eps
        T1 = kin.fk(q + dq, "fftip")
        np.testing.assert_allclose((T1[:3, 3] - T0[:3, 3]) / eps, J[:3, i], atol=1e-5)
        W = (T1[:3, :3] - T0[:3, :3]) / eps @ T0[:3, :3].T
        np.testing.assert_allclose([W[2, 1], W[0, 2], W[1, 0]], J[3:, i], atol=1e-5)


def test_unknown_link_is_clear(robots_dir):
    kin = get_kinematics(robots_dir / "hands/leap_hand/leap_hand_right.urdf")
    with pytest.raises(KeyError, match="not_a_link"):
        kin.fk_function("not_a_link")


def _package_urdfs() -> list[Path]:
    """The example-robot-data URDFs the roster uses (Allegro, Panda, UR5, xArm7)."""
    from handedit.embodiments import roster

    out = []
    package = [a for spec in (roster.hand_spec("allegro"), roster.arm_spec("panda"), roster.arm_spec("ur5"), roster.arm_spec("xarm7"))
               for a in spec.assets if a.source == "package"]
    assert len(package) == 4
    for a in package:
        p = roster._package_file(a.package, a.path)
        assert p is not None, f"{a.package} does not ship {a.path}"
        out.append(p)
    return out


def test_fk_matches_yourdfpy_arms_and_assemblies(robots_dir):
    urdfs = sorted((robots_dir / "arms").glob("*/*.urdf")) + sorted((robots_dir / "assembly").glob("*/*.urdf"))
    assert len(urdfs) == 7
    for path in urdfs:
        _check_fk(path, n=2)


def test_fk_matches_yourdfpy_packaged_robots():
    for path in _package_urdfs():
        _check_fk(path, n=2)


def test_chain_runs_root_to_link(robots_dir):
    kin = get_kinematics(robots_dir / "arms/xarm7/xarm7_glb.urdf")
    chain = kin.chain("link7")
    assert chain[0].parent == kin.base_link and chain[-1].child == "link7"
    assert [j.name for j in chain if j.q_index >= 0] == [f"joint{i}" for i in range(1, 8)]
