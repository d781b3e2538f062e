"""Robot rendering: geometry agrees with FK and the camera model, depth is metric, renderers are
reusable, thread-bound and fail loudly on broken assets. Real dex-urdf hands + packaged Allegro."""

from __future__ import annotations

import json
import os
import shutil
import site
import threading
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import yourdfpy  # noqa: E402

from handedit.camera import Intrinsics, project  # noqa: E402
from handedit.render import RobotRenderer, frame_points, get_renderer, rotation_from_euler  # noqa: E402
from handedit.render.model import joint_limits  # noqa: E402

def _manifest_hands() -> list[str]:
    """Hand keys of the shared assets' manifest (read at collection time; it grows)."""
    from conftest import SHARED

    path = SHARED / "assets/robots/manifest.json"
    if not path.is_file():
        return []  # the robots_dir fixture then fails with what is missing
    return sorted(k for k, v in json.loads(path.read_text()).items() if v["kind"] == "hand")


HANDS = [*_manifest_hands(), "allegro_pkg"]
W, H = 160, 120
# Principal point off-centre on purpose: a cx/cy sign or flip error shows up as misplaced links.
INTR = Intrinsics(fx=120.0, fy=120.0, cx=74.0, cy=64.0, width=W, height=H)


def packaged_allegro() -> Path:
    for sp in site.getsitepackages():
        p = Path(sp) / "cmeel.prefix/share/example-robot-data/robots/allegro_hand_description/urdf/allegro_right_hand.urdf"
        if p.is_file():
            return p
    pytest.fail("example-robot-data's allegro_right_hand.urdf not found in site-packages")


def hand_urdf(robots_dir: Path, key: str) -> Path:
    if key == "allegro_pkg":
        return packaged_allegro()
    manifest = json.loads((robots_dir / "manifest.json").read_text())
    return robots_dir / manifest[key]["urdf"]


def scenario(r: RobotRenderer, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = joint_limits(r.urdf)
    q = np.random.default_rng(seed).uniform(lo, hi)
    T = frame_points(r.points(q), rotation_from_euler(0.4, 0.3, 0.2), INTR, fill=0.7)
    return q, T


@pytest.fixture(scope="module", params=HANDS)
def hand(request, robots_dir):
    path = hand_urdf(robots_dir, request.param)
    r = RobotRenderer(path, W, H)
    q, T = scenario(r)
    res = r.render(q[None], T[None], INTR)
    return request.param, path, r, q, T, res


def test_hand_list_covers_every_hand_asset(robots_dir):
    manifest = json.loads((robots_dir / "manifest.json").read_text())
    hands = {k for k, v in manifest.items() if v["kind"] == "hand"}
    assert hands and hands == set(HANDS) - {"allegro_pkg"}
    # every hand folder of the assets is covered by a manifest entry
    assert {p.name for p in (robots_dir / "hands").iterdir() if p.is_dir()} == {
        Path(manifest[k]["urdf"]).parts[1] for k in hands
    }


def test_joint_names_are_yourdfpy_actuated_order(hand):
    _, path, r, *_ = hand
    assert r.joint_names == yourdfpy.URDF.load(str(path), load_meshes=False).actuated_joint_names


def test_mask_in_image_and_consistent_with_depth(hand):
    _, _, _, _, _, res = hand
    assert res.rgba.shape == (1, H, W, 4) and res.rgba.dtype == np.uint8
    assert res.depth.shape == (1, H, W) and res.depth.dtype == np.float32
    mask, rgba, depth = res.mask[0], res.rgba[0], res.depth[0]
    assert mask.sum() > 0.03 * W * H, "robot should fill a good part of the image"
    border = np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]])
    assert not border.any(), "robot must lie fully inside the image"
    assert set(np.unique(rgba[..., 3])) <= {0, 255}
    np.testing.assert_array_equal(mask, depth > 0)
    assert not rgba[~mask][:, :3].any(), "RGB must be black off the robot"


