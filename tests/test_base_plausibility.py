"""Base plausibility inside the virtual-base search: the operator's head and torso as a
keep-out volume (BODY_COLLISION), critical frames with a tolerance, the reach-aware second
grid, and the ranking by the robot's footprint against the human arm's corridor."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from handedit.camera import Intrinsics
from handedit.reasons import Reason
from handedit.retarget.arm import arm_model
from handedit.retarget.hand_arm import critical_frames
from handedit.retarget.plausibility import BaseView, footprint_outside, forearm_angle, human_limbs
from handedit.retarget.virtual_base import (
    CandidateScore,
    VirtualBaseConfig,
    body_distance,
    reach_centre,
    refine_grid,
    search_virtual_base,
)
from test_virtual_base import UP, _known_sequence, _q_offsets, _true_base

CFG = VirtualBaseConfig()
EMB = "ur5_shadow"
INTR = Intrinsics(300.0, 300.0, 160.0, 120.0, 320, 240)


@pytest.fixture
def assets(monkeypatch, robots_dir: Path) -> Path:
    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))
    return robots_dir


def _camera_at(p: np.ndarray, n: int) -> np.ndarray:
    """(n,4,4) camera poses (image up = UP, looking along +z) at point ``p``."""
    T = np.eye(4)
    T[:3, 3] = p
    return np.tile(T, (n, 1, 1))


def test_body_distance_is_a_head_torso_capsule():
    cam = _camera_at(np.zeros(3), 1)[0]  # camera frame: up is -y, forward +z
    through_head = np.array([[-0.3, 0.0, -0.1], [0.3, 0.0, -0.1]])  # 10 cm behind the lens, across the head
    beside = np.array([[0.4, 0.0, -0.1], [0.4, 0.5, -0.1]])  # 40 cm to the side, down along the torso
    below = np.array([[-0.3, 0.4, -0.1], [0.3, 0.4, -0.1]])  # across the chest, 40 cm below the eyes
    assert body_distance(through_head, cam, UP, 0.10, 0.6) == pytest.approx(0.0, abs=1e-9)
    assert body_distance(below, cam, UP, 0.10, 0.6) == pytest.approx(0.0, abs=1e-9)
    assert body_distance(beside, cam, UP, 0.10, 0.6) == pytest.approx(0.4, abs=1e-9)


WIDE = CFG.model_copy(update={"body_radius_m": 1.0})  # a body wide enough to hold every candidate's shoulder, refined or not


def _head_at_base(n_hit: int):
    """The true base's sequence with the camera (head) on the true base in the first ``n_hit``
    of 6 frames (far away in the others): whatever the candidate, of either grid, and the
    IK's choice of elbow, the robot's shoulder is inside the operator's body there."""
    targets, Tb = _known_sequence()
    cams = _camera_at(np.array([5.0, 0, 0]), 6)
    cams[:n_hit, :3, 3] = Tb[:3, 3]
    return search_virtual_base(targets, np.ones(len(targets), bool), EMB, WIDE, up=UP, init_base=Tb, cameras=cams)


def test_arm_through_the_head_is_a_body_collision(assets):
    """Every frame through the body: each candidate keeps nothing and is discarded for it;
    with the head far away the same candidate is kept."""
    targets, Tb = _known_sequence()
    free = search_virtual_base(targets, np.ones(len(targets), bool), EMB, WIDE, up=UP, init_base=Tb,
                               cameras=_camera_at(np.array([5.0, 0, 0]), 6))
    assert free.candidates[13].reason == Reason.OK
    hit = _head_at_base(6)
    assert (hit.frame_status[13] == Reason.BODY_COLLISION).all()
    assert hit.candidates[13].reason == Reason.BODY_COLLISION and not hit.candidates[13].last_resort
    assert "body collision" in hit.candidates[13].detail
    assert hit.reason == Reason.NO_VALID_BASE and hit.chosen is None  # nothing to keep: the sequence is lost


