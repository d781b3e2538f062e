"""Hand-arm virtual base: grid, IK feasibility, reach rejection, support-plane ranking,
collision primitives, shoulder initialisation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from handedit.reasons import Reason
from handedit.retarget.arm import arm_model
from handedit.retarget.virtual_base import (
    VirtualBaseConfig,
    arms_collide,
    candidate_grid,
    initial_base,
    search_virtual_base,
    seg_dists,
    self_collision,
    upright_frame,
)

EMB = "ur5_shadow"
CFG = VirtualBaseConfig()
UP = np.array([0.0, -1.0, 0.0])  # camera frame: image up


@pytest.fixture
def assets(monkeypatch, robots_dir: Path) -> Path:
    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))
    return robots_dir


def _true_base() -> np.ndarray:
    return upright_frame(np.array([0.35, 0.25, -0.2]), UP, np.array([-0.3, 0.0, 1.0]))


UR5_Q = (0.3, -1.0, 1.2, -0.8, -1.2, 0.2)  # offsets from mid-range: an elbow-up reach
XARM_Q = (-0.228, -0.017, 0.467, 0.521, -0.171, 0.086, -0.214)  # its elbow height varies across the grid


def _q_offsets(arm, q_off=UR5_Q) -> np.ndarray:
    """Joint offsets from mid-range: the hand's own wrist joints (Shadow's, moved by the arm IK) at 0."""
    return np.r_[q_off, np.zeros(arm.n - len(q_off))]


def _known_sequence(n: int = 6, seed: int = 3, emb: str = EMB, q_off=UR5_Q):
    """Wrist targets produced by the arm's own FK from a known base along a joint path."""
    arm = arm_model(emb)
    rng = np.random.default_rng(seed)
    mid = (arm.lo_s + arm.hi_s) / 2
    qa = mid + _q_offsets(arm, q_off)
    qb = qa + rng.normal(0, 0.15, arm.n)
    Tb = _true_base()
    Q = np.stack([qa * (1 - s) + qb * s for s in np.linspace(0, 1, n)])
    targets = np.stack([Tb @ arm.wrist_pose(q) for q in Q])
    return targets, Tb


def test_grid_is_27_upright_candidates(assets):
    T0 = _true_base()
    reach = arm_model(EMB).reach
    grid = candidate_grid(T0, reach)
    assert len(grid) == 27
    offs = np.array([np.linalg.inv(T0)[:3, :3] @ (g[3][:3, 3] - T0[:3, 3]) for g in grid])
    np.testing.assert_allclose(sorted(set(np.round(offs[:, 0] / reach, 6))), [-0.15, 0.0, 0.15], atol=1e-9)
    np.testing.assert_allclose(sorted(set(np.round(offs[:, 1] / reach, 6))), [-0.10, 0.0, 0.10], atol=1e-9)
    np.testing.assert_allclose(offs[:, 2], 0.0, atol=1e-12)  # height fixed
    for g in grid:  # roll/pitch fixed: base z stays world up
        np.testing.assert_allclose(g[3][:3, 2], UP, atol=1e-12)
    yaws = {round(np.degrees(np.arctan2(*(np.linalg.inv(T0[:3, :3]) @ g[3][:3, 0])[[1, 0]])), 6) for g in grid}
    assert yaws == {-15.0, 0.0, 15.0}


def test_reachable_sequence_is_accepted(assets):
    targets, Tb = _known_sequence()
    res = search_virtual_base(targets, np.ones(len(targets), bool), EMB, CFG, up=UP, init_base=Tb)
    assert len(res.candidates) == 27 and len(res.scores_json()) == 27
    assert res.reason == Reason.OK and res.selected_by == "auto:top1"
    centre = res.candidates[13]  # the true base is the grid centre
    assert centre.reason == Reason.OK and centre.ee_error_mm < 1.0 and centre.critical_success == 1.0
    keys = [res.candidates[i].key() for i in res.ranking]
    assert keys == sorted(keys) and res.chosen == res.ranking[0]
    assert (res.status == Reason.OK).all()
    arm = arm_model(EMB)
    for t, q in zip(targets, res.arm_q):  # the chosen base reproduces the wrist trajectory
        T = res.camera_from_base @ arm.wrist_pose(q)
        assert np.linalg.norm(T[:3, 3] - t[:3, 3]) < CFG.pos_tol_mm / 1000
    assert res.qpos.shape == (len(targets), arm.kin.dof)
    assert np.all(res.qpos[:, arm.arm_idx] >= arm.lower) and np.all(res.qpos[:, arm.arm_idx] <= arm.upper)
    assert set(res.trajectories) == set(res.ranking[:3])