def test_geometry_matches_fk_projection_and_depth(hand):
    """Independent FK (fresh yourdfpy load) composed with root_pose and handedit.camera.project."""
    _, path, _, q, T, res = hand
    mask, depth = res.mask[0], res.depth[0]
    urdf = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=True)
    urdf.update_cfg(q)
    verts_root = urdf.scene.to_mesh().vertices
    verts_cam = verts_root @ T[:3, :3].T + T[:3, 3]

    # every visual vertex projects into the silhouette (1 px slack for rasterisation)
    grown = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    uv = np.round(project(verts_cam, INTR)).astype(int)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    assert inside.all()
    assert grown[uv[:, 1], uv[:, 0]].mean() > 0.998

    # link frames of links with visual geometry land on the robot
    links = [link.name for link in urdf.robot.links if link.visuals]
    assert links
    origins = np.array([(T @ urdf.get_transform(name, urdf.base_link))[:3, 3] for name in links])
    uv = np.round(project(origins, INTR)).astype(int)
    grown = cv2.dilate(mask.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    off = [name for name, (u, v) in zip(links, uv) if not (0 <= u < W and 0 <= v < H and grown[v, u])]
    assert not off, f"link origins off the rendered robot: {off}"

    # depth is metric z in the camera frame, within the robot's own z range
    d = depth[mask]
    z = verts_cam[:, 2]
    assert d.min() >= z.min() - 1e-3 and d.max() <= z.max() + 1e-3
    assert d.min() < z.min() + 0.003, "the nearest visible surface is near the nearest vertex"


def test_moving_away_shrinks_mask_and_shifts_depth(hand):
    _, _, r, q, T, res = hand
    far = T.copy()
    far[2, 3] += 0.05
    res_far = r.render(q[None], far[None], INTR)
    assert res_far.mask.sum() < 0.95 * res.mask.sum()
    shift = res_far.depth[0][res_far.mask[0]].min() - res.depth[0][res.mask[0]].min()
    assert abs(shift - 0.05) < 0.002


def test_reuse_gives_identical_output(hand):
    _, _, r, q, T, res = hand
    q2, T2 = scenario(r, seed=1)
    other = r.render(q2[None], T2[None], INTR)
    again = r.render(np.stack([q, q2]), np.stack([T, T2]), INTR)
    np.testing.assert_array_equal(again.rgba[0], res.rgba[0])
    np.testing.assert_array_equal(again.depth[0], res.depth[0])
    np.testing.assert_array_equal(again.rgba[1], other.rgba[0])
    assert not np.array_equal(other.rgba[0], res.rgba[0])


def test_colours_follow_assets(robots_dir):
    """Allegro (GLB) black with white tips; packaged Allegro's colourless STL links neutral grey;
    a materials override recolours matching links."""
    def robot_rgb(r):
        q, T = scenario(r)
        res = r.render(q[None], T[None], INTR)
        return res.rgba[0][res.mask[0]][:, :3].astype(float)

    rgb = robot_rgb(RobotRenderer(hand_urdf(robots_dir, "allegro"), W, H))
    assert np.median(rgb) < 40, "dex-urdf Allegro is black"

    rgb = robot_rgb(RobotRenderer(packaged_allegro(), W, H))
    assert np.abs(rgb - rgb.mean(axis=1, keepdims=True)).max() < 12, "colourless meshes render grey"
    assert np.median(rgb) > 60

    rgb = robot_rgb(RobotRenderer(packaged_allegro(), W, H, materials={r"link_.*": (1.0, 0.0, 0.0, 1.0)}))
    red = rgb[:, 0] > 2 * rgb[:, 1] + 20
    assert 0.5 < red.mean() < 1.0, "links recoloured red, base_link keeps its own colour"


def test_bad_inputs_are_rejected(robots_dir):
    r = get_renderer(hand_urdf(robots_dir, "allegro"), W, H)
    q, T = scenario(r)
    with pytest.raises(ValueError, match="dof"):
        r.render(q[None, :-1], T[None], INTR)
    with pytest.raises(ValueError, match="frames"):
        r.render(np.stack([q, q]), T[None], INTR)
    with pytest.raises(ValueError, match="rigid"):
        r.render(q[None], (T @ np.diag([1.0, 1.0, -1.0, 1.0]))[None], INTR)
    with pytest.raises(ValueError, match="finite"):
        r.render(np.full((1, len(q)), np.nan), T[None], INTR)
    with pytest.raises(ValueError, match="intrinsics"):
        r.render(q[None], T[None], Intrinsics.default_for(320, 240))
    with pytest.raises(ValueError, match="RGBA"):
        RobotRenderer(hand_urdf(robots_dir, "allegro"), W, H, materials={".*": (255, 0, 0, 255)})


def test_missing_mesh_names_the_file(robots_dir, tmp_path):
    src = robots_dir / "hands" / "allegro_hand"
    dst = tmp_path / "hands" / "allegro_hand"
    shutil.copytree(src, dst)
    urdf = yourdfpy.URDF.load(str(dst / "allegro_hand_right_glb.urdf"), load_meshes=False)
    victim = next(v.geometry.mesh.filename for link in urdf.robot.links for v in link.visuals if v.geometry.mesh)
    (dst / "allegro_hand_right_glb.urdf").parent.joinpath(victim).unlink()
    with pytest.raises(FileNotFoundError, match=Path(victim).name.replace(".", r"\.")):
        RobotRenderer(dst / "allegro_hand_right_glb.urdf", W, H)


def test_second_thread_builds_its_own_renderer(robots_dir):
    path = hand_urdf(robots_dir, "schunk_svh")
    mine = get_renderer(path, W, H)
    assert get_renderer(path, W, H) is mine, "cached per thread"
    q, T = scenario(mine)
    expected = mine.render(q[None], T[None], INTR)
    out: dict = {}

    def work():
        try:
            with pytest.raises(RuntimeError, match="thread"):
                mine.render(q[None], T[None], INTR)
            theirs = get_renderer(path, W, H)
            out["renderer"] = theirs
            out["result"] = theirs.render(q[None], T[None], INTR)
        except BaseException as exc:  # surfaced in the main thread
            out["error"] = exc

    t = threading.Thread(target=work)
    t.start()
    t.join(timeout=60)
    assert "error" not in out, out.get("error")
    assert out["renderer"] is not mine
    np.testing.assert_array_equal(out["result"].rgba, expected.rgba)
    np.testing.assert_array_equal(out["result"].depth, expected.depth)
    # the main thread's renderer still works after the other thread's context exists
    np.testing.assert_array_equal(mine.render(q[None], T[None], INTR).rgba, expected.rgba)


def _largest_mesh(urdf_path: Path):
    from handedit.render.model import load_urdf

    return max(load_urdf(urdf_path).scene.geometry.values(), key=lambda m: len(m.faces))


def test_decimation_keeps_silhouette_where_it_applies(robots_dir):
    """decimate=0.2 simplifies the Ability hand's dense meshes (its wrist alone has 43k faces)
    and the rendered silhouette stays within IoU 0.98 at random in-limit poses."""
    path = hand_urdf(robots_dir, "ability")
    full = get_renderer(path, W, H)
    dec = RobotRenderer(path, W, H, decimate=0.2)
    assert dec.n_faces < 0.6 * full.n_faces, "the dense meshes are simplified"
    for seed in range(3):
        q, T = scenario(full, seed)
        a = full.render(q[None], T[None], INTR).mask[0]
        b = dec.render(q[None], T[None], INTR).mask[0]
        assert (a & b).sum() / (a | b).sum() >= 0.98, f"pose seed {seed}"
    dec.close()


def test_decimate_mesh_policy(robots_dir):
    """Small meshes stay intact; dense ones are simplified even when unwelded (as GLB exports
    are), keep their silhouette, and fall back to the original when the shape cannot be kept."""
    import trimesh

    from handedit.render.model import DECIMATE_MIN_FACES, decimate_mesh, silhouette_iou

    big = _largest_mesh(hand_urdf(robots_dir, "ability"))
    assert len(big.faces) > 10 * DECIMATE_MIN_FACES
    small = _largest_mesh(hand_urdf(robots_dir, "schunk_svh"))
    assert len(small.faces) <= DECIMATE_MIN_FACES
    assert decimate_mesh(small, 0.1) is small
    assert decimate_mesh(big, 1.0) is big

    # one vertex per triangle corner: nothing is connected until welded
    soup = trimesh.Trimesh(big.triangles.reshape(-1, 3), np.arange(3 * len(big.faces)).reshape(-1, 3), process=False)
    for mesh in (big, soup):
        out = decimate_mesh(mesh, 0.2)
        assert len(out.faces) < 0.5 * len(big.faces)
        assert silhouette_iou(big, out) >= 0.99
    assert decimate_mesh(big, 0.2, min_iou=1.01) is big, "unreachable quality: keep the original"

    # the UR5e's CAD export, where the gentle simplifier pass stalls at ~97 % of the faces
    ur5 = trimesh.load(robots_dir / "arms/ur5e/meshes/visual/upperarm.glb")
    stalls = max(ur5.geometry.values(), key=lambda m: len(m.faces))
    out = decimate_mesh(stalls, 0.2)
    assert len(out.faces) < 0.3 * len(stalls.faces) and silhouette_iou(stalls, out) >= 0.99
    with pytest.raises(ValueError, match="fraction"):
        decimate_mesh(big, 0.0)


def test_decimated_meshes_shade_like_their_source():
    """A dense box split at its creases (as CAD exports are) keeps flat faces when simplified:
    its vertex normals stay square to the faces, not averaged across the edges. A box without
    seams is shaded smooth across its edges, and so is its simplification (LEAP's glossy palm
    went flat black when split)."""
    import trimesh

    from handedit.render.model import DECIMATE_MIN_FACES, decimate_mesh

    welded = trimesh.creation.box((0.04, 0.03, 0.02))
    while len(welded.faces) <= 2 * DECIMATE_MIN_FACES:
        welded = welded.subdivide()
    creased = trimesh.graph.smooth_shade(welded, angle=np.radians(30))
    assert len(creased.vertices) > len(welded.vertices), "the creased box has seams"
    for box, flat in ((creased, True), (welded, False)):
        out = decimate_mesh(box, 0.1)
        assert len(out.faces) < 0.5 * len(box.faces)
        square = np.abs(out.vertex_normals).max(axis=1)
        if flat:
            assert (square > 0.999).all(), f"{(square <= 0.999).sum()} of {len(square)} normals lean across an edge"
        else:
            assert (square < 0.99).sum() >= 8, "the corners' normals lean, as the source's do"


def test_silhouette_error_measures_how_far_the_outline_moves():
    """Against itself a mesh strays 0; a sphere 1 mm larger or moved by 3 mm strays that much
    (rounded up by at most three grid cells: the measure errs wide); a 1 mm detail 30 mm off the
    sphere that is lost strays 1 mm, its own width, not its distance from the rest."""
    import trimesh

    from handedit.render.model import LOD_SILHOUETTE_PX, silhouette_error

    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    cell = 0.1 / (LOD_SILHOUETTE_PX - 1)
    assert silhouette_error(ball, ball) == 0.0
    grown = trimesh.creation.icosphere(subdivisions=4, radius=0.051)
    assert -cell <= silhouette_error(ball, grown) - 0.001 <= 3 * cell
    moved = ball.copy()
    moved.apply_translation((0.003, 0.0, 0.0))
    assert -cell <= silhouette_error(ball, moved) - 0.003 <= 3 * cell
    detail = trimesh.creation.box((0.001, 0.001, 0.001))
    detail.apply_translation((0.0, 0.0, -0.08))  # 30 mm below the sphere
    with_detail = trimesh.util.concatenate([ball, detail])
    cell = 0.13 / (LOD_SILHOUETTE_PX - 1)
    assert -cell <= silhouette_error(with_detail, ball) - 0.001 <= 3 * cell


def test_levels_of_detail_are_cached_by_content(tmp_path, monkeypatch):
    """A fresh process reads the levels back from the user cache, identical to the built ones;
    a corrupt cache file is built again and rewritten; another mesh gets its own file."""
    import trimesh

    from handedit.render import model

    monkeypatch.setenv("HANDEDIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(model, "_LODS", {})
    ball = trimesh.creation.icosphere(subdivisions=5, radius=0.05)
    built = model.lod_meshes(ball)
    files = list((tmp_path / "lod").glob("*.npz"))
    assert len(files) == 1 and len(built) == len(model.LOD_FRACTIONS)
    assert len(built[-1][0].faces) < 0.2 * len(ball.faces) and built[-1][1] > 0

    def same(a, b):
        for (ma, ea), (mb, eb) in zip(a, b):
            assert ea == eb
            for x, y in ((ma.vertices, mb.vertices), (ma.faces, mb.faces), (ma.vertex_normals, mb.vertex_normals)):
                np.testing.assert_array_equal(x, y)

    monkeypatch.setattr(model, "_LODS", {})  # a fresh process
    monkeypatch.setattr(model, "decimate_mesh", lambda *a, **k: pytest.fail("read back, not built"))
    same(built, model.lod_meshes(ball))
    monkeypatch.undo()
    monkeypatch.setenv("HANDEDIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(model, "_LODS", {})
    files[0].write_bytes(files[0].read_bytes()[:100])  # truncated
    same(built, model.lod_meshes(ball))
    assert files[0].stat().st_size > 1000, "rewritten whole"
    model.lod_meshes(trimesh.creation.icosphere(subdivisions=5, radius=0.04))
    assert len(list((tmp_path / "lod").glob("*.npz"))) == 2


def test_a_mesh_and_its_mirror_share_their_levels(tmp_path, monkeypatch):
    """A left robot's mesh (its right one reflected, as a mirrored URDF loads it) gets the right
    one's levels reflected, without simplifying again, and the same levels whichever side is
    asked first."""
    import trimesh

    from handedit.render import model

    right = trimesh.creation.icosphere(subdivisions=5, radius=0.05)
    right.vertices[:, 1] += 0.5 * right.vertices[:, 0]  # a shear: the mirror image is another shape
    left = trimesh.Trimesh(right.vertices * [1, -1, 1], right.faces[:, ::-1], process=False)

    def levels(first, second, cache):
        monkeypatch.setenv("HANDEDIT_CACHE_DIR", str(tmp_path / cache))
        monkeypatch.setattr(model, "_LODS", {})
        a = model.lod_meshes(first)
        simplify = model.decimate_mesh
        monkeypatch.setattr(model, "decimate_mesh", lambda *a, **k: pytest.fail("simplified twice"))
        b = model.lod_meshes(second)
        monkeypatch.setattr(model, "decimate_mesh", simplify)
        assert len(list((tmp_path / cache / "lod").glob("*.npz"))) == 1
        return a, b

    r1, l1 = levels(right, left, "right-first")
    l2, r2 = levels(left, right, "left-first")
    for (mr, er), (ml, el) in zip(r1, l1):
        assert er == el
        np.testing.assert_array_equal(ml.vertices, mr.vertices * [1, -1, 1])
        np.testing.assert_array_equal(ml.faces, mr.faces[:, ::-1])
    for x, y in ((r1, r2), (l1, l2)):
        for (ma, ea), (mb, eb) in zip(x, y):
            assert ea == eb
            np.testing.assert_array_equal(ma.vertices, mb.vertices)
            np.testing.assert_array_equal(ma.faces, mb.faces)


def test_levels_of_detail_coarsen_with_distance(robots_dir):
    """The Ability hand's dense meshes get levels with fewer faces and growing errors; a link is
    drawn at the coarsest level whose outline moves at most lod_px pixels at its nearest point
    (full mesh when it reaches the near plane): a close-up draws more faces than the whole hand in
    view, and both silhouettes stay those of the full meshes."""
    from handedit.render.renderer import Z_NEAR, lod_levels

    error = np.array([[0.0, 0.001, 0.004], [0.0, 0.002, np.inf]])
    cube = np.array([[x, y, z] for x in (-0.01, 0.01) for y in (-0.01, 0.01) for z in (-0.01, 0.01)])
    corners = np.stack([cube, cube])
    levels = {}
    for z in (0.05, 0.2, 0.5, 2.0, 0.5 * Z_NEAR):
        poses = np.tile(np.eye(4), (2, 1, 1))
        poses[:, 2, 3] = z
        levels[z] = lod_levels(poses, corners, INTR, error, px=1.0).tolist()
    # f = 120 px: error * 120 / (z - 0.01) <= 1
    assert levels == {0.05: [0, 0], 0.2: [1, 0], 0.5: [2, 1], 2.0: [2, 1], 0.5 * Z_NEAR: [0, 0]}, levels

    path = hand_urdf(robots_dir, "ability")
    full = get_renderer(path, W, H)
    lod = RobotRenderer(path, W, H, lod_px=1.0)
    dense = [p for p in lod.model.parts if len(p.faces) > 10000]
    assert dense and all(p.lods for p in dense)
    for p in dense:
        faces = [len(x.faces) for x in (p, *p.lods)]
        errors = [x.error for x in p.lods]
        assert faces[-1] < 0.5 * faces[0] and errors == sorted(errors) and errors[-1] > 0
    q, T = scenario(full)
    # the same pose seen through a 16x longer lens (a close-up of the hand's middle) and as framed
    close = Intrinsics(fx=16 * INTR.fx, fy=16 * INTR.fy, cx=W / 2 + 16 * (INTR.cx - W / 2), cy=H / 2 + 16 * (INTR.cy - H / 2),
                       width=W, height=H)
    drawn = {}
    for name, intr in (("close-up", close), ("framed", INTR)):
        a = full.render(q[None], T[None], intr).mask[0]
        b = lod.render(q[None], T[None], intr).mask[0]
        assert a.sum() > 0.1 * W * H and (a & b).sum() / (a | b).sum() >= 0.98, name
        shown = [n for n in lod.scene.mesh_nodes if n.mesh.is_visible]
        drawn[name] = {n.name.split("@lod")[0]: int(n.name.split("@lod")[1]) if "@lod" in n.name else 0 for n in shown}
        if name == "framed":
            assert sum(len(prim.indices) for n in shown for prim in n.mesh.primitives) < 0.5 * full.n_faces
    both = drawn["close-up"].keys() & drawn["framed"].keys()
    assert both and all(drawn["close-up"][k] <= drawn["framed"][k] for k in both), drawn
    assert any(drawn["close-up"][k] < drawn["framed"][k] for k in both), drawn
    lod.close()


def test_decimation_without_backend_fails_clearly(robots_dir, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "fast_simplification", None)  # import now raises ImportError
    with pytest.raises(ImportError, match="fast-simplification") as err:
        RobotRenderer(hand_urdf(robots_dir, "ability"), W, H, decimate=0.2)
    assert "decimate=None" in str(err.value)


def test_render_embodiment_uses_roster(robots_dir, monkeypatch):
    from handedit import embodiments
    from handedit.render import render_embodiment

    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))
    emb = embodiments.get_embodiment("allegro")
    r = RobotRenderer(embodiments.resolve_urdf(emb), W, H, materials=emb.materials)
    q, T = scenario(r)
    res = render_embodiment("allegro", q[None], T[None], INTR)
    assert res.mask.sum() > 0.03 * W * H
    np.testing.assert_array_equal(res.rgba, r.render(q[None], T[None], INTR).rgba)


HAND_ARMS = ["panda_allegro", "ur5_inspire", "ur5_schunk_svh", "ur5_shadow", "xarm_ability", "xarm_leap",
             "panda_orca", "kuka_sharpa", "ur5_wuji", "jaka_zu7_dexhand021", "rm65_brainco",
             "rm75_rohand"]
NEW_HANDS = ["orca", "revo2", "sharpa", "wuji", "dexhand021", "rohand"]  # hands wired from the assets' newer robots


@pytest.mark.parametrize("emb_id", HAND_ARMS + ["allegro", "leap"] + NEW_HANDS)
def test_renderer_fk_equals_the_scene_graph(robots_dir, monkeypatch, emb_id):
    """The renderer's one-pass FK (``render.fk.LinkFK``) gives yourdfpy's scene-graph transforms,
    polynomial mimics included (RoHand), at random configurations."""
    from handedit.embodiments.linkage import poly_mimics, update_cfg
    from handedit.render import embodiment_renderer

    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))
    r = embodiment_renderer(emb_id, W, H)
    lo, hi = joint_limits(r.urdf)
    polys = poly_mimics(r.urdf_path)
    assert (emb_id in ("rohand", "rm75_rohand")) == bool(polys)
    for seed in range(3):
        q = np.random.default_rng(seed).uniform(lo, hi)
        ours = r.link_transforms(q)
        update_cfg(r.urdf, q, polys)
        for link, T in ours.items():
            np.testing.assert_allclose(T, r.urdf.get_transform(link, r.urdf.base_link), atol=1e-9, err_msg=link)


