"""Hand-retargeting QC: contact distance / loss, penetration, joint limits and thresholds
against an object mesh + pose; 'not possible' without one; the synthetic grasp clip."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import trimesh

from handedit.keypoints import JOINT_INDEX
from handedit.reasons import Reason
from handedit.retarget import RetargetConfig, get_retargeter, retarget
from handedit.retarget.qc import RetargetQCConfig, retarget_qc

EMB = "allegro"
CFG = RetargetConfig()
QC = RetargetQCConfig()


@pytest.fixture
def assets(monkeypatch, robots_dir: Path) -> Path:
    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))
    return robots_dir


def _own_fk(n: int = 3):
    """Keypoints from the robot's own FK (exact fit) in an open pose, 0.45 m in front of the camera."""
    rt = get_retargeter(EMB, CFG)
    q = rt.q_neutral.copy()
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 0.45]
    kp = np.zeros((n, 21, 3))
    valid = np.zeros((n, 21), bool)
    for i in range(n):
        kp[i, rt.mano_idx] = rt.robot_points(q, T)
    valid[:, rt.mano_idx] = True
    kp[:, 17], valid[:, 17] = kp[:, 13], True  # palm frame needs a pinky MCP
    return rt, kp, valid


def _box(centre, half) -> trimesh.Trimesh:
    b = trimesh.creation.box(extents=2 * np.asarray(half, float))
    b.apply_translation(centre)
    return b


def _mesh(*boxes: trimesh.Trimesh):
    m = trimesh.util.concatenate(list(boxes))
    return np.asarray(m.vertices), np.asarray(m.faces)


def _pose(n):
    return np.tile(np.eye(4), (n, 1, 1))  # object frame = camera frame


def test_no_object_means_not_possible(assets):
    rt, kp, valid = _own_fk()
    r = retarget(kp, valid, EMB, CFG)
    q = retarget_qc(r, kp, valid, EMB, QC)
    assert not q.contact_checked and "not possible" in q.notes[0]
    np.testing.assert_array_equal(q.status, r.status)
    assert np.isnan(q.contact_distance_mm).all() and np.isnan(q.penetration_mm).all()


def test_contact_kept(assets):
    rt, kp, valid = _own_fk()
    r = retarget(kp, valid, EMB, CFG)
    tip, dip = kp[0, JOINT_INDEX["index_tip"]], kp[0, JOINT_INDEX["index_dip"]]
    d = (tip - dip) / np.linalg.norm(tip - dip)
    mesh = _mesh(_box(tip + d * 0.011, [0.01] * 3))  # surface 1 mm beyond the tip
    q = retarget_qc(r, kp, valid, EMB, QC, object_mesh=mesh, object_pose=_pose(3))
    assert q.contact_checked and q.human_contact.all()
    assert (q.status == Reason.OK).all(), q.details
    assert (q.contact_distance_mm < 5).all()


def test_contact_distance_and_loss(assets):
    rt, kp, valid = _own_fk()
    r = retarget(kp, valid, EMB, CFG)
    it, dp = JOINT_INDEX["index_tip"], JOINT_INDEX["index_dip"]
    th = JOINT_INDEX["thumb_tip"]
    d = (kp[0, it] - kp[0, dp]) / np.linalg.norm(kp[0, it] - kp[0, dp])
    human = kp.copy()
    human[:, it] = kp[:, it] + 0.025 * d  # the human index reaches 25 mm further than the robot's
    far_box = _box(kp[0, it] + d * 0.031, [0.005] * 3)  # touched by the human index only
    d_th = (kp[0, th] - kp[0, JOINT_INDEX["thumb_ip"]]) / np.linalg.norm(kp[0, th] - kp[0, JOINT_INDEX["thumb_ip"]])
    thumb_box = _box(kp[0, th] + d_th * 0.006, [0.005] * 3)  # touched by both thumbs
    q = retarget_qc(r, human, valid, EMB, QC, object_mesh=_mesh(far_box, thumb_box), object_pose=_pose(3))
    assert (q.status == Reason.CONTACT_DISTANCE).all(), q.details
    assert (q.contact_distance_mm > QC.contact_distance_mm).all() and "contact distance" in q.details[0]
    # without the thumb contact no robot fingertip touches any more: contact loss
    q = retarget_qc(r, human, valid, EMB, QC, object_mesh=_mesh(far_box), object_pose=_pose(3))
    assert (q.status == Reason.CONTACT_LOSS).all(), q.details