def test_body_collisions_alone_leave_a_base_of_last_resort(assets):
    """The robot's shoulder in the body in 4 of 6 frames, for every candidate of both grids:
    each keeps fewer than ``min_reachability`` of the frames, but only the operator's body
    stops it, so the sequence keeps a base and those 4 frames alone fail (before: all 6 lost
    to NO_VALID_BASE)."""
    hit = _head_at_base(4)
    assert WIDE.min_reachability * 6 > 2  # the 2 frames left are fewer than min_reachability asks for
    assert (hit.frame_status[:27, :4] == Reason.BODY_COLLISION).all() and hit.diagnosis["refined"]
    assert not (hit.frame_status[:, :4] == Reason.OK).any()  # nor is any refined base clear of the body
    assert hit.reason == Reason.OK and hit.chosen is not None and hit.diagnosis["last_resort"] > 0
    assert hit.candidates[hit.chosen].detail.startswith("last resort")
    assert (hit.status[:4] == Reason.BODY_COLLISION).all() and (hit.status[4:] == Reason.OK).all()


def test_a_clear_base_beats_the_last_resort(assets):
    """When one candidate is clear of the body, no candidate of last resort is considered."""
    hit = _head_at_base(0)
    assert hit.reason == Reason.OK and "last_resort" not in hit.diagnosis
    assert not any(c.detail.startswith("last resort") for c in hit.candidates)


def test_a_neighbours_settled_branch_is_taken_without_the_seed_search(assets, monkeypatch):
    """No seed keeps the full body clearance (a constant 13 cm here, below the 16.5 cm asked
    for): the first candidate tries every seed and settles; its neighbour, hinted with that
    branch, takes it after one solve when it keeps about as much, and searches again when not."""
    import importlib

    vb = importlib.import_module("handedit.retarget.virtual_base")
    targets, Tb = _known_sequence()
    arm = arm_model(EMB)
    target = np.linalg.inv(Tb) @ targets[0]
    solves = []
    solve = type(arm).solve

    def counted(self, *a, **k):
        solves.append(k.get("near", False))
        return solve(self, *a, **k)

    monkeypatch.setattr(type(arm), "solve", counted)
    seeds = [(arm.lo_s + arm.hi_s) / 2, np.zeros(arm.n)]
    first, settled = vb._first_frame(arm, target, seeds, CFG, lambda q: 0.13)
    assert settled == pytest.approx(0.13) and len(solves) == len(seeds) + CFG.body_seeds
    solves.clear()
    again, room = vb._first_frame(arm, target, [first.x] + seeds, CFG, lambda q: 0.13, hinted=True, hint_settled=settled)
    assert solves == [True] and room == pytest.approx(0.13)  # one solve, Newton first from the hint
    np.testing.assert_allclose(again.x, first.x, atol=1e-4)  # the same branch (Shadow's wrist joints make the arm redundant)
    solves.clear()
    vb._first_frame(arm, target, [first.x] + seeds, CFG, lambda q: 0.13, hinted=True, hint_settled=0.2)
    assert len(solves) == 1 + len(seeds) + CFG.body_seeds  # the neighbour kept more: search again


def test_the_body_seeds_search_for_clearance_only_once_a_seed_reached_the_target(assets, monkeypatch):
    """A first frame 3 m from the base: no seed reaches it, so the random body seeds (which look
    for a branch clearer of the operator, not for reach) are not tried, and the closest of the
    regular seeds' solutions is returned, rejected; one that reaches but keeps too little
    clearance tries them all (the test above)."""
    import importlib

    vb = importlib.import_module("handedit.retarget.virtual_base")
    targets, Tb = _known_sequence()
    arm = arm_model(EMB)
    far = np.linalg.inv(Tb) @ targets[0]
    far[:3, 3] *= 3.0 / np.linalg.norm(far[:3, 3])
    solves = []
    solve = type(arm).solve

    def counted(self, *a, **k):
        out = solve(self, *a, **k)
        solves.append(out)
        return out

    monkeypatch.setattr(type(arm), "solve", counted)
    seeds = [(arm.lo_s + arm.hi_s) / 2, np.zeros(arm.n)]
    sol, settled = vb._first_frame(arm, far, seeds, CFG, lambda q: 0.13)
    assert len(solves) == len(seeds) and settled is None
    assert sol.pos_err_mm > CFG.pos_tol_mm
    assert sol.pos_err_mm + 10 * sol.rot_err_deg == min(s.pos_err_mm + 10 * s.rot_err_deg for s in solves)


