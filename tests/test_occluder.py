"""The occluder of a source without an object mesh, from the image: what hid the human fingers."""

from __future__ import annotations

import numpy as np
import pytest

from handedit.sources.synthetic import make_clip_specs
from handedit.vision.occluder import finger_footprint, hidden_fingers


@pytest.fixture(scope="module")
def grasp():
    """A synthetic grasp (the object in front of some fingers), its mesh withheld: only the
    keypoints and the hand's mask are used; the object's mask is the truth."""
    spec = make_clip_specs(1, seed=3, n_frames=24, width=320, height=240)[0]
    src = spec.open()
    return src.info(), src.read(12, 24)


def test_the_object_in_front_of_the_fingers_is_found_without_its_mesh(grasp):
    info, c = grasp
    hand = c.gt["hand_mask"][:, None]
    occ = hidden_fingers(c.keypoints, c.keypoints_valid, hand, info.intrinsics)
    assert occ.sum() > 500
    assert (occ & c.object_mask).sum() / occ.sum() > 0.95  # what it finds is the object
    assert not (occ & c.gt["hand_mask"]).any()
    # the object's pixels over the fingers' footprints (no slack), beside the hand: most are found
    truth = c.object_mask & _feet(info, c) & ~c.gt["hand_mask"]
    assert (occ & truth).sum() / truth.sum() > 0.6


def test_a_visible_hand_hides_nothing_and_a_shifted_mask_is_not_an_occluder(grasp):
    info, c = grasp
    # the mask the bones would draw: every finger visible, nothing in front
    feet = _feet(info, c)
    assert not hidden_fingers(c.keypoints, c.keypoints_valid, (feet | c.gt["hand_mask"])[:, None], info.intrinsics).any()
    # a mask a couple of pixels off the bones (registration) stays within the slack
    shifted = np.roll(feet | c.gt["hand_mask"], 2, axis=2)[:, None]
    assert hidden_fingers(c.keypoints, c.keypoints_valid, shifted, info.intrinsics).sum() < 0.02 * feet.sum()
    # no hand mask, or the wrist untracked: nothing
    assert not hidden_fingers(c.keypoints, c.keypoints_valid, np.zeros_like(shifted), info.intrinsics).any()
    invalid = c.keypoints_valid.copy()
    invalid[..., 0] = False
    assert not hidden_fingers(c.keypoints, invalid, c.gt["hand_mask"][:, None], info.intrinsics).any()


def test_a_finger_the_mask_missed_is_not_an_occluder(grasp):
    """With the frames, a hidden pixel coloured like the hand (a finger the mask left out) is not
    an occluder; the object, whose colour is the scene's, still is."""
    info, c = grasp
    hand = c.gt["hand_mask"][:, None]
    missed = hand & ~_feet(info, c)[:, None]  # the mask loses every finger's visible part
    bare = hidden_fingers(c.keypoints, c.keypoints_valid, missed, info.intrinsics)
    seen = hidden_fingers(c.keypoints, c.keypoints_valid, missed, info.intrinsics, frames=c.frames)
    skin = bare & c.gt["hand_mask"]
    assert skin.sum() > 200 and (seen & skin).sum() < 0.2 * skin.sum()
    obj = bare & c.object_mask
    assert (seen & obj).sum() > 0.8 * obj.sum()


def _feet(info, c) -> np.ndarray:
    """Where the fingers are, visible or hidden."""
    return finger_footprint(c.keypoints, c.keypoints_valid, info.intrinsics, c.gt["hand_mask"].shape[1:])
