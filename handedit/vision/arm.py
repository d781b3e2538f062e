"""The human arm in the image, from a source's 3-D arm joints: capsules, corridor, coverage.

Why 3-D: EgoDex tracks each arm (wrist, elbow, shoulder) in the camera frame, but the
elbow is often beside or behind the camera (5-19 cm deep) and the shoulder behind it, so
the projected joints lie far outside the view and say little by themselves. A capsule
around the 3-D segments, clipped at a near plane and projected with its radius scaled by
depth, keeps the forearm's direction and its width in perspective: near the camera the arm
is wide, far from it narrow. What a sleeve looks like is left to the image (segment).

The same capsule defines the measures the paper's human screening applies by eye:
``coverage`` (how much of the forearm a hand-arm mask holds: the sleeve must go) and
``outside_share`` (how much of a robot lies outside the human arm's corridor: a robot arm
must appear where the human arm was).
"""

from __future__ import annotations

import cv2
import numpy as np

from handedit.camera import Intrinsics, project
from handedit.reasons import STATUS_DTYPE, Reason

NEAR_M = 0.05  # capsule segments are clipped to z >= this (the arm runs past the camera)
FOREARM_RADIUS_M = 0.04  # a forearm's radius; the measure of the hand-arm issue
CORRIDOR_FRAC = 0.05  # the corridor grows by this share of the image width
MAX_OFF_ARM = 0.25  # a hand-arm robot with more of its pixels outside the corridor is OFF_ARM (composite; the base search)
MAX_HAND_HIDDEN = 0.2  # a robot arm over more of a human hand's pixels than this hides the robot's hand: HAND_HIDDEN


def clip_near(a: np.ndarray, b: np.ndarray, near: float = NEAR_M) -> tuple[np.ndarray, np.ndarray] | None:
    """The part of segment [a, b] at z >= ``near`` (None: all of it is nearer)."""
    if a[2] < near and b[2] < near:
        return None
    if a[2] < near:
        a = b + (a - b) * (b[2] - near) / (b[2] - a[2])
    elif b[2] < near:
        b = a + (b - a) * (a[2] - near) / (a[2] - b[2])
    return a, b


def tracked(line: np.ndarray) -> np.ndarray:
    """The tracked part of a ``limbs`` polyline: its points up to the first NaN one."""
    ok = np.isfinite(line).all(-1)
    return line if ok.all() else line[: int(np.argmin(ok))]


def capsule(points: np.ndarray, intr: Intrinsics, radius_m: float, shape: tuple[int, int], *, start_m: float = 0.0,
            near: float = NEAR_M) -> np.ndarray:
    """Bool (H,W) mask of the capsule of ``radius_m`` around the 3-D polyline ``points`` (camera
    frame, metres), projected with ``intr`` (at the mask's resolution), each disc's radius
    scaled by its depth. ``start_m``: the first metres along the polyline are left out (the
    hand's own region when seeding the arm)."""
    h, w = shape
    out = np.zeros((h, w), np.uint8)
    pts = np.asarray(points, float)
    walked = 0.0
    for a, b in zip(pts[:-1], pts[1:]):
        seg_len = float(np.linalg.norm(b - a))
        if seg_len < 1e-6:
            continue
        t0 = min(1.0, max(0.0, (start_m - walked) / seg_len))
        walked += seg_len
        if t0 >= 1.0:
            continue
        clipped = clip_near(a + t0 * (b - a), b, near)
        if clipped is None:
            continue
        a2, b2 = clipped
        uv = project(np.stack([a2, b2]), intr)
        # discs a third of the smallest radius apart along the projected segment
        r_min = intr.fx * radius_m / max(a2[2], b2[2])
        n = int(min(2000, max(2, np.linalg.norm(uv[1] - uv[0]) / max(1.0, r_min / 3.0) + 2)))
        ts = np.linspace(0.0, 1.0, n)
        P = a2[None] + ts[:, None] * (b2 - a2)[None]
        centres, radii = project(P, intr), intr.fx * radius_m / P[:, 2]
        for (u, v), r in zip(centres, radii):
            if -r <= u <= w + r and -r <= v <= h + r:
                cv2.circle(out, (int(round(u)), int(round(v))), max(1, int(round(r))), 1, -1)
    return out.astype(bool)


def forearm_capsule(wrist: np.ndarray, elbow: np.ndarray, intr: Intrinsics, shape: tuple[int, int],
                    radius_m: float = FOREARM_RADIUS_M) -> np.ndarray:
    """The forearm (wrist to elbow) as a capsule of ``radius_m``: the coverage measure's region."""
    return capsule(np.stack([np.asarray(wrist, float), np.asarray(elbow, float)]), intr, radius_m, shape)