def test_beyond_reach_is_rejected(assets):
    targets, Tb = _known_sequence(n=4)
    arm = arm_model(EMB)
    far = targets.copy()
    far[:, :3, 3] += Tb[:3, 0] * 3.0 * arm.max_reach  # 3 L_r straight ahead of the base
    res = search_virtual_base(far, np.ones(len(far), bool), EMB, CFG.model_copy(update={"n_seeds": 2}), up=UP, init_base=Tb)
    assert res.reason == Reason.NO_VALID_BASE and res.chosen is None and res.ranking == []
    assert all(c.reason == Reason.OUT_OF_REACH for c in res.candidates)
    # no frame may fail (critical_tolerance of 4 frames): after the first, the frames are not solved
    assert res.status[0] == Reason.OUT_OF_REACH and (res.status[1:] == Reason.NO_VALID_BASE).all()
    assert "out of reach" in res.detail


def test_support_plane_collision_is_not_ranked_first(assets):
    emb, cfg = "xarm_ability", CFG.model_copy(update={"n_seeds": 3})
    targets, Tb = _known_sequence(emb=emb, q_off=XARM_Q)
    valid = np.ones(len(targets), bool)
    free = search_virtual_base(targets, valid, emb, cfg, up=UP, init_base=Tb)
    arm = arm_model(emb)

    def lowest(i):  # lowest moving capsule point of candidate i along the sequence (height along UP)
        Tc = free.candidates[i].camera_from_base
        return min((UP @ (Tc[:3, :3] @ arm.chain(q) + Tc[:3, 3:4]))[arm.arm_points].min() for q in free.arm_tracks[i])

    top = free.ranking[0]
    h_top = lowest(top)
    others = {i: lowest(i) for i in free.ranking[1:]}
    best_other = max(others.values())
    assert best_other > h_top + 0.002  # the grid does move the arm's lowest point
    # support plane: just above the top candidate's lowest point, well below the best other's
    h_plane = h_top + 0.5 * (best_other - h_top) - CFG.link_radius - CFG.plane_margin
    h_plane = max(h_plane, h_top - CFG.link_radius - CFG.plane_margin + 1e-3)
    plane = np.concatenate([UP, [-h_plane]])
    res = search_virtual_base(targets, valid, emb, cfg, up=UP, support_plane=plane, init_base=Tb)
    assert res.candidates[top].reason == Reason.COLLISION
    assert res.ranking and res.ranking[0] != top and res.chosen != top
    assert len(res.candidates) == 27


def test_shoulder_initialisation(assets):
    targets, _ = _known_sequence(n=3)
    arm = arm_model(EMB)
    left, right = np.array([-0.2, 0.3, 0.0]), np.array([0.2, 0.3, 0.0])
    T0 = initial_base(targets, np.ones(3, bool), UP, arm.reach, CFG, np.stack([left, right]), arm.shoulder)
    # first joint below the human shoulder (by init_shoulder_drop x L_r)
    np.testing.assert_allclose(T0[:3, :3] @ arm.shoulder + T0[:3, 3], right - CFG.init_shoulder_drop * arm.reach * UP, atol=1e-9)
    np.testing.assert_allclose(T0[:3, 2], UP, atol=1e-12)
    fwd = targets[:, :3, 3].mean(0) - (left + right) / 2
    fwd -= (fwd @ UP) * UP
    assert T0[:3, 0] @ fwd / np.linalg.norm(fwd) > 0.999


def test_segment_distances_against_brute_force():
    """All pairs at once (``seg_dists``) match a dense search over both segments' parameters,
    for general, parallel, crossing and point-like segments."""
    rng = np.random.default_rng(7)
    p1, q1, p2, q2 = (rng.normal(0, 0.3, (60, 3)) for _ in range(4))
    q2[:10] = p2[:10] + (q1[:10] - p1[:10]) * 0.7  # parallel
    q1[10:15] = p1[10:15]  # the first a point
    q2[15:20] = p2[15:20]  # the second a point
    q1[20:25], q2[20:25] = p1[20:25], p2[20:25]  # both points
    p2[25:30] = (p1[25:30] + q1[25:30]) / 2  # touching
    got = seg_dists(p1, q1, p2, q2)
    u = np.linspace(0, 1, 401)
    for k in range(len(got)):
        a = p1[k] + u[:, None] * (q1[k] - p1[k])
        b = p2[k] + u[:, None] * (q2[k] - p2[k])
        brute = np.linalg.norm(a[:, None] - b[None], axis=-1).min()
        assert got[k] <= brute + 1e-12 and got[k] >= brute - 0.005, (k, got[k], brute)
    assert np.allclose(got[25:30], 0.0, atol=1e-12)


