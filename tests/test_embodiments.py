"""Roster, asset resolution and URDF loading errors."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from handedit.embodiments import (
    AssetsMissing,
    BrokenUrdf,
    EmbodimentError,
    MissingMesh,
    UrdfNotFound,
    describe_embodiment,
    get_embodiment,
    list_embodiments,
    load_urdf,
    resolve_asset,
    resolve_urdf,
)
from handedit.embodiments.kinematics import get_kinematics
from handedit.keypoints import FINGERTIPS

HAND_IDS = ["allegro", "shadow", "leap", "inspire", "ability", "schunk_svh", "orca", "revo2", "sharpa", "wuji", "dexhand021",
            "rohand"]


@pytest.fixture
def assets(monkeypatch, robots_dir: Path) -> Path:
    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))
    return robots_dir


def test_roster_ids_and_fields():
    from handedit.embodiments.robot_files import BUILTIN

    ids = [e.id for e in list_embodiments()]
    files = [p for d in ("hands", "hand_arms") for p in (BUILTIN / d).glob("*.yaml")]
    assert set(HAND_IDS) <= set(ids) and len(ids) == len(set(ids)) == len(files)
    assert get_embodiment("inspire").name == "RH56DFX"
    assert get_embodiment("schunk_svh").name == "Schunk SVH"
    tracks = [e.track for e in list_embodiments()]
    assert tracks.count("hand") == 13 and tracks.count("hand_arm") == 13
    for e in list_embodiments():
        assert (e.track == "hand") == (e.arm is None)
        assert e.description.startswith("A ") and e.description.endswith(".")
        for pattern in e.materials:
            re.compile(pattern)


def _paper_rows(shared_dir: Path, macro: str) -> dict[str, str]:
    tex = (shared_dir / "paper" / "handedit.tex").read_text()
    return {m.group(1): " ".join(m.group(2).split()) for m in re.finditer(r"\\" + macro + r"\{([^}]*)\}\{ \}\{([^}]*)\}", tex)}


def test_names_and_descriptions_verbatim_from_paper(shared_dir):
    """The paper's reference bank is the spec: same display names, descriptions word for word."""
    hands, arms = _paper_rows(shared_dir, "handbankrow"), _paper_rows(shared_dir, "armbankrow")
    assert len(hands) == 13 and len(arms) == 13
    ours = {e.name: e for e in list_embodiments()}
    assert set(ours) == set(hands) | set(arms)
    for name, text in {**hands, **arms}.items():
        e = ours[name]
        assert e.track == ("hand" if name in hands else "hand_arm")
        assert e.description == text, name


def test_missing_assets_name_what_to_provide(assets):
    from handedit.embodiments import asset_status

    ok, msg = asset_status(get_embodiment("rh5dg2"))
    assert not ok and "hands/inspire_rh5dg2/rh5dg2_right.urdf" in msg and "HANDEDIT_ASSET_DIRS" in msg
    with pytest.raises(AssetsMissing, match="rh5dg2_right.urdf"):
        describe_embodiment("ur5_rh5dg2")
    available = [e.id for e in list_embodiments() if asset_status(e)[0]]
    assert set(HAND_IDS) <= set(available)
    assert {"ur5_shadow", "xarm_ability", "xarm_leap", "panda_allegro", "ur5_inspire", "ur5_schunk_svh",
            "panda_orca", "kuka_sharpa", "ur5_wuji", "jaka_zu7_dexhand021", "rm65_brainco", "rm75_rohand"} <= set(available)
    assert len(available) == 24  # all but rh5dg2 and ur5_rh5dg2 (its meshes are not public)


def test_hand_arm_describe_arm_joints_first(assets):
    track, joints = describe_embodiment("xarm_ability")
    assert track == "hand_arm"
    assert joints[:7] == [f"joint{i}" for i in range(1, 8)] and joints[7:] == describe_embodiment("ability")[1]


def test_hand_arm_materials_keep_hand_colours_off_the_arm(assets):
    from handedit.embodiments import render_materials

    mats = render_materials(get_embodiment("xarm_leap"))
    hand = get_embodiment("leap")
    assert mats[re.escape("fingertip")] == hand.link_color("fingertip")
    assert all(not re.fullmatch(p, "link3") for p in mats), "xArm links keep their URDF colours"