def test_a_first_frame_no_seed_reached_hints_no_neighbour(assets, monkeypatch):
    """The next candidate starts from its neighbour's first-frame joints only when those reached
    the target: a closest miss (IK_INFEASIBLE, here every third candidate's, made so after its
    solve) would steer it to whatever branch the miss lay on."""
    import importlib

    vb = importlib.import_module("handedit.retarget.virtual_base")
    targets, Tb = _known_sequence()
    evaluate, hints, made = vb._evaluate, [], []

    def spoiled(*a, **k):
        hints.append(a[6] if len(a) > 6 else k.get("hint"))
        track = evaluate(*a, **k)
        made.append(len(made) % 3 == 0)
        if made[-1]:
            track.status[0] = Reason.IK_INFEASIBLE
        return track

    monkeypatch.setattr(vb, "_evaluate", spoiled)
    search_virtual_base(targets, np.ones(len(targets), bool), EMB, CFG, up=UP, init_base=Tb)
    assert len(hints) >= 27
    after_miss = [h for h, miss in zip(hints[1:], made[:-1]) if miss]
    after_reach = [h for h, miss in zip(hints[1:], made[:-1]) if not miss]
    assert after_miss and all(h is None for h in after_miss)
    assert after_reach and all(h is not None for h in after_reach)


def test_one_failed_frame_in_fifty_does_not_discard_a_candidate(assets):
    """critical_tolerance: 1 of 50 critical frames may fail; that frame alone is rejected."""
    targets, Tb = _known_sequence(n=50)
    arm = arm_model(EMB)
    bad = targets.copy()
    bad[20, :3, 3] += Tb[:3, 0] * 3.0 * arm.max_reach  # one frame far out of reach
    valid = np.ones(len(bad), bool)
    res = search_virtual_base(bad, valid, EMB, CFG, up=UP, init_base=Tb)
    assert res.reason == Reason.OK and res.chosen is not None
    assert res.status[20] == Reason.OUT_OF_REACH and (np.delete(res.status, 20) == Reason.OK).all()
    strict = search_virtual_base(bad, valid, EMB, CFG.model_copy(update={"critical_tolerance": 0.0}), up=UP, init_base=Tb,
                                 critical=valid)
    assert not set(res.ranking) & set(strict.ranking)  # without the tolerance, every one of them is discarded
    # a frame that is not critical never discards a candidate, whatever the tolerance
    crit = valid.copy()
    crit[20] = False
    lenient = search_virtual_base(bad, valid, EMB, CFG.model_copy(update={"critical_tolerance": 0.0}), up=UP,
                                  init_base=Tb, critical=crit)
    assert set(lenient.ranking) >= set(res.ranking) and lenient.chosen == res.chosen


def test_a_candidate_past_its_critical_tolerance_is_not_solved_further(assets):
    """Once more critical frames fail than the tolerance allows (1 of 50 here), the candidate
    is discarded whatever follows: the rest of the sequence is not solved, and the verdict is
    the one the whole sequence gives."""
    import importlib

    vb = importlib.import_module("handedit.retarget.virtual_base")
    targets, Tb = _known_sequence(n=50)
    arm = arm_model(EMB)
    far = Tb.copy()
    far[:3, 3] += Tb[:3, 0] * 3.0 * arm.max_reach  # every target out of reach of this base
    valid = np.ones(len(targets), bool)
    whole = vb._evaluate(arm, far, targets, valid, None, CFG)
    cut = vb._evaluate(arm, far, targets, valid, None, CFG, critical=valid)
    assert whole.stopped is None and (whole.status == Reason.OUT_OF_REACH).all()
    assert cut.stopped == 1 and (cut.status[:2] == Reason.OUT_OF_REACH).all()
    assert (cut.status[2:] == Reason.NO_VALID_BASE).all()  # not solved
    entry = (0.0, 0.0, 0.0, far)
    a, b = (vb._score(0, entry, t, arm, valid, valid, CFG) for t in (whole, cut))
    assert a.reason == b.reason == Reason.OUT_OF_REACH and "where the search stopped" in b.detail
    # a candidate within its tolerance is solved to the end, the same as without the rule
    near = vb._evaluate(arm, Tb, targets, valid, None, CFG, critical=valid)
    assert near.stopped is None and (near.status == Reason.OK).all()
    np.testing.assert_array_equal(near.arm_q, vb._evaluate(arm, Tb, targets, valid, None, CFG).arm_q)


