"""OakInk2, HOI4D and HO-Cap adapters on fixture trees in their layouts, and one curate run
over a fixture clip of each MANO-based dataset (ARCTIC included)."""

from __future__ import annotations

import numpy as np
import pytest

import _arctic_fixture as afx
import _dataset_fixtures as fx
from handedit.camera import project
from handedit.reasons import Reason
from handedit.sources import (ArcticTree, HocapSpec, HocapTree, Hoi4dSpec, Hoi4dTree, Oakink2Spec, Oakink2Tree, SourceError)


@pytest.fixture(scope="module")
def trees(tmp_path_factory):
    d = tmp_path_factory.mktemp("mano_sources")
    mano = fx.write_mano(d / "mano")
    return {"mano": mano, "mano_pca": fx.write_mano(d / "mano_pca", fx.pca_basis()),
            "oakink2": fx.write_oakink2(d / "oakink2"), "hoi4d": fx.write_hoi4d(d / "hoi4d"),
            "hocap": fx.write_hocap(d / "hocap"), "arctic": afx.write_tree(d / "arctic", d / "mano_arctic")}


def _skin_hits(frames, kp, valid, intr) -> float:
    hits = []
    for i in range(len(frames)):
        for s in range(kp.shape[1]):
            if not valid[i, s].all():
                continue
            uv = np.round(project(kp[i, s], intr)).astype(int)
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < afx.W) & (uv[:, 1] >= 0) & (uv[:, 1] < afx.H)
            px = frames[i][uv[inside, 1], uv[inside, 0]].astype(int)
            hits.append((np.abs(px - [215, 160, 120]).max(-1) < 40).mean())
    return float(np.mean(hits))


def test_oakink2_quaternions_centring_world_to_camera_and_mocap_frame_ids(trees):
    src = Oakink2Spec(root=trees["oakink2"], sequence=fx.OAK_TOKEN, mano_dir=trees["mano"]).open()
    info, c = src.info(), src.read(0, afx.T)
    want = np.stack([fx.to_cam(fx.world_joints(s, centre=True)) for s in fx.SIDES], 1)
    assert np.abs(c.keypoints - want).max() < 1e-6  # wxyz quaternions, manotorch centring, then + tsl, cam_extr
    plain = np.stack([fx.to_cam(fx.world_joints(s)) for s in fx.SIDES], 1)
    assert np.abs(c.keypoints - plain).max() > 5e-3  # (centring matters: the wrist is off MANO's origin)
    assert info.meta["object"] == "O_box" and info.meta["mocap_frames"] == [fx.OAK_FIDS[0], fx.OAK_FIDS[-1]]
    assert src.seq.images[3].name == f"{fx.OAK_FIDS[3]:06d}.png"  # image frames are named by mocap frame id
    assert c.frame_ok.all() and _skin_hits(c.frames, c.keypoints, c.keypoints_valid, src.intrinsics) > 0.95
    assert np.allclose(c.object_pose[5], fx.world_to_cam(5) @ fx.BOX_POSE) and c.object_mask.mean() > 0.01


def test_hoi4d_camera_frame_hands_palette_masks_and_object_pose(trees):
    root = trees["hoi4d"]
    src = Hoi4dSpec(root=root, sequence=fx.HOI_SEQ, mano_dir=trees["mano"]).open()
    info, c = src.info(), src.read(0, afx.T)
    assert info.hands == ("right",) and info.fps == 15.0  # right hand only, 15 fps
    assert np.abs(c.keypoints[:, 0] - fx.world_joints("right")).max() < 1e-6  # manopth joints + trans, camera frame
    assert _skin_hits(c.frames, c.keypoints, c.keypoints_valid, src.intrinsics) > 0.95
    assert np.allclose(c.object_pose[0], fx.BOX_POSE, atol=1e-6)  # Euler XYZ + centre
    box = afx.paint(np.zeros((1, 1, 21, 3)), [fx._box_cam(0, np.eye(4))], afx.K, None)[0]
    painted = (box == (150, 150, 150)).all(-1)
    m = c.object_mask[0]
    assert (m & painted).sum() / (m | painted).sum() > 0.9  # the shipped mask's object labels, not the hand's
    from handedit.sources.hoi4d import decode_mask, voc_palette

    pal = voc_palette()
    assert (decode_mask(pal[np.array([[0, 1, 2, 6]])]) == [[0, 1, 2, 6]]).all()
    assert [s.sequence for s in Hoi4dTree(root=root, mano_dir=trees["mano"]).clips()] == [fx.HOI_SEQ]