def test_unknown_id_lists_known():
    with pytest.raises(EmbodimentError, match="known ids: .*allegro"):
        get_embodiment("not_a_robot")


def test_allegro_resolves_from_pypi_package(monkeypatch):
    monkeypatch.delenv("HANDEDIT_ASSET_DIRS", raising=False)
    p = resolve_urdf(get_embodiment("allegro"))
    assert p.name == "allegro_right_hand.urdf" and p.is_file()
    assert "example-robot-data" in str(p)
    with pytest.raises(AssetsMissing, match=r"hands/shadow_hand/shadow_hand_right_glb\.urdf.*HANDEDIT_ASSET_DIRS"):
        resolve_urdf(get_embodiment("shadow"))


@pytest.mark.parametrize("emb_id", HAND_IDS)
def test_resolve_from_asset_dir(assets, emb_id):
    emb = get_embodiment(emb_id)
    ra = resolve_asset(emb)
    assert ra.origin.resolve().is_relative_to(Path(assets).resolve())  # a symlinked shared/ resolves too
    kin = get_kinematics(ra.path)
    links = set(kin.link_names)
    kps = ra.asset.keypoints
    assert {k.link for k in kps} <= links
    assert sum(k.mano == 0 for k in kps) == 1
    assert {k.mano for k in kps} & set(FINGERTIPS)
    assert {n for n, _ in ra.asset.locked_joints} <= set(kin.joint_names)
    # every link gets a colour consistent with the description
    assert all(emb.link_color(l) is not None for l in links)


@pytest.mark.parametrize("emb_id", HAND_IDS)
def test_wrist_from_root_matches_calibration(assets, emb_id):
    from handedit.retarget.palm import calibrate_wrist_from_root

    T = resolve_asset(get_embodiment(emb_id)).asset.wrist_from_root_matrix
    np.testing.assert_allclose(T, calibrate_wrist_from_root(emb_id), atol=2e-4)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)


def test_load_urdf_meshes(assets):
    u = load_urdf(resolve_urdf(get_embodiment("allegro")))
    assert len(u.scene.geometry) > 0
    assert load_urdf(resolve_urdf(get_embodiment("allegro"))) is u  # cached


def _copy_allegro(robots_dir: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "robots" / "hands" / "allegro_hand"
    shutil.copytree(robots_dir / "hands" / "allegro_hand", dst)
    return dst / "allegro_hand_right_glb.urdf"


def test_missing_urdf_names_file(tmp_path):
    with pytest.raises(UrdfNotFound, match=re.escape(str(tmp_path / "nope.urdf"))):
        load_urdf(tmp_path / "nope.urdf")


def test_broken_xml_names_file(robots_dir, tmp_path):
    urdf = _copy_allegro(robots_dir, tmp_path)
    urdf.write_text(urdf.read_text()[:-200])  # truncated XML
    with pytest.raises(BrokenUrdf, match=re.escape(str(urdf.resolve())) + ".*not valid XML"):
        load_urdf(urdf)


def test_missing_mesh_names_file(robots_dir, tmp_path):
    urdf = _copy_allegro(robots_dir, tmp_path)
    meshes = sorted((urdf.parent / "meshes").rglob("*.glb"))
    victim = meshes[0]
    victim.unlink()
    with pytest.raises(MissingMesh, match=re.escape(victim.name)) as ei:
        load_urdf(urdf)
    assert str(urdf.resolve()) in str(ei.value) and "meshes/" in str(ei.value)


def test_describe_embodiment(assets):
    track, joints = describe_embodiment("inspire")
    assert track == "hand" and len(joints) == 6 and joints[0] == "thumb_proximal_yaw_joint"
    with pytest.raises(EmbodimentError) as ei:
        describe_embodiment("nope")
    assert int(ei.value.reason) == 902


def test_dexhand021_couplings_and_debug_visuals_are_derived(assets, monkeypatch, tmp_path):
    """The vendor URDF's distal joints become mimics of the proximal ones (1:1) and its debug
    visuals are dropped, in a derived file; FK agrees with yourdfpy's on it to 1e-9."""
    import yourdfpy
    from lxml import etree

    monkeypatch.setenv("HANDEDIT_CACHE_DIR", str(tmp_path))
    raw = assets / "hands/dexhand021/urdf/dexhand021_right_simplified.urdf"
    before = raw.read_bytes()
    path = resolve_asset(get_embodiment("dexhand021")).path
    assert path != raw and path.is_relative_to(tmp_path) and raw.read_bytes() == before
    kin = get_kinematics(path)
    assert kin.dof == 15 and not any(n.endswith("_4") for n in kin.joint_names)
    u = yourdfpy.URDF.load(str(path), load_meshes=False)
    assert u.actuated_joint_names == kin.joint_names
    rng = np.random.default_rng(1)
    for _ in range(4):
        q = kin.clip(rng.uniform(-0.5, 2.0, kin.dof))
        u.update_cfg(q)
        for link in ("r_f_link1_tip", "r_f_link2_4", "r_f_link5_tip"):
            np.testing.assert_allclose(u.get_transform(link, u.base_link), kin.fk(q, link), atol=1e-9)
        rel = np.linalg.inv(kin.fk(q, "r_f_link2_3")) @ kin.fk(q, "r_f_link2_4")
        angle = np.arccos(np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1, 1))
        assert angle == pytest.approx(q[kin.joint_names.index("r_f_joint2_3")], abs=1e-9)  # the 1:1 coupling
    hidden = [l for l in etree.parse(str(path)).getroot().findall("link") if re.fullmatch(r"r_f_link\d_(tip|pad)", l.get("name"))]
    assert len(hidden) == 10 and all(l.find("visual") is None for l in hidden)
    raw_links = etree.parse(str(raw)).getroot().findall("link")
    assert sum(l.find("visual") is not None for l in raw_links if re.fullmatch(r"r_f_link\d_(tip|pad)", l.get("name"))) == 10