def test_a_wrist_flip_rejects_the_frames_past_it_not_the_base(assets):
    """A joint that jumps more than max_joint_step between kept frames (a warm start ran into
    its limit and the restart found the other branch) rejects the frames outside the longest
    continuous run as DISCONTINUITY; the candidate survives on the rest, ranked below a base
    that keeps every frame, and is discarded when that run is under min_reachability."""
    import importlib

    vb = importlib.import_module("handedit.retarget.virtual_base")
    targets, Tb = _known_sequence(n=20)
    arm = arm_model(EMB)
    valid = np.ones(len(targets), bool)
    track = vb._evaluate(arm, Tb, targets, valid, None, CFG, critical=valid)
    assert (track.status == Reason.OK).all()
    entry = (0.0, 0.0, 0.0, Tb)
    whole = vb._score(0, entry, track, arm, valid, valid, CFG)
    flipped = vb._Track(track.arm_q.copy(), track.status.copy(), track.pos_err, track.chains)
    flipped.arm_q[14:, 4] += 2 * np.pi - 0.4  # the wrist roll comes back from its other end at frame 14
    sc = vb._score(1, entry, flipped, arm, valid, valid, CFG)
    assert sc.reason == Reason.OK and sc.continuity <= CFG.max_joint_step
    assert (flipped.status[:14] == Reason.OK).all() and (flipped.status[14:] == Reason.DISCONTINUITY).all()
    assert sc.reachability == sc.critical_success == 14 / 20
    assert whole.key() < sc.key()
    early = vb._Track(track.arm_q.copy(), track.status.copy(), track.pos_err, track.chains)
    early.arm_q[6:, 4] += 2 * np.pi - 0.4  # the longer run is the later one: frames 0-5 go
    assert vb._score(2, entry, early, arm, valid, valid, CFG).reason == Reason.OK
    assert (early.status[:6] == Reason.DISCONTINUITY).all() and (early.status[6:] == Reason.OK).all()
    short = vb._Track(track.arm_q.copy(), track.status.copy(), track.pos_err, track.chains)
    short.arm_q[[5, 10, 15], 4] += 1.0  # a jump out and back three times: no run keeps half
    assert vb._score(3, entry, short, arm, valid, valid, CFG).reason == Reason.DISCONTINUITY


def test_a_base_the_dual_arm_check_rechooses_brings_its_own_frame_statuses(assets):
    """The dual-arm check may give a side a lower-ranked base: that side's frames then fail
    where the new base fails, not where the first choice did; the hand's own rejections and
    its QC's stay."""
    from types import SimpleNamespace

    from handedit.retarget.hand_arm import HandArmResult, merge_hand_qc, with_base
    from handedit.retarget.sides import SidesResult, _rechoose
    from handedit.retarget.virtual_base import VirtualBaseResult

    arm, n, OK = arm_model(EMB), 6, Reason.OK
    frame_status = np.full((2, n), OK, np.int16)
    frame_status[0, 2:4] = Reason.BODY_COLLISION  # the first choice's failures
    frame_status[1, 4] = Reason.JOINT_LIMIT  # the second's
    hand = SimpleNamespace(status=np.array([Reason.FINGERTIP_ERROR, OK, OK, OK, OK, OK], np.int16),
                           qpos=np.zeros((n, 0)), joint_names=[])
    qc = SimpleNamespace(status=hand.status.copy(), details={5: "contact lost"})
    qc.status[5] = Reason.CONTACT_LOSS
    bases = [SimpleNamespace(camera_from_base=np.eye(4)) for _ in range(2)]
    vb = VirtualBaseResult(EMB, arm.reach, bases, [0, 1], 0, "auto:top1", int(OK), "", np.eye(4), None, None,
                           frame_status[0], {}, np.zeros((2, n, arm.n)), frame_status)
    res = HandArmResult(np.zeros((n, arm.kin.dof), np.float32), np.tile(np.eye(4), (n, 1, 1)), np.zeros(n), np.zeros(n),
                        *with_base(hand.status, vb, 0), vb, list(arm.kin.joint_names), [], hand)
    first, details = merge_hand_qc(res, qc)
    assert list(first) == [Reason.FINGERTIP_ERROR, OK, Reason.BODY_COLLISION, Reason.BODY_COLLISION, OK,
                           Reason.CONTACT_LOSS]
    out = SidesResult(res.qpos[:, None].copy(), res.root_pose[:, None].copy(), np.zeros((n, 1)), np.zeros((n, 1)),
                      first[:, None].copy(), {(i, 0): d for i, d in details.items()}, res.joint_names,
                      virtual_base={"right": {}})
    _rechoose(out, 0, "right", 1, res, qc, None, None)
    assert list(out.hand_status[:, 0]) == [Reason.FINGERTIP_ERROR, OK, OK, OK, Reason.JOINT_LIMIT, Reason.CONTACT_LOSS]
    assert out.details == {(4, 0): "joint limit with base 1", (5, 0): "contact lost"}
    assert out.virtual_base["right"] == {"chosen": 1, "selected_by": "dual-arm:1"}
    assert list(res.status) == list(with_base(hand.status, vb, 0)[0])  # the side's own result is left as it was