def test_penetration(assets):
    rt, kp, valid = _own_fk()
    r = retarget(kp, valid, EMB, CFG)
    palm = (kp[0, JOINT_INDEX["middle_mcp"]] + kp[0, 0]) / 2
    mesh = _mesh(_box(palm, [0.03, 0.03, 0.03]))  # the palm's surface lies >= 1 cm from this point
    q = retarget_qc(r, kp, valid, EMB, QC, object_mesh=mesh, object_pose=_pose(3))
    assert (q.status == Reason.PENETRATION).all(), q.details
    assert (q.penetration_mm > QC.penetration_mm).all()
    # moving the object 30 cm away (through its pose) clears it
    pose = _pose(3)
    pose[:, 0, 3] = 0.3
    q = retarget_qc(r, kp, valid, EMB, QC, object_mesh=mesh, object_pose=pose)
    assert (q.status == Reason.OK).all() and (q.penetration_mm == 0).all()


def test_joint_limit_and_thresholds(assets):
    rt, kp, valid = _own_fk()
    r = retarget(kp, valid, EMB, CFG)
    bad = dataclasses.replace(r, qpos=r.qpos.copy())
    bad.qpos[1, 0] = rt.upper[0] + 0.1
    q = retarget_qc(bad, kp, valid, EMB, QC)
    assert q.status[1] == Reason.JOINT_LIMIT and q.status[0] == Reason.OK
    far = dataclasses.replace(r, fingertip_error_mm=np.array([10.0, 50.5, 10.0], np.float32),
                              wrist_error_mm=np.array([51.0, 10.0, 49.0], np.float32))
    q = retarget_qc(far, kp, valid, EMB, QC)  # > 50 mm rejects, <= 50 mm passes
    assert list(q.status) == [Reason.WRIST_ERROR, Reason.FINGERTIP_ERROR, Reason.OK]
    assert "50.5 mm" in q.details[1]


def test_synthetic_grasp_clip(assets):
    """The synthetic source's object mesh + pose: contact is seen where the hand grasps."""
    from handedit.sources.synthetic import CONTACT_END, SyntheticSpec, frame_keypoints, frame_state

    src = SyntheticSpec(n_frames=8, width=64, height=48).open()
    plan = src.plan
    kps, poses = [], []
    for t in range(8):
        st = frame_state(plan, t, 8)
        cw = np.linalg.inv(st.world_from_camera)
        kps.append(frame_keypoints(plan, st) @ cw[:3, :3].T + cw[:3, 3])
        poses.append(cw @ st.world_from_object)
    kp, valid = np.array(kps), np.ones((8, 21), bool)
    r = retarget(kp, valid, "shadow", CFG)
    q = retarget_qc(r, kp, valid, "shadow", QC, object_mesh=src.object_mesh(), object_pose=np.array(poses))
    grasp = np.arange(8) / 7 >= CONTACT_END + 0.1
    assert q.contact_checked and q.human_contact[grasp].all() and not q.human_contact[0]
    assert np.isfinite(q.contact_distance_mm[grasp]).all()
    assert set(np.unique(q.status)) <= {Reason.OK, Reason.CONTACT_DISTANCE, Reason.CONTACT_LOSS, Reason.PENETRATION}
    for i, text in q.details.items():
        assert q.status[i] >= 100 and text


# --- the solve's contact terms (handedit.retarget.contact) ---------------------------------------


