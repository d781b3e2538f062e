"""The human arm from 3-D joints (handedit.vision.arm), the sleeve in the hand-arm mask on
real EgoDex frames, the off-arm screen (Reason.OFF_ARM) and the hidden-hand screen (Reason.HAND_HIDDEN)."""

from __future__ import annotations

import numpy as np
import pytest

from handedit.camera import Intrinsics, project
from handedit.reasons import Reason
from handedit.vision.arm import (MAX_HAND_HIDDEN, capsule, clip_near, corridor, coverage, forearm_capsule, hand_hidden_shares,
                                  limbs, off_arm_shares, outside_share, screen_status)

INTR = Intrinsics(300.0, 300.0, 159.5, 119.5, 320, 240)


def test_capsule_width_follows_depth():
    """A fronto-parallel segment at depth z projects to a band 2 f r / z wide."""
    for z in (0.3, 0.6):
        pts = np.array([[-0.1, 0.0, z], [0.1, 0.0, z]])
        m = capsule(pts, INTR, 0.02, (240, 320))
        col = m[:, 160]
        assert abs(int(col.sum()) - 2 * 300 * 0.02 / z) <= 2
        assert col[119] and not m[:, :5].any() or z == 0.3  # centred on the axis


def test_capsule_clipped_at_the_near_plane():
    """An arm running behind the camera keeps its in-view part and its direction."""
    wrist, elbow = np.array([0.0, 0.05, 0.3]), np.array([0.0, 0.3, -0.1])
    a, b = clip_near(wrist, elbow, 0.05)
    assert b[2] == pytest.approx(0.05) and np.allclose(a, wrist)
    m = forearm_capsule(wrist, elbow, INTR, (240, 320))
    assert m.any() and m[239, 160]  # it reaches the bottom border, where the arm leaves the view
    assert clip_near(np.array([0, 0, -0.1]), np.array([0, 0, 0.01]), 0.05) is None


def test_limbs_stop_at_the_first_untracked_joint():
    kp = np.zeros((2, 21, 3))
    kp[:, 0] = (0, 0, 0.3)
    arm = np.array([[[0, 0.2, 0.2], [0, 0.3, 0.0], [0, 0.3, -0.1]]] * 2, float)
    valid = np.array([[True, False, True], [True, True, True]])
    out = limbs(kp, arm, valid)
    assert out.shape == (2, 4, 3)
    assert np.isfinite(out[0, :2]).all() and np.isnan(out[0, 2:]).all()
    assert np.isfinite(out[1]).all()


def test_coverage_corridor_outside_share():
    arm = np.zeros((240, 320), bool)
    arm[100:140, 100:200] = True
    mask = np.zeros_like(arm)
    mask[100:140, 100:150] = True
    assert coverage(mask, arm) == pytest.approx(0.5)
    assert coverage(mask, np.zeros_like(arm)) is None  # not in view
    corr = corridor(mask, arm, frac=0.05)  # grown by 16 px
    assert corr[90, 150] and not corr[60, 150]
    robot = np.zeros_like(arm)
    robot[0:40, 0:100] = True  # all outside
    robot[100:140, 100:200] = True  # 4000 inside, 4000 outside
    assert outside_share(robot, corr) == pytest.approx(0.5, abs=0.01)
    assert outside_share(np.zeros_like(arm), corr) == 0.0


def test_off_arm_shares_flags_a_robot_where_no_arm_was():
    n, S, H, W = 2, 1, 240, 320
    human = np.zeros((n, S, H, W), bool)
    human[:, 0, 150:240, 140:180] = True  # an arm rising from the bottom border
    robot = np.zeros_like(human)
    robot[0, 0, 150:240, 135:185] = True  # frame 0: the robot covers the arm
    robot[1, 0, 0:120, 0:320] = True  # frame 1: a link across the top of the view
    robot[1, 0, 150:240, 140:180] = True
    checked = np.ones((n, S), bool)
    shares = off_arm_shares(robot, human, None, None, checked)
    assert shares[0, 0] < 0.05 and shares[1, 0] > 0.25
    # the tracked forearm widens the corridor: a capsule along the top row makes frame 1 plausible
    line = np.array([[[-0.3, -0.15, 0.5], [0.3, -0.15, 0.5], [np.nan] * 3]] * n)[:, None]
    widened = off_arm_shares(robot, human, line, INTR, checked)
    assert widened[1, 0] < shares[1, 0]
    assert np.isnan(off_arm_shares(robot, human, None, None, np.zeros((n, S), bool))).all()


