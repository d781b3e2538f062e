"""The synthetic source is the ground-truth oracle: its pixels, masks and 3D must agree."""

from __future__ import annotations

import os
import pickle

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import cv2
import numpy as np
import pytest
import trimesh

from handedit.camera import project
from handedit.keypoints import FINGERS, FINGERTIPS, MCPS, WRIST
from handedit.sources.base import ClipChunk, SourceError
from handedit.sources.synthetic import CLOSE_END, GENERATOR_VERSION, SyntheticSpec, make_clip_specs

SMALL = dict(width=160, height=120, n_frames=12)


@pytest.fixture(scope="module")
def clip() -> tuple[SyntheticSpec, ClipChunk]:
    spec = SyntheticSpec(clip_id="t", seed=3, **SMALL)
    return spec, spec.open().read(0, spec.n_frames)


def _world(chunk: ClipChunk, pts_cam: np.ndarray, i: int) -> np.ndarray:
    T = chunk.world_from_camera[i]
    return pts_cam @ T[:3, :3].T + T[:3, 3]


def test_chunks_are_deterministic_and_independent(clip):
    spec, full = clip
    other = SyntheticSpec(**spec.model_dump()).open()  # a fresh source, as a worker would open it
    part = other.read(4, 8)
    assert part.start == 4 and part.n == 4
    np.testing.assert_array_equal(part.frames, full.frames[4:8])
    np.testing.assert_array_equal(part.keypoints, full.keypoints[4:8])
    np.testing.assert_array_equal(part.object_mask, full.object_mask[4:8])
    np.testing.assert_array_equal(part.object_pose, full.object_pose[4:8])
    for k in ("hand_mask", "handarm_mask", "background"):
        np.testing.assert_array_equal(part.gt[k], full.gt[k][4:8])
    # pickled sources (what Dask ships) reproduce the same pixels
    again = pickle.loads(pickle.dumps(spec.open())).read(4, 5)
    np.testing.assert_array_equal(again.frames[0], full.frames[4])


def test_chunk_shapes_and_types(clip):
    spec, c = clip
    n, H, W = spec.n_frames, spec.height, spec.width
    assert c.frames.shape == (n, H, W, 3) and c.frames.dtype == np.uint8
    assert c.world_from_camera.shape == (n, 4, 4)
    assert c.keypoints.shape == (n, 1, 21, 3) and c.keypoints.dtype == np.float32
    assert c.keypoints_valid.shape == (n, 1, 21) and c.keypoints_valid.dtype == bool
    assert c.frame_ok.all() and c.object_pose.shape == (n, 4, 4)
    assert c.gt["background"].shape == (n, H, W, 3) and c.gt["background"].dtype == np.uint8
    for k in ("hand_mask", "handarm_mask"):
        assert c.gt[k].shape == (n, H, W) and c.gt[k].dtype == bool
    assert not np.any(c.keypoints[~c.keypoints_valid])  # invalid joints are zeroed


def test_info_fingerprint_and_specs():
    spec = SyntheticSpec(seed=5, **SMALL)
    info = spec.open().info()
    assert info.has_keypoints and info.has_object and info.n_frames == 12
    assert (info.width, info.height) == (160, 120) and info.intrinsics.width == 160
    assert set(info.ground_truth) == {"hand_mask", "handarm_mask", "background"}
    assert info.meta["generator"] == GENERATOR_VERSION
    assert info.fingerprint == SyntheticSpec(seed=5, **SMALL).open().info().fingerprint
    assert info.fingerprint != SyntheticSpec(seed=6, **SMALL).open().info().fingerprint
    specs = make_clip_specs(8, seed=1, width=160)
    assert [s.clip_id for s in specs[:2]] == ["synthetic-0000", "synthetic-0001"]
    assert specs == make_clip_specs(8, seed=1, width=160) and all(s.width == 160 for s in specs)
    assert len({s.seed for s in specs}) == 8
    assert {s.open().info().meta["object"] for s in specs} == {"box", "cylinder"}
    with pytest.raises(SourceError):
        spec.open().read(10, 13)