def test_critical_frames_are_hands_in_view():
    kp = np.zeros((3, 21, 3))
    kp[:, :, 2] = 0.5
    kp[1, :, 0] = 5.0  # far right of the view
    kp[2, 0, 0] = 5.0  # only the wrist is out of view: still a hand in the image
    crit = critical_frames(kp, np.ones((3, 21), bool), np.ones(3, bool), INTR)
    assert crit.tolist() == [True, False, True]
    assert critical_frames(kp, np.ones((3, 21), bool), np.array([True, True, False]), None).tolist() == [True, True, False]


def test_reach_centre_and_the_second_grid(assets):
    targets, Tb = _known_sequence()
    arm = arm_model(EMB)
    T1, start = reach_centre(Tb, targets, np.ones(len(targets), bool), arm, 0.65)
    d = np.median(np.linalg.norm(targets[:, :3, 3] - (T1[:3, :3] @ arm.shoulder + T1[:3, 3]), axis=1)) / arm.reach
    assert d == pytest.approx(0.65, abs=1e-3) and start != pytest.approx(0.65, abs=1e-3)
    np.testing.assert_allclose(np.cross(T1[:3, 3] - Tb[:3, 3], Tb[:3, 0]), 0, atol=1e-9)  # slid along forward only
    out = np.array([1.0, 0.0, 0.0])
    grid = refine_grid(T1, arm.reach, out)
    assert len(grid) == 27
    assert {(g[0], g[4]) for g in grid} == {(a, b) for a in (0.0, 0.15, 0.3) for b in (0.0, 0.15, 0.3)}
    for lat, fwd, yaw, T, down in grid:  # outward, forward and down (along world up), upright and unyawed
        expect = T1[:3, 3] + (lat * out + fwd * T1[:3, 0] - down * T1[:3, 2]) * arm.reach
        np.testing.assert_allclose(T[:3, 3], expect, atol=1e-12)
        np.testing.assert_allclose(T[:3, :3], T1[:3, :3])
        assert yaw == 0.0


def test_no_base_in_the_grid_is_refined(assets):
    """Targets beyond the grid's reach: the paper's 27 all fail, the second grid (centred at
    0.65 L_r from the targets) finds the base, and the diagnosis says so."""
    targets, Tb = _known_sequence()
    arm = arm_model(EMB)
    far = Tb.copy()
    far[:3, 3] -= Tb[:3, 0] * 0.8 * arm.max_reach  # the grid centre 0.8 max reach behind the true base
    res = search_virtual_base(targets, np.ones(len(targets), bool), EMB, CFG.model_copy(update={"n_seeds": 3}), up=UP,
                              init_base=far)
    assert res.diagnosis["refined"] and len(res.candidates) == 54
    assert res.diagnosis["grid"].get("ok", 0) == 0 and res.diagnosis["refine"].get("ok", 0) > 0
    assert res.reason == Reason.OK and res.candidates[res.chosen].stage == "refine"


def test_a_base_off_the_arm_is_refined_too():
    """The second grid is searched when the best of the 27 lies off the human arm or crosses its
    forearm, not only when none survives; a plausible best, or one not measured, is enough."""
    from handedit.retarget.virtual_base import _why_refine

    def score(i, off, fa, reason=Reason.OK, crit=1.0):
        return CandidateScore(i, 0, 0, 0, np.eye(4), int(reason), "", crit, 1.0, 5.0, 0.2, 0.1, off_corridor=off,
                              forearm_deg=fa)

    assert _why_refine([score(0, 0.0, 0.0, Reason.OUT_OF_REACH)], CFG) == "no valid base"
    assert _why_refine([score(0, 0.05, 10.0), score(1, 0.4, 60.0)], CFG) == ""  # the best is plausible
    assert "0.22 off the arm" in _why_refine([score(0, 0.22, 10.0)], CFG)
    assert "40 degrees" in _why_refine([score(0, 0.1, 40.0)], CFG)
    assert _why_refine([score(0, float("nan"), float("nan"))], CFG) == ""  # not measured (no view): the 27 stand
    assert _why_refine([score(0, 0.22, 10.0)], CFG.model_copy(update={"refine_off_corridor": 0.3})) == ""