def test_rohand_linkages_close_over_the_actuator_range(assets, monkeypatch, tmp_path):
    """RoHand's open-tree URDF (25 joints) becomes a 6-actuator hand whose 19 passive joints are
    polynomial mimics of their slider; over each actuator's range, every pin of the slider-cranks
    and four-bars meets itself through both branches (and the thumb's unmodelled rod keeps its
    length), while the straight-line mimics alone (what plain URDF tools apply) leave them open.
    FK of the casadi kinematics and of yourdfpy (with the polynomials applied) agree to 1e-9."""
    import yourdfpy

    from handedit.embodiments.kinematics import Kinematics
    from handedit.embodiments.linkage import closure_gaps, poly_mimics, solve, update_cfg

    monkeypatch.setenv("HANDEDIT_CACHE_DIR", str(tmp_path))
    ra = resolve_asset(get_embodiment("rohand"))
    kin, tree = get_kinematics(ra.path), Kinematics(ra.origin)
    assert tree.dof == 25 and kin.dof == 6
    assert kin.joint_names == ["if_slider_link", "mf_slider_link", "rf_slider_link", "lf_slider_link", "th_root_link",
                               "th_slider_link"]
    polys = poly_mimics(ra.path)
    assert len(polys) == 19
    u = yourdfpy.URDF.load(str(ra.path), load_meshes=False)
    worst_line = 0.0
    for lk in ra.asset.linkages:
        a = kin.joint_names.index(lk.actuator)
        xs = np.linspace(kin.lower[a], kin.upper[a], 25)
        exact = solve(tree, lk, xs)
        for x, row in zip(xs, exact):
            q = np.zeros(tree.dof)
            q[tree.joint_names.index(lk.actuator)] = x
            line = q.copy()
            for j, v in zip(lk.passive, row):
                q[tree.joint_names.index(j)] = float(polys[j](x))
                m = u.joint_map[j].mimic
                line[tree.joint_names.index(j)] = m.multiplier * x + m.offset
            assert closure_gaps(tree, lk, q).max() < 5e-6, (lk.actuator, x)
            worst_line = max(worst_line, closure_gaps(tree, lk, line).max())
        assert np.ptp(exact[:, lk.passive.index(lk.passive[-1])]) > 0.3  # the linkage moves its joints
    assert worst_line > 1e-4
    rng = np.random.default_rng(3)
    for _ in range(4):
        q = rng.uniform(kin.lower, kin.upper)
        update_cfg(u, q, polys)
        for link in ("if_distal_link", "if_connecting_link", "lf_slider_abpart_link", "th_distal_link", "th_connecting_link"):
            np.testing.assert_allclose(u.get_transform(link, u.base_link), kin.fk(q, link), atol=1e-9)
