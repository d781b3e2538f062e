"""The ARCTIC adapter on a fixture tree in the official layout (tests/_arctic_fixture.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from handedit.camera import project
from handedit.reasons import Reason
from handedit.sources import ArcticSpec, ArcticTree, SourceError
import _arctic_fixture as fx


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    d = tmp_path_factory.mktemp("arctic")
    fx.write_tree(d / "data", d / "mano")
    return d / "data", d / "mano"


def _spec(tree, **kw):
    root, mano = tree
    return ArcticSpec(root=root, subject=fx.SUBJECT, sequence=fx.SEQ, mano_dir=mano, **kw)


def test_keypoints_are_the_chain_fk_in_the_egocentric_camera(tree):
    src = _spec(tree).open()
    info = src.info()
    c = src.read(0, fx.T)
    assert info.hands == ("left", "right") and info.has_object and c.keypoints.shape == (fx.T, 2, 21, 3)
    assert np.abs(c.keypoints - fx.expected_keypoints()).max() < 1e-6  # MANO (flat_hand_mean=False), world -> ego
    assert c.keypoints_valid.all()
    assert np.allclose(np.linalg.inv(c.world_from_camera[5]), fx.world_to_cam(5))


def test_frames_are_aligned_by_ioi_offset_and_undistorted(tree):
    src = _spec(tree, frames=(4, 12)).open()
    c = src.read(0, 8)
    rows, cols = fx.MARK_CORE
    marks = c.frames[:, rows, cols].reshape(8, -1, 3).mean(1)[:, 0]
    assert np.allclose(marks, 8 * (np.arange(4, 12) + fx.IOI_OFFSET), atol=4)  # mocap 4 is image 4 + ioi_offset
    intr = src.intrinsics
    # the painted skeletons are where the pinhole projection puts the joints once undistorted
    hit_und, hit_raw, shift = [], [], []
    for i in range(8):
        raw = cv2.cvtColor(cv2.imread(str(src.seq.images[4 + i])), cv2.COLOR_BGR2RGB)
        for s in range(2):
            uv = np.round(project(c.keypoints[i, s], intr)).astype(int)
            uv = uv[(uv[:, 0] >= 0) & (uv[:, 0] < fx.W) & (uv[:, 1] >= 0) & (uv[:, 1] < fx.H)]
            assert len(uv) >= 18
            skin = lambda im: (np.abs(im[uv[:, 1], uv[:, 0]].astype(int) - [215, 160, 120]).max(-1) < 40)  # noqa: E731
            hit_und.append(skin(c.frames[i]).mean())
            hit_raw.append(skin(raw).mean())
            dist_uv = cv2.projectPoints(c.keypoints[i, s].reshape(-1, 1, 3).astype(float), np.zeros(3), np.zeros(3),
                                        fx.K, fx.DIST8)[0].reshape(-1, 2)
            shift.append(np.linalg.norm(dist_uv - project(c.keypoints[i, s], intr), axis=1).max())
    assert np.mean(hit_und) > 0.95 and max(shift) > 5  # the distortion moves joints by > 5 px
    assert np.mean(hit_und) > np.mean(hit_raw)


def test_object_pose_units_mask_and_articulated_mesh(tree):
    src = _spec(tree).open()
    c = src.read(0, fx.T)
    obj = fx.object_params()
    want = fx.world_to_cam(7)[:3, :3] @ (obj[7, 4:] / 1000.0) + fx.world_to_cam(7)[:3, 3]
    assert np.allclose(c.object_pose[7][:3, 3], want)  # millimetres -> metres, world -> ego
    verts, faces = src.object_mesh()
    assert 0.05 < np.ptp(verts, axis=0).max() < 0.2  # metres (the template is in mm)
    area = c.object_mask.mean(axis=(1, 2))
    assert (area > 0.01).all()
    ys, xs = np.nonzero(c.object_mask[7])
    centre = project(want[None], src.intrinsics)[0]
    assert abs(xs.mean() - centre[0]) < 15 and abs(ys.mean() - centre[1]) < 25
    assert area[-1] != area[0]  # the lid opens (the top part follows the articulation angle)


def test_bad_input_is_one_clear_error(tree, tmp_path, monkeypatch):
    root, mano = tree
    monkeypatch.delenv("HANDEDIT_MANO_DIR", raising=False)
    with pytest.raises(SourceError, match="--mano-dir"):
        ArcticSpec(root=root, subject=fx.SUBJECT, sequence=fx.SEQ).open()
    with pytest.raises(SourceError, match=r"MANO_(LEFT|RIGHT)\.pkl not found"):
        ArcticSpec(root=root, subject=fx.SUBJECT, sequence=fx.SEQ, mano_dir=tmp_path).open()
    with pytest.raises(SourceError, match="does not exist"):
        ArcticSpec(root=root, subject=fx.SUBJECT, sequence="nope_01", mano_dir=mano).open()
    with pytest.raises(SourceError, match="raw_seqs"):
        ArcticTree(root=tmp_path).clips()
    assert [s.id for s in ArcticTree(root=root, mano_dir=mano).clips()] == [f"arctic-{fx.SUBJECT}-{fx.SEQ}"]


def test_curate_arctic_tree_through_every_stage(tree, tmp_path, prefect_api, dask_cluster):
    from handedit.flows.config import ClusterConfig, CurateConfig
    from handedit.flows.curate import run_curate
    from handedit.storage import Unit, open_store, read_ledger, read_records

    root, mano = tree
    config = CurateConfig(out=str(tmp_path / "handedit.zarr"), sources=[ArcticTree(root=root, mano_dir=mano)],
                          embodiments=["allegro"], frames_per_chunk=8,
                          cluster=ClusterConfig(address=dask_cluster.scheduler_address))
    run_curate(config)
    store = open_store(config.out)
    clip = f"arctic-{fx.SUBJECT}-{fx.SEQ}"
    for stage in ("ingest", "registration", "segment"):
        assert (store[Unit(stage, clip).path]["status"][:] == Reason.OK).all(), stage
    ret = Unit("retarget", clip, embodiment="allegro")
    assert all(r.extra["qc_contact_checked"] for r in read_records(store, ret).values())  # the object mesh is used
    for stage in ("retarget", "render", "composite"):
        hs = store[Unit(stage, clip, embodiment="allegro").path]["hand_status"][:]
        assert (hs == Reason.OK).all(), (stage, hs)
    assert (store[Unit("qc", clip, embodiment="allegro").path]["status"][:] == Reason.OK).all()
    assert not len(read_ledger(store))