@pytest.mark.parametrize("emb_id", HAND_ARMS + ["leap"] + NEW_HANDS)
def test_embodiment_render_contains_projected_fk_links(robots_dir, monkeypatch, emb_id):
    """Every available hand-arm (composed URDF, roster colours) renders inside the image and the
    casadi-FK positions of its visual links project onto the rendered silhouette."""
    from handedit.embodiments import get_embodiment, resolve_urdf
    from handedit.embodiments.kinematics import get_kinematics
    from handedit.render import embodiment_renderer
    from handedit.render.views import canonical_views

    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))
    r = embodiment_renderer(emb_id, W, H)
    rig = canonical_views(r, 1)
    res = r.render(rig.qpos, rig.camera_from_root, rig.intrinsics)
    mask = res.mask[0]
    assert mask.sum() > 0.01 * W * H
    assert not np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]]).any()
    kin = get_kinematics(resolve_urdf(get_embodiment(emb_id)))
    T = rig.camera_from_root[0]
    links = r.model.links
    pts = np.array([(T @ kin.fk(rig.qpos[0], l))[:3, 3] for l in links])
    uv = np.round(project(pts, rig.intrinsics)).astype(int)
    grown = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    off = [l for l, (u, v) in zip(links, uv) if not (0 <= u < W and 0 <= v < H and grown[v, u])]
    assert not off, f"link origins off the silhouette: {off}"
    # the arm's pixels are tagged (HAND_HIDDEN reads them), and every robot pixel stays opaque
    assert set(np.unique(res.rgba[0, ..., 3]).tolist()) <= {0, 255}
    if emb_id in HAND_ARMS:
        from handedit.embodiments.compose import compose_embodiment

        c = compose_embodiment(emb_id)
        assert c.base_link in r.arm_links and c.ee_link in r.arm_links and c.hand_root not in r.arm_links
        arm = res.arm[0]
        assert not (arm & ~mask).any() and 0.1 * mask.sum() < arm.sum() < 0.95 * mask.sum()
    else:
        assert res.arm is None and not r.arm_links