def coverage(handarm_mask: np.ndarray, forearm: np.ndarray, min_px: int = 50) -> float | None:
    """Share of the forearm capsule's in-view pixels inside the hand-arm mask (None: the
    forearm is not in view, fewer than ``min_px`` pixels)."""
    n = int(forearm.sum())
    if n < min_px:
        return None
    return float((handarm_mask & forearm).sum()) / n


def corridor(handarm_mask: np.ndarray, forearm: np.ndarray | None = None, frac: float = CORRIDOR_FRAC) -> np.ndarray:
    """Where a robot arm may appear: the human arm (hand-arm mask and forearm capsule), grown
    by ``frac`` of the image width."""
    region = handarm_mask if forearm is None else (handarm_mask | forearm)
    dist = cv2.distanceTransform((~region).astype(np.uint8), cv2.DIST_L2, 3)
    return dist <= frac * region.shape[1]


def outside_share(robot_mask: np.ndarray, corridor_mask: np.ndarray) -> float:
    """Share of the robot's pixels outside the human arm's corridor (0 for an empty robot)."""
    n = int(robot_mask.sum())
    return float((robot_mask & ~corridor_mask).sum()) / n if n else 0.0


def limbs(keypoints: np.ndarray, arm_keypoints: np.ndarray, arm_valid: np.ndarray | None = None) -> np.ndarray:
    """(..., 1+m, 3) polylines wrist -> elbow -> shoulder from (..., 21, 3) hand keypoints and
    (..., m, 3) arm joints; NaN from the first untracked joint on (the polyline stops there)."""
    wrist = np.asarray(keypoints, float)[..., :1, :]
    arm = np.asarray(arm_keypoints, float).copy()
    if arm_valid is not None:
        stop = np.cumprod(np.asarray(arm_valid, bool), axis=-1).astype(bool)  # untracked from the first gap on
        arm[~stop] = np.nan
    return np.concatenate([wrist, arm], axis=-2)


def off_arm_shares(robot_mask: np.ndarray, human_mask: np.ndarray, limbs_3d: np.ndarray | None, intr: Intrinsics | None,
                   checked: np.ndarray, frac: float = CORRIDOR_FRAC, step: int = 4) -> np.ndarray:
    """(n,S) share of each checked side's robot pixels outside its arm corridor (NaN where not
    checked): the paper's "base plausibility" screen, a robot arm must appear where the human
    arm was. ``robot_mask``/``human_mask`` (n,S,H,W); ``limbs_3d`` (n,S,m,3) adds the tracked
    forearm's capsule to the corridor. Measured on every ``step``-th pixel (a share, not a mask)."""
    n, S, H, W = robot_mask.shape
    out = np.full((n, S), np.nan, np.float32)
    small = (max(1, W // step), max(1, H // step))
    intr_s = None if intr is None else intr.scaled(*small)
    for i, k in zip(*np.nonzero(checked)):
        robot = robot_mask[i, k, ::step, ::step][: small[1], : small[0]]
        if not robot.any():
            out[i, k] = 0.0
            continue
        human = human_mask[i, k, ::step, ::step][: small[1], : small[0]]
        line = None if limbs_3d is None or intr_s is None else tracked(limbs_3d[i, k])
        forearm = None if line is None or len(line) < 2 else capsule(line, intr_s, FOREARM_RADIUS_M, human.shape)
        out[i, k] = outside_share(robot, corridor(human, forearm, frac))
    return out


def screen_status(own: np.ndarray, checked: np.ndarray, shares: np.ndarray, max_share: float, reason: Reason) -> np.ndarray:
    """(n,S) statuses with ``reason`` where a checked side's share exceeds ``max_share`` (composite's
    hand-arm screens: ``OFF_ARM`` from ``off_arm_shares``, ``HAND_HIDDEN`` from ``hand_hidden_shares``)."""
    return np.where(checked & (shares > max_share), reason, own).astype(STATUS_DTYPE)


def hand_hidden_shares(robot_arm: np.ndarray, hand_mask: np.ndarray, checked: np.ndarray, step: int = 2) -> np.ndarray:
    """(n,S) share of each checked side's human hand pixels where the composite shows a robot
    arm link, any robot's (NaN where not checked or the hand has no pixel). A robot arm is wider
    than a human forearm: seen from the operator's eyes, a wrist module or an elbow passing near
    the lens can hide the robot's own hand where the human hand was in view, and the pair then
    shows an arm, not a hand doing the task. ``robot_arm`` (n,H,W) bool (render's ``robot_arm``,
    what is left visible), ``hand_mask`` (n,S,H,W); measured on every ``step``-th pixel."""
    n, S = hand_mask.shape[:2]
    out = np.full((n, S), np.nan, np.float32)
    for i, k in zip(*np.nonzero(checked)):
        hand = hand_mask[i, k, ::step, ::step]
        m = int(hand.sum())
        if m:
            out[i, k] = float((hand & robot_arm[i, ::step, ::step]).sum()) / m
    return out