def test_footprint_and_forearm_measures():
    limb = np.array([[0.0, 0.05, 0.45], [0.0, 0.1, 0.4], [0.1, 0.3, 0.35], [0.2, 0.4, 0.1]])  # palm, wrist, elbow, shoulder
    view = BaseView(INTR, limb[None], True)
    along = np.stack([limb[3], limb[2], limb[1]])  # the robot arm where the human arm was
    across = np.array([[-0.3, -0.2, 0.5], [-0.2, -0.1, 0.45], [0.0, 0.1, 0.4]])  # in from the top left
    assert footprint_outside(along, limb, view, 0.035) < 0.05
    assert footprint_outside(across, limb, view, 0.035) > 0.5
    assert np.isnan(footprint_outside(np.array([[5.0, 0, 0.5], [6.0, 0, 0.5]]), limb, view, 0.035))  # not in view
    assert forearm_angle(along, limb) < 5.0
    assert forearm_angle(across, limb) > 60.0


def test_human_limbs_hint_the_forearm_without_arm_tracking():
    kp = np.zeros((2, 21, 3))
    kp[:, 0] = (0.0, 0.0, 0.5)  # wrist
    kp[:, 9] = (0.0, -0.1, 0.5)  # middle knuckle above it
    limbs, tracked = human_limbs(kp)
    assert not tracked and limbs.shape == (2, 3, 3)
    np.testing.assert_allclose(limbs[0, 2], (0.0, 0.25, 0.5))  # continued down, away from the knuckle
    arm = np.zeros((2, 3, 3))
    arm[:, 0], arm[:, 1] = (0.0, 0.3, 0.4), (0.2, 0.4, 0.1)
    valid = np.array([[True, True, True], [False, True, True]])
    limbs, tracked = human_limbs(kp, arm, valid)
    assert tracked and limbs.shape == (2, 4, 3)
    np.testing.assert_allclose(limbs[0, 2:], arm[0, :2])
    np.testing.assert_allclose(limbs[1, 2], (0.0, 0.25, 0.5))  # elbow not tracked: the hint, and no shoulder
    assert np.isnan(limbs[1, 3]).all()


def test_plausibility_ranks_before_reachability():
    def score(off, reach, fa=0.0):
        return CandidateScore(0, 0, 0, 0, np.eye(4), 1, "", 1.0, reach, 5.0, 0.2, 0.1, off_corridor=off, forearm_deg=fa)

    assert score(0.0, 0.97).key() < score(0.4, 1.0).key()  # a robot where the arm was beats a fuller reach
    assert score(0.0, 1.0, fa=10).key() < score(0.0, 1.0, fa=80).key()  # ties: the forearm that follows the human's
    assert score(0.02, 1.0).key() < score(float("nan"), 1.0).key()  # not in view ranks last


def test_frames_composite_would_drop_count_against_a_base():
    """A base that keeps every critical frame but fills the view off the arm, or hides its own
    hand, in most of them (composite's OFF_ARM or HAND_HIDDEN would drop those) ranks below
    one that loses a few to the body."""
    full = CandidateScore(0, 0, 0, 0, np.eye(4), 1, "", 1.0, 1.0, 5.0, 0.2, 0.1, off_corridor=0.55, screened_rate=0.75)
    fewer = CandidateScore(1, 0, 0, 0, np.eye(4), 1, "", 0.81, 0.81, 5.0, 0.2, 0.1, off_corridor=0.07)
    assert fewer.key() < full.key()
    assert CandidateScore(2, 0, 0, 0, np.eye(4), 1, "", 1.0, 1.0, 5.0, 0.2, 0.1, off_corridor=0.07).key() < fewer.key()