def test_jaka_joint_caps_are_blue_faces_of_its_grey_links(robots_dir, monkeypatch):
    """The frozen description's blue joint caps: ``Link_k@caps`` splits each STL link mesh into
    the faces square to a joint axis near it (blue) and the rest (metallic grey)."""
    from handedit.embodiments import get_embodiment, render_materials, resolve_urdf
    from handedit.embodiments.roster import arm_spec
    from handedit.render.model import build_model, srgb_to_linear

    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))
    emb = get_embodiment("jaka_zu7_dexhand021")
    mats = render_materials(emb)
    JAKA_BLUE, GRAY = arm_spec("jaka_zu7").materials[r"Link_[1-6]@caps"], arm_spec("jaka_zu7").materials[r".*"]  # its arm file
    assert JAKA_BLUE[2] > 0.5 > JAKA_BLUE[0] and max(GRAY[:3]) - min(GRAY[:3]) < 0.05  # blue caps, grey links
    assert mats[r"Link_3@caps"] == JAKA_BLUE and mats[r"Link_3"] == GRAY and not any(k.startswith("r_f_") and k.endswith("@caps") for k in mats)
    model = build_model(resolve_urdf(emb), materials=mats)
    blue, grey = srgb_to_linear(JAKA_BLUE), srgb_to_linear(GRAY)
    for k in range(1, 7):
        parts = {p.material.rgba: p for p in model.parts if p.link == f"Link_{k}"}
        assert set(parts) == {blue, grey}, k
        cap, body = parts[blue], parts[grey]
        assert 0 < len(cap.faces) < 0.5 * len(body.faces)
        tri = cap.vertices[cap.faces].astype(float)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        assert np.median(np.abs(n).max(axis=1)) > 0.95  # flat faces square to an axis