def test_masks_and_background_are_exact(clip):
    _, c = clip
    hand, handarm, bg = c.gt["hand_mask"], c.gt["handarm_mask"], c.gt["background"]
    assert not np.any(hand & ~handarm)
    outside = ~handarm
    np.testing.assert_array_equal(c.frames[outside], bg[outside])
    # the hand really is painted over the background, and the forearm is not "hand"
    assert np.any(c.frames[handarm] != bg[handarm])
    assert all(h.sum() > 50 for h in hand)
    assert all((a & ~h).sum() > 50 for a, h in zip(handarm, hand))
    assert all(o.sum() > 30 for o in c.object_mask)
    # the forearm leaves the frame through a border, as in an egocentric view
    for a in handarm:
        border = np.concatenate([a[0], a[-1], a[:, 0], a[:, -1]])
        assert border.any()


def test_keypoints_project_onto_the_hand(clip):
    spec, c = clip
    intr = spec.open().info().intrinsics
    hits = total = 0
    for i in range(c.n):
        dist = cv2.distanceTransform((~c.gt["handarm_mask"][i]).astype(np.uint8), cv2.DIST_L2, 3)
        uv = project(c.keypoints[:, 0][i], intr)
        for j in (WRIST, *FINGERTIPS, *MCPS):
            if not c.keypoints_valid[:, 0][i, j]:
                continue
            u, v = np.round(uv[j]).astype(int)
            if not (0 <= u < spec.width and 0 <= v < spec.height):
                continue
            total += 1
            near_hand = dist[v, u] <= 3.0
            hits += near_hand
            assert near_hand or c.object_mask[i, v, u], f"frame {i} joint {j} at ({u},{v}) off the hand"
    assert total > 0.8 * c.n * 11 and hits > 0.85 * total


def test_camera_is_an_upright_head_camera(clip):
    _, c = clip
    for T, kp in zip(c.world_from_camera, c.keypoints[:, 0]):
        assert T[2, 1] < -0.3  # image "down" points down in the world
        assert T[2, 2] < -0.4  # looking down at the table
        height = T[2, 3]
        assert 0.3 < height < 0.6
        depth = np.linalg.norm(kp[WRIST])
        assert 0.25 < depth < 0.7  # hand at arm's length from the eyes


