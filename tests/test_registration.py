"""Registration of keypoints to the pixels: exact keypoints stay put, shifted ones come back."""

from __future__ import annotations

import numpy as np
import pytest

from handedit.camera import project
from handedit.reasons import Reason
from handedit.sources.synthetic import SyntheticSpec
from handedit.vision.registration import RegistrationConfig, register, rotation_for_offset


@pytest.fixture(scope="module")
def clip():
    """The reaching phase (open hand, no object in front of the fingers)."""
    src = SyntheticSpec(n_frames=24, width=320, height=240, seed=4).open()
    return src.info(), src.read(2, 10)


def test_exact_keypoints_stay_put(clip):
    info, c = clip
    r = register(c.frames, c.keypoints, c.keypoints_valid, info.intrinsics, RegistrationConfig(method="colour-align"))
    present = r.hand_status == Reason.OK
    assert present.all()
    assert np.abs(r.offset_px[present]).max() <= 2.0  # px at 320x240
    assert (r.status == Reason.OK).all()
    # the synthetic source says its keypoints are exact: "auto" leaves them alone
    assert info.keypoints_exact
    auto = register(c.frames, c.keypoints, c.keypoints_valid, info.intrinsics, exact=True)
    assert auto.method == "none:keypoints-exact" and (auto.offset_px == 0).all()


def test_shifted_keypoints_are_moved_back(clip):
    info, c = clip
    intr = info.intrinsics
    shift = np.array([10.0, -7.0])
    moved = c.keypoints.astype(float).copy()
    for i in range(len(moved)):
        R = rotation_for_offset(project(moved[i, 0, 0], intr), shift, intr)
        moved[i, 0] = moved[i, 0] @ R.T
    uv0 = project(c.keypoints[:, 0], intr)
    np.testing.assert_allclose(project(moved[:, 0], intr) - uv0, np.broadcast_to(shift, uv0.shape), atol=3.0)  # a rotation shifts all joints about alike (wide lens)
    r = register(c.frames, moved.astype(np.float32), c.keypoints_valid, intr)
    assert r.method == "classical:colour-align"
    ok = r.hand_status[:, 0] == Reason.OK
    err = np.linalg.norm(project(r.keypoints[ok, 0], intr) - uv0[ok], axis=-1)[c.keypoints_valid[ok, 0]]
    assert np.median(err) < 4.0 and np.median(np.linalg.norm(r.offset_px[ok, 0] + shift, axis=-1)) < 4.0
    # depth and shape are kept: the correction is a rotation about the camera centre (+ depth scale)
    np.testing.assert_allclose(np.linalg.norm(np.diff(r.keypoints[ok, 0], axis=1), axis=-1),
                               np.linalg.norm(np.diff(moved[ok, 0], axis=1), axis=-1), rtol=1e-4, atol=1e-6)


def test_sides_out_of_view_are_absent_and_untracked_sides_have_no_keypoints(clip):
    info, c = clip
    kp = np.concatenate([c.keypoints, c.keypoints], axis=1).astype(float)
    valid = np.concatenate([c.keypoints_valid, c.keypoints_valid], axis=1)
    kp[:, 0, :, 0] += 5.0  # far to the right: out of view
    valid[:6, 1] = False  # not tracked
    r = register(c.frames, kp, valid, info.intrinsics)
    assert (r.hand_status[:, 0] == Reason.ABSENT).all()
    assert (r.hand_status[:6, 1] == Reason.NO_KEYPOINTS).all()
    assert (r.status == Reason.OK).all()  # registration never rejects a frame
    assert RegistrationConfig(method="none") and (register(c.frames, kp, valid, info.intrinsics,
                                                           RegistrationConfig(method="none")).offset_px == 0).all()


def test_a_large_disk_dilates_exactly_as_opencv_does():
    """``_dilate_disk`` (row-wise) is the registration's speed-up of ``cv2.dilate`` by its disk."""
    import cv2

    from handedit.vision.registration import _dilate_disk, _disk

    rng = np.random.default_rng(0)
    for _ in range(200):
        h, w = rng.integers(1, 90, 2)
        m = rng.random((h, w)) < rng.choice([0.002, 0.02, 0.2])
        r = float(rng.uniform(0, 30))
        assert (_dilate_disk(m, r) == cv2.dilate(m.astype(np.uint8), _disk(r)).astype(bool)).all(), (h, w, r)


def test_the_search_in_its_box_finds_what_the_whole_image_finds(egodex_dir, monkeypatch):
    """Each side's offset is searched in the box it can read (``_search_box``): on real EgoDex
    frames (both hands, offsets of 10-40 px) the offsets, scales and scores equal those of the
    search over the whole image."""
    from handedit.sources.egodex import EgoDexSource, EgoDexSpec
    from handedit.vision import registration

    src = EgoDexSource(EgoDexSpec(root=egodex_dir, task="add_remove_lid", episode="0", frames=(0, 6), resize=(960, 540)))
    c = src.read(0, 6)
    boxed = register(c.frames, c.keypoints, c.keypoints_valid, src.intrinsics)
    monkeypatch.setattr(registration, "_search_box", lambda shape, *a: (slice(0, shape[0]), slice(0, shape[1])))
    whole = register(c.frames, c.keypoints, c.keypoints_valid, src.intrinsics)
    assert (boxed.hand_status == Reason.OK).sum() >= 8 and np.abs(boxed.offset_px).max() >= 5
    np.testing.assert_array_equal(boxed.offset_px, whole.offset_px)
    np.testing.assert_array_equal(boxed.scale, whole.scale)
    np.testing.assert_array_equal(boxed.score, whole.score)
