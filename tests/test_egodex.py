"""The EgoDex adapter on the two real episodes in ../shared/data/egodex (read in place).

Golden values from that folder's README; broken trees are made of symlinks to the real
files plus files the test writes, in a temporary folder (nothing derived is kept)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from handedit.camera import project
from handedit.keypoints import JOINT_INDEX
from handedit.sources import EgoDexTree, SourceError
from handedit.sources.egodex import EgoDexSpec, joint_names, read_annotations

LID, INSERT = ("add_remove_lid", "0"), ("insert_remove", "2")


def spec(root: Path, which=LID, **kw) -> EgoDexSpec:
    return EgoDexSpec(root=root, task=which[0], episode=which[1], **kw)


def test_golden_keypoints(egodex_dir):
    src = spec(egodex_dir).open()
    c = src.read(0, 1)
    left, right = src.info().hands.index("left"), src.info().hands.index("right")
    np.testing.assert_allclose(c.keypoints[0, right, JOINT_INDEX["wrist"]], (0.2229, 0.2687, 0.2614), atol=1e-4)
    np.testing.assert_allclose(c.keypoints[0, right, JOINT_INDEX["index_tip"]], (0.1494, 0.2014, 0.3652), atol=1e-4)
    np.testing.assert_allclose(c.keypoints[0, left, JOINT_INDEX["wrist"]], (-0.0346, 0.2727, 0.2963), atol=1e-4)


def test_both_hands_camera_frame_and_info(egodex_dir):
    src = spec(egodex_dir, INSERT).open()
    info = src.info()
    assert info.hands == ("left", "right") and info.n_frames == 161 and info.has_arm
    assert (info.width, info.height) == (1920, 1080) and info.intrinsics.fx == pytest.approx(736.6339, abs=1e-3)
    assert info.world["up"] == [0.0, 1.0, 0.0] and info.world["support_plane"] is None
    assert info.meta["task"] and info.meta["llm_description"] and info.meta["dataset"] == "egodex"
    c = src.read(10, 14)
    assert c.keypoints.shape == (4, 2, 21, 3) and c.keypoints_valid.all()
    # camera frame = inv(T_world_camera) @ T_world_joint, column 3 (Apple's loader), checked independently
    import h5py

    with h5py.File(egodex_dir / "insert_remove/2.hdf5", "r") as f:
        for side, k in (("left", 0), ("right", 1)):
            names, arms = joint_names(side)
            T_wc = f["transforms/camera"][12]
            for j, name in enumerate(names):
                p = (np.linalg.inv(T_wc) @ f[f"transforms/{name}"][12])[:3, 3]
                np.testing.assert_allclose(c.keypoints[2, k, j], p, atol=1e-5)
            shoulder = (np.linalg.inv(T_wc) @ f[f"transforms/{arms[1]}"][12])[:3, 3]
            np.testing.assert_allclose(c.arm_keypoints[2, k, 1], shoulder, atol=1e-5)
    # both hands in front of the camera, inside the image, the left one left of the right one
    uv = project(c.keypoints[:, :, 0], info.intrinsics)
    assert (c.keypoints[:, :, 0, 2] > 0.1).all() and (uv[:, 0, 0] < uv[:, 1, 0]).all()


def test_window_and_working_resolution(egodex_dir):
    full = spec(egodex_dir).open()
    win = spec(egodex_dir, frames=(20, 28), resize=(960, 540)).open()
    info = win.info()
    assert info.clip_id == "egodex-add_remove_lid-0-f20-28" and info.n_frames == 8
    assert info.meta["resolution"] == {"file": [1920, 1080], "working": [960, 540]}
    a, b = full.read(22, 23), win.read(2, 3)
    np.testing.assert_array_equal(a.keypoints, b.keypoints)
    assert b.frames.shape == (1, 540, 960, 3)
    # intrinsics scale with the image: a joint projects to the same content
    uv_full = project(a.keypoints[0, 1], full.info().intrinsics)
    uv_win = project(b.keypoints[0, 1], info.intrinsics)
    np.testing.assert_allclose((uv_win + 0.5) * 2, uv_full + 0.5, atol=1e-3)
    # frames are the full-resolution frames, downsampled
    import cv2

    np.testing.assert_allclose(cv2.resize(a.frames[0], (960, 540), interpolation=cv2.INTER_AREA).astype(int),
                               b.frames[0].astype(int), atol=1)


def test_confidence_threshold_marks_joints_invalid(egodex_dir):
    c = spec(egodex_dir, min_confidence=0.5).open().read(0, 20)
    assert 0.05 < (~c.keypoints_valid).mean() < 0.9  # ARKit rates occluded fingertips low
    assert (c.keypoints[~c.keypoints_valid] == 0).all()


def test_tree_listing_is_stable(egodex_dir, tmp_path):
    for t, eps in (("a_task", ["10", "2", "0"]), ("b_task", ["1"])):
        (tmp_path / t).mkdir()
        for e in eps:
            (tmp_path / t / f"{e}.hdf5").symlink_to(egodex_dir / "add_remove_lid/0.hdf5")
            (tmp_path / t / f"{e}.mp4").symlink_to(egodex_dir / "add_remove_lid/0.mp4")
    ids = [s.id for s in EgoDexTree(root=tmp_path).clips()]
    assert ids == ["egodex-a_task-0", "egodex-a_task-2", "egodex-a_task-10", "egodex-b_task-1"]
    assert [s.id for s in EgoDexTree(root=tmp_path, max_clips=2).clips()] == ids[:2]
    assert [s.id for s in EgoDexTree(root=tmp_path, tasks=["b_task"]).clips()] == ids[3:]
    with pytest.raises(SourceError, match="no task folder"):
        EgoDexTree(root=tmp_path, tasks=["nope"]).clips()


def broken_tree(egodex_dir: Path, root: Path) -> dict[str, str]:
    """A tree with the two good episodes and three broken ones; -> clip id: expected message."""
    for task, ep in (LID, INSERT):
        (root / task).mkdir(parents=True, exist_ok=True)
        for ext in ("hdf5", "mp4"):
            (root / task / f"{ep}.{ext}").symlink_to(egodex_dir / task / f"{ep}.{ext}")
    bad = root / "broken"
    bad.mkdir()
    (bad / "1.hdf5").symlink_to(egodex_dir / "add_remove_lid/0.hdf5")  # no 1.mp4
    data = (egodex_dir / "add_remove_lid/0.hdf5").read_bytes()
    (bad / "2.hdf5").write_bytes(data[: len(data) // 3])  # truncated
    (bad / "2.mp4").symlink_to(egodex_dir / "add_remove_lid/0.mp4")
    (bad / "3.hdf5").symlink_to(egodex_dir / "add_remove_lid/0.hdf5")  # 94 frames ...
    (bad / "3.mp4").symlink_to(egodex_dir / "insert_remove/2.mp4")  # ... with a 161-frame video
    return {"egodex-broken-1": "does not exist", "egodex-broken-2": "could not be", "egodex-broken-3": "161 frames, the HDF5 94"}


def test_broken_episodes_name_the_file_and_the_fix(egodex_dir, tmp_path):
    expected = broken_tree(egodex_dir, tmp_path)
    by_id = {s.id: s for s in EgoDexTree(root=tmp_path).clips()}
    for clip_id, msg in expected.items():
        with pytest.raises(SourceError, match=msg) as e:
            by_id[clip_id].open()
        assert str(tmp_path / "broken") in str(e.value) and ("re-download" in str(e.value) or "beside it" in str(e.value))
    missing = tmp_path / "broken" / "4.hdf5"
    os.symlink(egodex_dir / "add_remove_lid/0.mp4", tmp_path / "broken" / "4.mp4")
    with pytest.raises(SourceError, match="4.hdf5 does not exist"):
        read_annotations(missing)