def test_collision_primitives():
    z = np.zeros(3)
    x = np.array([[1.0, 0, 0]])
    assert seg_dists(z[None], x, np.array([[0.5, 0.2, 0]]), np.array([[0.5, 1.0, 0]]))[0] == pytest.approx(0.2)
    assert seg_dists(z[None], x, np.array([[2.0, 0, 0]]), np.array([[3.0, 0, 0]]))[0] == pytest.approx(1.0)
    # a chain folded back onto itself collides; a straight one does not
    straight = np.array([[0, 0, 0], [0, 0, 0.3], [0, 0, 0.6], [0, 0, 0.9], [0, 0, 1.2]], float).T
    folded = np.array([[0, 0, 0], [0, 0, 0.3], [0.03, 0, 0.35], [0.08, 0, 0.3], [0.06, 0, 0.0]], float).T
    moving = np.ones(5, bool)
    assert not self_collision(straight, moving, 0.035)
    assert self_collision(folded, moving, 0.035)
    assert arms_collide(straight, moving, straight + 0.03, moving, 0.035)
    assert not arms_collide(straight, moving, straight + np.array([[1.0], [0], [0]]), moving, 0.035)


def test_arm_ik_warm_and_cold_agree(assets):
    arm = arm_model("xarm_ability")
    mid = (arm.lo_s + arm.hi_s) / 2
    q1 = mid + 0.3
    T1 = arm.wrist_pose(q1)
    T2 = arm.wrist_pose(q1 + 0.05)
    first = arm.solve(T1, q1 + 0.1)
    warm = arm.solve(T2, first.x, q_prev=first.x, smooth=1e-4, warm=first)
    cold = arm.solve(T2, mid)
    for s in (warm, cold):
        assert s.pos_err_mm < 0.5 and s.rot_err_deg < 0.1
    np.testing.assert_allclose(arm.wrist_pose(warm.x), arm.wrist_pose(cold.x), atol=1e-3)
    assert arm.reach > 0.5 and arm.n == 7


def test_warm_frames_by_newton_give_ipopts_search(assets, monkeypatch):
    """Warm IK frames go to projected Newton (arm.NEWTON_MAX_STEP); with it switched off every
    frame is IPOPT's: the same verdict, ranking and choice, the joint tracks within 1e-4 rad
    (a redundant arm: the two settle a hinted first frame a few 1e-5 rad apart in the null
    space), and most warm frames did take the Newton path."""
    import importlib

    am = importlib.import_module("handedit.retarget.arm")
    arm = arm_model("xarm_ability")
    targets, Tb = _known_sequence(n=8, emb="xarm_ability", q_off=XARM_Q)
    valid = np.ones(len(targets), bool)
    taken = []
    newton = arm.newton.solve

    def counted(x0, p):
        x, f, converged = newton(x0, p)
        taken.append(converged and np.abs(x - x0).max() <= am.NEWTON_MAX_STEP)
        return x, f, converged

    monkeypatch.setattr(arm.newton, "solve", counted)
    fast = search_virtual_base(targets, valid, "xarm_ability", CFG, up=UP, init_base=Tb)
    accepted = sum(taken)
    monkeypatch.setattr(am, "NEWTON_MAX_STEP", -1.0)  # no Newton solution is ever taken
    slow = search_virtual_base(targets, valid, "xarm_ability", CFG, up=UP, init_base=Tb)
    warm = int((fast.frame_status != Reason.NO_VALID_BASE).sum()) - len(fast.candidates)  # solved frames after the first
    assert warm >= 27 and accepted >= 0.8 * warm
    assert fast.ranking and fast.chosen == slow.chosen and fast.ranking == slow.ranking
    assert [c.reason for c in fast.candidates] == [c.reason for c in slow.candidates]
    np.testing.assert_allclose(np.stack(fast.arm_tracks), np.stack(slow.arm_tracks), atol=1e-4)


def test_ready_pose_is_collision_free(assets):
    """Franka's standard ready pose: the compact wrist + hand group must not read as a self-collision."""
    arm = arm_model("panda_allegro")
    q = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
    assert not self_collision(arm.chain(q), arm.moving, CFG.link_radius, arm.distal)
    # folding the forearm back onto the upper arm is caught
    folded = np.array([0.0, 0.3, 0.0, -3.0, 0.0, 0.5, 0.785])
    assert self_collision(arm.chain(folded), arm.moving, CFG.link_radius, arm.distal)