def test_hand_hidden_flags_an_arm_over_where_the_hand_was():
    """Frame 0: the robot's forearm reaches the hand's edge (the wrist), its hand covers the rest;
    frame 1: a wrist module near the lens lies over most of the hand; frame 2: the other robot's
    arm crosses it (any robot's arm counts); side 1 is not checked."""
    n, S, H, W = 3, 2, 120, 160
    hand = np.zeros((n, S, H, W), bool)
    hand[:, 0, 40:80, 60:100] = True
    hand[:, 1, 40:80, 110:150] = True
    arm = np.zeros((n, H, W), bool)
    arm[0, 76:120, 60:100] = True  # 4 of the hand's 40 rows
    arm[1, 30:120, 50:110] = True
    arm[2, 50:70, 0:160] = True
    checked = np.array([[True, False]] * n)
    shares = hand_hidden_shares(arm, hand, checked, step=1)
    assert shares[0, 0] == pytest.approx(0.1)
    assert shares[1, 0] == pytest.approx(1.0) and shares[2, 0] == pytest.approx(0.5)
    assert np.isnan(shares[:, 1]).all()
    own = np.full((n, S), Reason.OK, np.int16)
    status = screen_status(own, checked, shares, MAX_HAND_HIDDEN, Reason.HAND_HIDDEN)
    assert status[:, 0].tolist() == [Reason.OK, Reason.HAND_HIDDEN, Reason.HAND_HIDDEN]
    assert (status[:, 1] == Reason.OK).all()


def test_sleeve_in_the_hand_arm_mask_on_real_egodex(egodex_dir):
    """insert_remove/2: the left arm's green jacket sleeve. With the tracked arm the
    hand-arm mask holds most of the forearm capsule, and without it too (found in the image, as
    for a video); skin alone stops at the cuff. The hand mask stays the hand's."""
    from handedit.sources.egodex import EgoDexSpec, EgoDexSource
    from handedit.vision.registration import register
    from handedit.vision.segment import SegmentConfig, segment

    src = EgoDexSource(EgoDexSpec(root=egodex_dir, task="insert_remove", episode="2", frames=(24, 28), resize=(960, 540)))
    intr = src.intrinsics
    c = src.read(0, 4)
    r = register(c.frames, c.keypoints, c.keypoints_valid, intr, arm_keypoints=c.arm_keypoints)
    present = r.hand_status == 1
    with_arm = segment(c.frames, project(r.keypoints, intr), r.keypoints_valid, present=present,
                       limbs=limbs(r.keypoints, r.arm_keypoints, c.arm_valid), intr=intr)
    untracked = segment(c.frames, project(r.keypoints, intr), r.keypoints_valid, present=present)
    skin_only = segment(c.frames, project(r.keypoints, intr), r.keypoints_valid, SegmentConfig(untracked_arm=False),
                        present=present)
    left = 0
    covs, found, before = [], [], []
    for t in range(4):
        cap = forearm_capsule(r.keypoints[t, left, 0], r.arm_keypoints[t, left, 0], intr, (540, 960))
        covs.append(coverage(with_arm.handarm_mask[t, left], cap))
        found.append(coverage(untracked.handarm_mask[t, left], cap))
        before.append(coverage(skin_only.handarm_mask[t, left], cap))
        hand_iou = (with_arm.hand_mask[t, left] & skin_only.hand_mask[t, left]).sum() / \
            (with_arm.hand_mask[t, left] | skin_only.hand_mask[t, left]).sum()
        assert hand_iou > 0.9  # the hand scope as before
    assert min(covs) >= 0.85 and min(found) >= 0.85 and max(before) < 0.6, (covs, found, before)