@pytest.mark.parametrize("emb_id", ["allegro", "xarm_ability"])
def test_screen_box_render_equals_the_full_frame(robots_dir, monkeypatch, emb_id):
    """Rendering only the robot's screen box (scissored clear, box read-back) and only the links
    in view gives the pixels of the full frame with every link drawn, exactly; the boxes hold
    every robot pixel; a robot off screen is not drawn; one the near plane cuts is boxed too
    (its clipped hull), and so is one whose links cross the near plane beside the camera."""
    import handedit.render.renderer as renderer_mod
    from handedit.render import embodiment_renderer

    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))
    r = embodiment_renderer(emb_id, W, H)
    q, T = scenario(r)
    q2, T2 = scenario(r, seed=3)
    away, near, beside = T.copy(), T.copy(), T.copy()
    away[:3, 3] += [5.0, 0.0, 0.0]  # far to the right of the view
    z = (r.points(q) @ T[:3, :3].T + T[:3, 3])[:, 2]
    near[2, 3] -= z.min() + 0.3 * (z.max() - z.min())  # the near plane cuts the robot: its nearest 30 % behind the lens
    beside[:3, 3] += [0.3 * (z.max() - z.min()), 0.0, near[2, 3] - T[2, 3]]  # and to the right of the axis
    qs, Ts = np.stack([q, q2, q, q, q]), np.stack([T, T2, away, near, beside])
    boxed = r.render(qs, Ts, INTR)
    monkeypatch.setattr(renderer_mod, "screen_box", lambda *a, **k: (0, 0, W, H))
    monkeypatch.setattr(renderer_mod, "out_of_view", lambda c, *a: np.zeros(len(c), bool))  # every link drawn
    full = r.render(qs, Ts, INTR)
    np.testing.assert_array_equal(boxed.rgba, full.rgba)
    np.testing.assert_array_equal(boxed.depth, full.depth)
    assert boxed.mask[:2].sum() > 0.01 * W * H and not boxed.mask[2].any()
    for i in (0, 1, 3, 4):
        outside = boxed.mask[i].copy()
        outside[boxed.box(i)] = False
        assert not outside.any(), i
    for i in (0, 1):
        x, y, w, h = boxed.boxes[i]
        assert 0 < w * h < W * H  # a real crop
    assert all(full.mask[i].any() for i in (3, 4)), "the near-plane cases must show part of the robot"
    assert any(0 < boxed.boxes[i][2] * boxed.boxes[i][3] < W * H for i in (3, 4)), "a cut robot gets a real crop too"