def test_object_is_lifted_with_the_hand(clip):
    _, c = clip
    obj_world = [c.world_from_camera[i] @ c.object_pose[i] for i in range(c.n)]
    z = np.array([T[2, 3] for T in obj_world])
    assert z[-1] - z[0] > 0.06
    assert np.allclose(z[: c.n // 2], z[0], atol=1e-9)  # still on the table before the lift
    wrist = np.array([_world(c, c.keypoints[:, 0][i, WRIST], i) for i in range(c.n)])
    assert wrist[-1, 2] - wrist[c.n // 2, 2] > 0.06
    # after the grasp the wrist stays fixed in the object frame (rigid lift)
    last = c.n - 1
    rel = [np.linalg.inv(obj_world[i]) @ np.append(wrist[i], 1.0) for i in (int(np.ceil(0.62 * last)), last)]
    np.testing.assert_allclose(rel[0], rel[1], atol=1e-6)


@pytest.mark.parametrize("seed", [0, 2, 8, 11])
def test_fingertips_end_on_the_object(seed):
    spec = SyntheticSpec(seed=seed, width=64, height=48, n_frames=10)
    src = spec.open()
    V, F = src.object_mesh()
    mesh = trimesh.Trimesh(V, F, process=False)
    start = int(np.ceil(CLOSE_END * (spec.n_frames - 1)))
    c = src.read(start, spec.n_frames)
    for i in range(c.n):
        obj_from_cam = np.linalg.inv(c.object_pose[i])
        tips = c.keypoints[:, 0][i, list(FINGERTIPS)] @ obj_from_cam[:3, :3].T + obj_from_cam[:3, 3]
        _, dist, _ = trimesh.proximity.closest_point(mesh, tips)
        assert dist.max() < 0.02, f"seed {seed} frame {start + i}: tip distances {dist}"
        assert mesh.contains(tips).sum() == 0  # touching, not inside


def test_hand_has_human_proportions(clip):
    _, c = clip
    kp = c.keypoints[0, 0].astype(float)
    bone = lambda a, b: np.linalg.norm(kp[a] - kp[b])  # noqa: E731
    middle = bone(0, 9) + sum(bone(a, b) for a, b in zip(FINGERS["middle"], FINGERS["middle"][1:]))
    assert 0.175 < middle < 0.195  # wrist to middle fingertip along the bones
    assert 0.16 < bone(0, 12) < 0.195  # open hand at the start: nearly straight
    assert 0.05 < bone(5, 17) < 0.08  # knuckle breadth
    for name, joints in FINGERS.items():
        lengths = [bone(a, b) for a, b in zip(joints, joints[1:])]
        assert all(0.015 < x < 0.05 for x in lengths), (name, lengths)
        if name != "thumb":
            assert lengths[0] > lengths[1] > 0.8 * lengths[2]  # proximal > middle >~ distal


def test_a_still_clip_holds_its_hand_while_the_head_sways():
    """``still``: the hand and object stay put in the world for the whole clip (restoration never
    sees behind the hand), the camera keeps moving; a moving clip's fingerprint is unaffected."""
    from handedit.sources.synthetic import make_clip_specs

    still, moving = (make_clip_specs(1, seed=4, n_frames=12, width=96, height=72, still=s)[0] for s in (True, False))
    chunks = {}
    for name, spec in (("still", still), ("moving", moving)):
        c = spec.open().read(0, 12)
        wrist = np.einsum("tij,tj->ti", c.world_from_camera[:, :3, :3], c.keypoints[:, 0, 0].astype(float)) \
            + c.world_from_camera[:, :3, 3]
        chunks[name] = (c, np.linalg.norm(wrist - wrist[0], axis=1).max())
    assert chunks["still"][1] < 1e-5 and chunks["moving"][1] > 0.05
    assert np.abs(np.diff(chunks["still"][0].world_from_camera[:, :3, 3], axis=0)).max() > 1e-5  # the head sways
    assert still.open().fingerprint != moving.open().fingerprint


def test_a_sleeved_clip_covers_the_forearm_in_cloth_and_tracks_the_elbow():
    """``sleeve``: cloth over the forearm from a few cm past the wrist, labelled arm (the hand-arm
    truth is the arm with its sleeve), the elbow tracked in 3-D at the forearm's end; the hand is
    the same hand, and a clip without a sleeve keeps the fingerprint it had before sleeves."""
    import hashlib

    from handedit.sources.synthetic import make_plan
    from handedit.vision.arm import limbs
    from handedit.vision.segment import SegmentConfig, segment

    sleeved, bare = (make_clip_specs(3, seed=11, n_frames=6, width=160, height=120, sleeve=s)[2] for s in (True, False))
    cs, cb = sleeved.open().read(0, 6), bare.open().read(0, 6)
    assert sleeved.open().info().has_arm and not bare.open().info().has_arm and cb.arm_keypoints is None
    hs, hb = cs.gt["hand_mask"], cb.gt["hand_mask"]
    assert (hs & hb).sum() / (hs | hb).sum() > 0.95
    cloth = cs.gt["handarm_mask"] & ~cs.gt["hand_mask"]
    assert cloth.sum() > cb.gt["handarm_mask"].sum() - hb.sum()  # cloth stands off the skin
    assert np.abs(cs.frames[cloth].astype(int) - cb.frames[cloth].astype(int)).mean() > 20  # not the skin's colour
    wrist = cs.keypoints[:, 0, 0]
    assert cs.arm_valid[:, 0].tolist() == [[True, False, False]] * 6
    np.testing.assert_allclose(np.linalg.norm(cs.arm_keypoints[:, 0, 0] - wrist, axis=-1),
                               make_plan(sleeved).geom.forearm_length, rtol=1e-4)
    # the tracked elbow lets segmentation take the sleeve; without it (a video) the sleeve is found
    # in the image (the skin stops at the cuff, inside the view); skin alone loses it
    info = sleeved.open().info()
    kp2 = project(cs.keypoints, info.intrinsics)
    with_arm = segment(cs.frames, kp2, cs.keypoints_valid, limbs=limbs(cs.keypoints, *cs.arms()), intr=info.intrinsics)
    without = segment(cs.frames, kp2, cs.keypoints_valid)
    skin_only = segment(cs.frames, kp2, cs.keypoints_valid, SegmentConfig(untracked_arm=False))

    def iou(a, b):
        return float((a & b).sum() / (a | b).sum())

    truth = cs.gt["handarm_mask"]
    assert iou(with_arm.handarm_mask[:, 0], truth) > 0.85
    assert iou(without.handarm_mask[:, 0], truth) > 0.85 > iou(skin_only.handarm_mask[:, 0], truth) + 0.03
    assert iou(without.hand_mask[:, 0], skin_only.hand_mask[:, 0]) > 0.99  # the hand scope as before
    old = hashlib.sha256((bare.model_dump_json(exclude={"still", "sleeve"}) + GENERATOR_VERSION).encode()).hexdigest()
    assert bare.open().fingerprint == old != sleeved.open().fingerprint