def test_the_footprint_is_the_links_visual_hulls():
    """Each link's hull points, projected and filled: outside the corridor counts, inside
    does not, a link behind the camera is not in view."""
    from handedit.retarget.plausibility import _footprint_camera, silhouette_outside

    view = BaseView(INTR, np.full((1, 4, 3), np.nan), True)
    intr, shape = _footprint_camera(view)
    corridor = np.zeros(shape, bool)
    corridor[:, : shape[1] // 2] = True  # the left half of the image
    cube = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05)])
    left, right = cube + (-0.3, 0, 1.0), cube + (0.3, 0, 1.0)
    assert silhouette_outside([left], view, corridor) == 0.0
    assert silhouette_outside([right], view, corridor) == 1.0
    assert 0.4 < silhouette_outside([left, right], view, corridor) < 0.6
    assert np.isnan(silhouette_outside([cube + (0, 0, -1.0)], view, corridor))


def test_the_search_sees_where_an_arm_link_would_hide_the_hand():
    """The visible surface of the footprint: a nearer link paints over a farther one, whatever
    the order of the links; the hand's keypoint hull under a visible arm link is hidden."""
    from handedit.retarget.plausibility import hand_hidden, silhouette

    view = BaseView(INTR, np.full((1, 4, 3), np.nan), True)
    cube = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05)])
    hand_link = cube * (2, 2, 1) + (0, 0, 1.0)  # the robot hand where the human hand is
    hand = np.array([[x, y, 1.0] for x in np.linspace(-0.08, 0.08, 5) for y in np.linspace(-0.08, 0.08, 4)] + [[0, 0, 1.0]])
    behind, before = cube + (0.05, 0, 1.3), cube + (0.05, 0, 0.6)  # an arm link behind the hand, one near the lens
    for links, arm, hides in (([hand_link, behind], [False, True], False), ([hand_link, before], [False, True], True),
                              ([before, hand_link], [True, False], True)):
        robot, arm_visible = silhouette(links, view, np.array(arm))
        assert robot.any() and (arm_visible <= robot).all()
        share = hand_hidden(arm_visible, hand, view)
        assert (share > 0.3) if hides else (share == 0.0), (arm, share)
    hand_nan = hand.copy()
    hand_nan[2:] = np.nan  # fewer than three keypoints: not measured
    assert np.isnan(hand_hidden(arm_visible, hand_nan, view))
    assert not silhouette([hand_link], view)[1].any()  # no arm flags: nothing is an arm link


def test_search_ranks_by_footprint(assets):
    """With a view, kept candidates carry footprint and forearm measures, and the ranking
    follows the key (footprint before reachability)."""
    targets, Tb = _known_sequence()
    n = len(targets)
    arm = arm_model(EMB)
    cams = _camera_at(np.array([0.0, 0.0, -0.6]), n)  # behind the scene, looking along +z
    cam_from = np.linalg.inv(cams[0])
    wrist = (cam_from[:3, :3] @ targets[:, :3, 3].T + cam_from[:3, 3:4]).T
    chain = Tb[:3, :3] @ arm.chain(np.asarray((arm.lo_s + arm.hi_s) / 2 + _q_offsets(arm))) + Tb[:3, 3:4]
    elbow = cam_from[:3, :3] @ chain[:, np.flatnonzero(arm.proximal)[1]] + cam_from[:3, 3]
    limbs = np.stack([np.stack([w, w, elbow, elbow + (0, -0.1, 0)]) for w in wrist])
    intr = Intrinsics(400.0, 400.0, 320.0, 240.0, 640, 480)
    hand = wrist[:, None] + np.random.default_rng(0).normal(0, 0.03, (n, 21, 3))  # a hand's keypoints at the wrist
    res = search_virtual_base(targets, np.ones(n, bool), EMB, CFG, up=UP, init_base=Tb, cameras=cams,
                              view=BaseView(intr, limbs, True, hand))
    kept = [res.candidates[i] for i in res.ranking]
    assert len(kept) > 1 and all(np.isfinite(c.off_corridor) and np.isfinite(c.forearm_deg) for c in kept)
    assert all(0.0 <= c.hand_hidden <= 1.0 and 0.0 <= c.screened_rate <= 1.0 for c in kept)
    assert all(res.candidates[i].off_corridor == 0.0 and res.candidates[i].forearm_deg == 0.0
               for i in range(27) if i not in res.ranking)  # discarded candidates are not measured
    keys = [c.key() for c in kept]
    assert keys == sorted(keys) and keys[0][1] == min(k[1] for k in keys)
    assert res.diagnosis["plausibility"] == "tracked arm"