def test_links_out_of_view_are_the_ones_no_pixel_shows():
    """A link is skipped only when its box lies wholly beyond one plane of the view: behind the
    camera, or past an image edge (even with corners behind the camera); one that straddles an
    edge or the near plane is drawn."""
    from handedit.render.renderer import out_of_view

    cube = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05)])
    at = {"in view": (0, 0, 1.0), "behind": (0, 0, -0.5), "left": (-3.0, 0, 1.0), "below": (0, 3.0, 1.0),
          "right, reaching behind": (2.0, 0, 0.02), "on the left edge": (-0.6, 0, 1.0), "through the lens": (0, 0, 0.03)}
    poses = np.tile(np.eye(4), (len(at), 1, 1))
    poses[:, :3, 3] = list(at.values())
    out = dict(zip(at, out_of_view(poses, np.tile(cube, (len(at), 1, 1)), INTR)))
    assert out == {"in view": False, "behind": True, "left": True, "below": True, "right, reaching behind": True,
                   "on the left edge": False, "through the lens": False}, out


def test_near_clipped_hull_holds_what_the_plane_leaves():
    """A cube crossing the near plane: the clipped points lie in front of it and span the part
    of the cube in front (x, y within the cube's, z from the plane to the cube's front)."""
    from handedit.render.renderer import NEAR_CLIP, Z_NEAR, _near_clipped

    cube = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.2, 0.2) for z in (-0.05, 0.05)])
    behind = cube + (0, 0, -1.0)  # a second link wholly behind the camera drops out
    p = _near_clipped(np.concatenate([cube, behind]), np.array([0] * 8 + [1] * 8))
    assert (p[:, 2] > Z_NEAR).all() and np.isclose(p[:, 2].min(), NEAR_CLIP) and np.isclose(p[:, 2].max(), 0.05)
    np.testing.assert_allclose([p[:, 0].min(), p[:, 0].max(), p[:, 1].min(), p[:, 1].max()], [-0.1, 0.1, -0.2, 0.2])
    assert len(_near_clipped(behind, np.zeros(8, int))) == 0