def test_hoi4d_reads_its_15_fps_video_when_frames_are_not_decoded(trees, tmp_path):
    import shutil

    import cv2

    base = tmp_path / "copy"
    shutil.copytree(trees["hoi4d"].parent, base)
    rgb = base / "HOI4D_release" / fx.HOI_SEQ / "align_rgb"
    jpgs = sorted(rgb.glob("*.jpg"))
    for fps, name in ((15.0, "image.mp4"), (30.0, "fast.mp4")):
        w = cv2.VideoWriter(str(rgb / name), cv2.VideoWriter_fourcc(*"mp4v"), fps, (afx.W, afx.H))
        for p in jpgs:
            w.write(cv2.imread(str(p)))
        w.release()
    want = Hoi4dSpec(root=trees["hoi4d"], sequence=fx.HOI_SEQ, mano_dir=trees["mano"]).open().read(0, afx.T)
    for p in jpgs:
        p.unlink()
    c = Hoi4dSpec(root=base / "HOI4D_release", sequence=fx.HOI_SEQ, mano_dir=trees["mano"]).open().read(0, afx.T)
    assert c.frame_ok.all() and np.abs(c.frames.astype(int) - want.frames).mean() < 6  # the same frames, re-encoded
    assert np.array_equal(c.keypoints, want.keypoints)
    (rgb / "fast.mp4").replace(rgb / "image.mp4")
    with pytest.raises(SourceError, match="30 fps.*decode.py"):
        Hoi4dSpec(root=base / "HOI4D_release", sequence=fx.HOI_SEQ, mano_dir=trees["mano"]).open()


def test_hocap_pca_subject_betas_hololens_view_and_missing_frames(trees):
    src = HocapSpec(root=trees["hocap"], subject=fx.HOCAP_SUBJECT, sequence=fx.HOCAP_SEQ, mano_dir=trees["mano_pca"]).open()
    info, c = src.info(), src.read(0, afx.T)
    assert info.hands == ("left", "right")
    want = np.stack([fx.to_cam(fx.hocap_world_joints(s)) for s in fx.SIDES], 1)
    ok = c.keypoints_valid.all(-1)
    assert not ok[list(fx.LEFT_MISSING), 0].any() and ok[:, 1].all() and ok.sum() == 2 * afx.T - len(fx.LEFT_MISSING)
    assert np.abs(c.keypoints[ok] - want[ok]).max() < 1e-6  # 45 PCA @ the basis, betas from calibration, PV pose
    assert np.allclose(src.intrinsics.K, afx.K)  # intrinsics.bin: transposed, fx negated
    assert _skin_hits(c.frames, c.keypoints, c.keypoints_valid, src.intrinsics) > 0.95
    assert np.allclose(c.object_pose[2], fx.world_to_cam(2) @ fx.BOX_POSE, atol=1e-6)
    assert len(HocapTree(root=trees["hocap"], mano_dir=trees["mano_pca"]).clips()) == 1