def _box_behind_surface(rt, kp, valid, depth: float):
    """A large box whose face lies ``depth`` inside the robot's surface on the side where the
    surface stands furthest beyond the human keypoints (the keypoints stay outside it)."""
    from handedit.retarget.qc import robot_surface

    r = retarget(kp, valid, EMB, CFG)
    pts = robot_surface(EMB, r.qpos[0].astype(float), r.root_pose[0])
    axes = [s * np.eye(3)[a] for a in range(3) for s in (1.0, -1.0)]
    d = max(axes, key=lambda d: (pts @ d).max() - (kp[0][valid[0]] @ d).max())
    face = (pts @ d).max() - depth
    assert face > (kp[0][valid[0]] @ d).max()  # the human keypoints are clear of it
    centre = pts.mean(0) - (pts.mean(0) @ d) * d + (face + 0.1) * d
    return _mesh(_box(centre, [0.1] * 3))


def test_the_solve_keeps_a_contact_the_positions_alone_lose(assets):
    """The human index reaches 25 mm further than the robot's and touches a small box: positions
    alone leave every robot tip off it (CONTACT_LOSS); the touch term pins the robot's index tip
    to the box's surface, within the paper's thresholds (unchanged)."""
    rt, kp, valid = _own_fk()
    it, dp = JOINT_INDEX["index_tip"], JOINT_INDEX["index_dip"]
    d = (kp[0, it] - kp[0, dp]) / np.linalg.norm(kp[0, it] - kp[0, dp])
    human = kp.copy()
    human[:, it] = kp[:, it] + 0.025 * d
    mesh = _mesh(_box(kp[0, it] + d * 0.031, [0.005] * 3))
    seen = {}
    for on in (False, True):
        cfg = RetargetConfig(contact=on)
        r = retarget(human, valid, EMB, cfg, object_mesh=mesh, object_pose=_pose(3))
        seen[on] = retarget_qc(r, human, valid, EMB, QC, cfg, object_mesh=mesh, object_pose=_pose(3))
    assert (seen[False].status == Reason.CONTACT_LOSS).all(), seen[False].details
    assert (seen[True].status == Reason.OK).all(), seen[True].details
    assert (seen[True].contact_distance_mm < QC.contact_mm).all()


def test_the_solve_pushes_the_hand_out_of_the_object(assets):
    """A box 14 mm into the robot's surface (the human keypoints outside it): positions alone leave
    the robot in it (PENETRATION); the push-out planes bring it back within the QC's threshold
    (``push_depth_mm`` is the depth they aim for), at a few mm of fingertip error."""
    rt, kp, valid = _own_fk()
    mesh = _box_behind_surface(rt, kp, valid, 0.014)
    seen = {}
    for on in (False, True):
        cfg = RetargetConfig(contact=on)
        r = retarget(kp, valid, EMB, cfg, object_mesh=mesh, object_pose=_pose(3))
        seen[on] = (r, retarget_qc(r, kp, valid, EMB, QC, cfg, object_mesh=mesh, object_pose=_pose(3)))
    assert (seen[False][1].status == Reason.PENETRATION).all()
    r, q = seen[True]
    assert (q.status == Reason.OK).all(), q.details
    assert (q.penetration_mm < seen[False][1].penetration_mm - 5).all() and (r.fingertip_error_mm < 10).all()


def test_without_an_object_nearby_the_solve_is_unchanged(assets):
    """The contact problem is only solved near the object: an object a metre away, or none, gives
    the very same trajectory as the positions alone."""
    rt, kp, valid = _own_fk()
    human = kp + np.random.default_rng(0).normal(0, 0.004, kp.shape)
    mesh = _mesh(_box(kp[0, 0], [0.05] * 3))
    far = _pose(3)
    far[:, 0, 3] = 1.0
    a = retarget(human, valid, EMB, RetargetConfig(contact=False))
    for r in (retarget(human, valid, EMB, CFG), retarget(human, valid, EMB, CFG, object_mesh=mesh, object_pose=far)):
        np.testing.assert_array_equal(r.qpos, a.qpos)
        np.testing.assert_array_equal(r.root_pose, a.root_pose)