def test_a_collected_renderer_leaves_the_current_context_alone(robots_dir):
    """A renderer dropped without close() is deleted whenever the garbage collector runs,
    possibly inside another renderer's frame: the other renderer's context stays current."""
    import gc

    from handedit.render.gl import make_offscreen

    a = RobotRenderer(packaged_allegro(), W, H)
    q, T = scenario(a)
    before = a.render(q[None], T[None], INTR)
    doomed = make_offscreen(W, H)
    import ctypes

    from OpenGL.EGL import eglGetCurrentContext

    def current() -> int | None:
        return ctypes.cast(eglGetCurrentContext(), ctypes.c_void_p).value

    a._gl._platform.make_current()  # as inside a's frame
    mine = current()
    doomed.delete()
    del doomed
    gc.collect()
    assert mine is not None and current() == mine
    np.testing.assert_array_equal(a.render(q[None], T[None], INTR).rgba, before.rgba)
    a.close()


def test_scene_nodes_iterate_in_the_order_they_were_added():
    """pyrender keeps nodes in sets, iterated by memory address: equally distant meshes were drawn,
    and lights summed, in an order that changed between processes (same inputs, other pixels)."""
    import pyrender

    from handedit.render.gl import Scene

    scene = Scene()
    box = pyrender.Mesh.from_trimesh(__import__("trimesh").creation.box())
    meshes = [scene.add(box, name=f"m{i}") for i in range(40)]
    lights = [scene.add(pyrender.DirectionalLight(intensity=float(i + 1))) for i in range(6)]
    assert list(scene.mesh_nodes) == meshes and list(scene.directional_light_nodes) == lights
    assert list(scene.light_nodes) == lights
    scene.remove_node(meshes[3])
    assert list(scene.mesh_nodes) == meshes[:3] + meshes[4:]