def test_bad_layouts_are_one_clear_error(trees, tmp_path):
    with pytest.raises(SourceError, match="anno_preview"):
        Oakink2Tree(root=tmp_path).clips()
    with pytest.raises(SourceError, match="does not exist"):
        Oakink2Spec(root=trees["oakink2"], sequence="nope", mano_dir=trees["mano"]).open()
    with pytest.raises(SourceError, match="neither frames nor image.mp4"):
        Hoi4dSpec(root=tmp_path, sequence=fx.HOI_SEQ, mano_dir=trees["mano"]).open()
    (tmp_path / "subject_1" / "old").mkdir(parents=True)
    with pytest.raises(SourceError, match="meta.json"):
        HocapSpec(root=tmp_path, subject="subject_1", sequence="old", mano_dir=trees["mano"]).open()
    with pytest.raises(SourceError, match="MANO_(LEFT|RIGHT).pkl not found"):
        Oakink2Spec(root=trees["oakink2"], sequence=fx.OAK_TOKEN, mano_dir=tmp_path).open()


def test_curate_one_fixture_clip_of_each_mano_dataset(trees, tmp_path, prefect_api, dask_cluster):
    """Every stage on each: keypoints from MANO, the object's mesh in the retarget QC."""
    from handedit.flows.config import ClusterConfig, CurateConfig
    from handedit.flows.curate import run_curate
    from handedit.storage import Unit, open_store, read_records

    sources = [ArcticTree(root=trees["arctic"], mano_dir=trees["arctic"].parent / "mano_arctic"),
               Oakink2Tree(root=trees["oakink2"], mano_dir=trees["mano"]),
               Hoi4dTree(root=trees["hoi4d"], mano_dir=trees["mano"]),
               HocapTree(root=trees["hocap"], mano_dir=trees["mano_pca"])]
    config = CurateConfig(out=str(tmp_path / "handedit.zarr"), sources=sources, embodiments=["allegro"],
                          frames_per_chunk=8, cluster=ClusterConfig(address=dask_cluster.scheduler_address))
    run_curate(config)
    store = open_store(config.out)
    clips = sorted(store["clips"].group_keys())
    assert [c.split("-")[0] for c in clips] == ["arctic", "hocap", "hoi4d", "oakink2"]
    for clip in clips:
        for stage in ("ingest", "registration", "segment"):
            assert (store[Unit(stage, clip).path]["status"][:] == Reason.OK).all(), (clip, stage)
        recs = read_records(store, Unit("retarget", clip, embodiment="allegro")).values()
        assert recs and all(r.extra["qc_contact_checked"] for r in recs), clip
        render = store[Unit("render", clip, embodiment="allegro").path]["hand_status"][:]
        assert (render == Reason.OK).any(axis=0).all(), (clip, render)  # every annotated hand gets a robot
        assert (store[Unit("qc", clip, embodiment="allegro").path]["status"][:] == Reason.OK).any(), clip


def test_an_object_mesh_or_an_image_edited_in_place_changes_the_clip_fingerprint(trees, tmp_path):
    """The object's mesh is read by ingest (occlusion depth) and retarget (contact QC), the
    frames by ingest: their content, not only the annotation files, identifies the clip."""
    import shutil

    import cv2

    root = tmp_path / "oakink2"
    shutil.copytree(trees["oakink2"], root)
    spec = Oakink2Spec(root=root, sequence=fx.OAK_TOKEN, mano_dir=trees["mano"])
    before = spec.open().info().fingerprint
    assert spec.open().info().fingerprint == before  # stable
    mesh = root / "object_raw" / "align_ds" / "O_box" / "model.obj"
    import trimesh

    trimesh.load(mesh).apply_scale(1.1).export(mesh)  # same file name, a bigger box
    moved = spec.open().info().fingerprint
    assert moved != before
    # and a frame's image file rewritten in place (same name, other pixels)
    image = sorted((root / "data" / fx.OAK_TOKEN / fx.OAK_EGO).glob("*.png"))[1]
    cv2.imwrite(str(image), 255 - cv2.imread(str(image)))
    assert spec.open().info().fingerprint not in (before, moved)