def test_a_yawed_candidate_is_its_yaw_mate_turned(assets, monkeypatch):
    """The grid's yaw triples differ only by a turn of the base about its z axis, which the first
    joint of most arms undoes exactly (``ArmModel.yaw_sign``): a yawed candidate of a six-joint arm
    whose first frame lands on its mate's branch takes the mate's track with that joint turned back,
    every link where the mate's were, and solves no other frame. The same verdicts, ranking and
    chosen track as solving every candidate on its own, with half the IK solves or fewer."""
    from handedit.retarget.virtual_base import GRID_YAW_DEG, candidate_grid

    emb = "ur5_inspire"  # six joints: no self-motion, so one branch is one solution
    arm = arm_model(emb)
    assert arm.yaw_sign != 0 and arm_model("rm75_rohand").yaw_sign == 0  # RM75's first joint is off the base's axis
    q, a = (arm.lo_s + arm.hi_s) / 2 + 0.4, np.radians(15.0)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    np.testing.assert_allclose(Rz @ arm.chain(q - arm.yaw_sign * a * np.eye(arm.n)[0]), arm.chain(q), atol=1e-12)
    targets, Tb = _known_sequence(n=12, emb=emb)
    valid = np.ones(len(targets), bool)
    solves = []
    monkeypatch.setattr(type(arm), "solve", lambda self, *a, f=type(arm).solve, **k: solves.append(1) or f(self, *a, **k))
    shared = search_virtual_base(targets, valid, emb, CFG, up=UP, init_base=Tb)
    n_shared = len(solves)
    solves.clear()
    own = search_virtual_base(targets, valid, emb, CFG.model_copy(update={"share_yaw": False}), up=UP, init_base=Tb)
    assert n_shared <= 0.5 * len(solves), (n_shared, len(solves))
    assert shared.ranking and shared.chosen == own.chosen and shared.ranking[:3] == own.ranking[:3]
    assert [c.reason for c in shared.candidates] == [c.reason for c in own.candidates]
    np.testing.assert_allclose(shared.arm_q, own.arm_q, atol=1e-6)
    grid, turned = candidate_grid(Tb, arm.reach), 0
    for k in range(27):
        if not k % 3:  # yaw -15 starts a triple
            continue
        mate = shared.arm_tracks[k - 1].copy()
        mate[:, 0] -= arm.yaw_sign * np.radians(GRID_YAW_DEG[k % 3] - GRID_YAW_DEG[k % 3 - 1])
        if np.allclose(shared.arm_tracks[k], mate, atol=1e-12):
            turned += 1
            assert np.array_equal(shared.frame_status[k], shared.frame_status[k - 1])
            for i in np.flatnonzero(shared.frame_status[k] == Reason.OK):  # where its mate's wrist was
                np.testing.assert_allclose(grid[k][3] @ arm.wrist_pose(shared.arm_tracks[k][i]),
                                           grid[k - 1][3] @ arm.wrist_pose(shared.arm_tracks[k - 1][i]), atol=1e-9)
    assert turned >= 12, turned


def test_a_yawed_candidate_on_another_branch_is_solved_on_its_own(assets):
    """The grid's yaw is the paper's way to try other arm postures: a yawed candidate whose own
    first frame lands off its mate's branch keeps its own track; one on it takes the mate's."""
    from handedit.retarget.virtual_base import _evaluate, _Track, _yaw_turned, candidate_grid

    arm = arm_model("ur5_inspire")
    targets, Tb = _known_sequence(n=6, emb="ur5_inspire")
    valid = np.ones(len(targets), bool)
    grid = candidate_grid(Tb, arm.reach)
    mate = _evaluate(arm, grid[12][3], targets, valid, None, CFG)
    turned = _yaw_turned(arm, grid[12], grid[13], mate)
    assert turned is not None and _evaluate(arm, grid[13][3], targets, valid, None, CFG, mate.arm_q[0], turned=turned) \
        is turned
    elsewhere = _Track(turned.arm_q + 1.0, turned.status.copy(), turned.pos_err, turned.chains)
    own = _evaluate(arm, grid[13][3], targets, valid, None, CFG, mate.arm_q[0], turned=elsewhere)
    assert own is not elsewhere and np.abs(own.arm_q - elsewhere.arm_q).max() > 0.5
    assert _yaw_turned(arm, grid[2], grid[3], mate) is None  # another lateral/forward offset: not a mate
    xarm = arm_model("xarm_ability")  # seven joints: its candidates are solved on their own
    assert xarm.yaw_sign != 0 and _yaw_turned(xarm, grid[12], grid[13], mate) is None
    stuck = _Track(np.tile(arm.lo_s, (6, 1)), np.full(6, Reason.OK), np.zeros(6), mate.chains)
    pair = (grid[0], grid[1]) if arm.yaw_sign > 0 else (grid[1], grid[0])  # the turn that passes the lower limit
    assert _yaw_turned(arm, *pair, stuck) is None  # the turned joint would leave its range: solved on its own
