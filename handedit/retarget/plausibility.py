"""Base plausibility inside the virtual-base search: the paper's operator review, as numbers.

The paper's operator drops a base whose robot arm fills the view where no human arm was,
passes through the operator's head, reaches in from an odd direction, or hides the hand
doing the task. Three measures stand in for that look, from the robot's geometry and the
search's joint tracks (no GL rendering; the operator's head and torso as a keep-out volume
is ``virtual_base.body_distance``):

* ``silhouette_outside``: the share of the robot's projected footprint (each link's visual
  hull, filled; ``footprint_outside`` draws capsules around the links' origins instead, for
  a robot without meshes) outside the human arm's corridor in the image (the human hand,
  wrist, forearm and upper arm, as far as the source tracks them, grown by a share of the
  image width): the robot must appear where the human arm was. Capsules of 3.5 cm missed
  what fills the view: Jaka's thick upper arm beside the camera measured 4 % outside where
  the rendered robot was more than 35 % outside;
* ``forearm_angle``: the angle between the robot's forearm and the human forearm (ties go
  to the candidate that follows the human arm);
* ``hand_hidden``: the share of the human hand's footprint (its keypoints' hull) where the
  robot's visible surface is an arm link, composite's HAND_HIDDEN screen before rendering:
  seen from the operator's eyes, a robot forearm near the lens can hide its own hand. The
  hull is smaller than the hand's mask (fingers' width, the wrist), so this reads about 1.3x
  composite's share on the same frame (EgoDex add_remove_lid, xArm+Ability and Panda+Allegro).

Where the source does not track the arm, the human forearm is continued from the hand
(wrist, away from the middle knuckle, ``FOREARM_HINT_M``): its direction, not its length.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from handedit.camera import Intrinsics
from handedit.keypoints import JOINT_INDEX, WRIST
from handedit.vision.arm import CORRIDOR_FRAC, FOREARM_RADIUS_M, NEAR_M, capsule, corridor, limbs, outside_share, tracked

FOREARM_HINT_M = 0.25  # a forearm's length: the hinted forearm runs this far back from the wrist
FOOTPRINT_WIDTH = 160  # the footprint is measured on an image this many pixels wide (a share, not a mask)


@dataclass(frozen=True)
class BaseView:
    """What the search needs to judge a base in the image, for one side of one sequence.

    intr: the camera at the working resolution (the mirrored camera for a left side);
    limbs: (T,m,3) per frame the human polyline palm -> wrist -> elbow -> shoulder in the
    camera frame, NaN after its tracked part (``human_limbs``); tracked_arm: whether the
    elbow/shoulder come from the source (else the forearm is the hint); hand: the hand's
    keypoints (``hand_hidden``; None: not measured)."""

    intr: Intrinsics
    limbs: np.ndarray
    tracked_arm: bool
    hand: np.ndarray | None = None  # (T,21,3) the hand's keypoints in the same camera frame, NaN where not valid
    _corridors: dict = field(default_factory=dict, repr=False, compare=False)

    def corridor(self, i: int) -> np.ndarray:
        """Frame ``i``'s human arm corridor (``human_corridor``), made once: every candidate reads it."""
        if i not in self._corridors:
            self._corridors[i] = human_corridor(self.limbs[i], self)
        return self._corridors[i]


def human_limbs(keypoints: np.ndarray, arm_keypoints: np.ndarray | None = None,
                arm_valid: np.ndarray | None = None) -> tuple[np.ndarray, bool]:
    """(T,m,3) palm centre -> wrist -> elbow -> shoulder (camera frame) per frame, NaN after
    the first untracked joint; without tracked arm joints, palm -> wrist -> hinted elbow.
    Returns the polylines and whether any frame tracks the arm."""
    kp = np.asarray(keypoints, float)
    palm, wrist = kp[:, JOINT_INDEX["middle_mcp"]], kp[:, WRIST]
    axis = wrist - palm
    norm = np.linalg.norm(axis, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        hint = wrist + FOREARM_HINT_M * axis / norm
    if arm_keypoints is None or arm_valid is None or not np.asarray(arm_valid, bool)[:, 0].any():
        return np.stack([palm, wrist, hint], axis=1), False
    line = limbs(kp, np.asarray(arm_keypoints)[:, :2], np.asarray(arm_valid)[:, :2])  # wrist, elbow, shoulder
    no_elbow = ~np.isfinite(line[:, 1]).all(-1)
    line[no_elbow, 1] = hint[no_elbow]  # no elbow in a frame: the hint stands in (and no shoulder)
    return np.concatenate([palm[:, None], line], axis=1), True


def _footprint_camera(view: BaseView) -> tuple[Intrinsics, tuple[int, int]]:
    """The camera and shape of the small image the footprint is measured on."""
    w = FOOTPRINT_WIDTH
    h = max(1, int(round(view.intr.height * w / view.intr.width)))
    return view.intr.scaled(w, h), (h, w)


def human_corridor(limb_cam: np.ndarray, view: BaseView, frac: float = CORRIDOR_FRAC) -> np.ndarray:
    """Where a robot arm may appear on the footprint image: the human arm's capsule (``limb_cam``,
    camera frame, as far as it is tracked) grown by ``frac`` of the image width."""
    intr, shape = _footprint_camera(view)
    line = tracked(limb_cam)
    human = capsule(line, intr, FOREARM_RADIUS_M, shape) if len(line) >= 2 else np.zeros(shape, bool)
    return corridor(human, None, frac)


def footprint_outside(robot_cam: np.ndarray, limb_cam: np.ndarray, view: BaseView, link_radius: float,
                      frac: float = CORRIDOR_FRAC, corridor_mask: np.ndarray | None = None) -> float:
    """Share of the robot arm's footprint (capsules of ``link_radius`` around the polyline
    ``robot_cam``, camera frame) outside the human arm's corridor (``limb_cam``, or its
    ``corridor_mask`` when the caller has it: ``BaseView.corridor``); NaN when the robot is
    not in view."""
    intr, shape = _footprint_camera(view)
    robot = capsule(robot_cam, intr, link_radius, shape)
    if not robot.any():
        return float("nan")
    return outside_share(robot, human_corridor(limb_cam, view, frac) if corridor_mask is None else corridor_mask)


def silhouette(links_cam: list[np.ndarray], view: BaseView, arm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The robot's footprint on the footprint image and where an arm link (``arm``: per link,
    ``ArmModel.hull_is_arm``) is its visible surface: each link's visual hull (``links_cam``:
    its points in the camera frame, ``ArmModel.link_points``) projected and filled, nearer
    links (by mean depth) over farther; points behind the near plane are pulled onto it."""
    intr, shape = _footprint_camera(view)
    label = np.zeros(shape, np.uint8)  # 0: no robot, 1: hand link, 2: arm link
    drawn = [(float(np.mean(p[:, 2])), k) for k, p in enumerate(links_cam) if len(p) and (p[:, 2] > 0).any()]
    for _, k in sorted(drawn, reverse=True):  # far to near: a nearer link paints over
        p = links_cam[k]
        z = np.maximum(p[:, 2], NEAR_M)
        uv = np.stack([intr.fx * p[:, 0] / z + intr.cx, intr.fy * p[:, 1] / z + intr.cy], axis=1)
        hull = cv2.convexHull(np.clip(np.round(uv), -1e5, 1e5).astype(np.int32))
        cv2.fillConvexPoly(label, hull, 2 if arm is not None and arm[k] else 1)
    return label > 0, label == 2


def silhouette_outside(links_cam: list[np.ndarray], view: BaseView, corridor_mask: np.ndarray,
                       robot: np.ndarray | None = None) -> float:
    """Share of the robot's footprint (``silhouette``, or ``robot`` when the caller has it)
    outside the human arm's corridor (``corridor_mask``: ``BaseView.corridor``). NaN when no
    link is in view."""
    robot = silhouette(links_cam, view)[0] if robot is None else robot
    if not robot.any():
        return float("nan")
    return outside_share(robot, corridor_mask)


def hand_hidden(arm_visible: np.ndarray, hand_cam: np.ndarray, view: BaseView) -> float:
    """Share of the human hand's footprint (the hull of its keypoints ``hand_cam``, camera
    frame, NaN where not valid) where an arm link is the robot's visible surface
    (``silhouette``'s second mask); NaN when fewer than three keypoints are in front."""
    intr, shape = _footprint_camera(view)
    p = hand_cam[np.isfinite(hand_cam).all(-1) & (hand_cam[:, 2] > NEAR_M)] if hand_cam is not None else np.zeros((0, 3))
    if len(p) < 3:
        return float("nan")
    uv = np.stack([intr.fx * p[:, 0] / p[:, 2] + intr.cx, intr.fy * p[:, 1] / p[:, 2] + intr.cy], axis=1)
    hand = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(hand, cv2.convexHull(np.clip(np.round(uv), -1e5, 1e5).astype(np.int32)), 1)
    m = int(hand.sum())
    return float((arm_visible & (hand > 0)).sum()) / m if m else float("nan")


def forearm_angle(robot_cam: np.ndarray, limb_cam: np.ndarray) -> float:
    """Angle (degrees) between the robot's forearm (wrist -> its elbow: the link point farthest
    from the shoulder-wrist line) and the human forearm (wrist -> elbow); NaN when either is
    missing. ``robot_cam``: the arm's polyline from its shoulder to its wrist."""
    pts = np.asarray(robot_cam, float)
    if len(pts) < 3 or not np.isfinite(limb_cam[1:3]).all():
        return float("nan")
    s, w = pts[0], pts[-1]
    axis = (w - s) / (np.linalg.norm(w - s) + 1e-12)
    rel = pts[1:-1] - s
    off = np.linalg.norm(rel - (rel @ axis)[:, None] * axis, axis=1)
    a = pts[1 + int(np.argmax(off))] - w
    b = limb_cam[2] - limb_cam[1]
    c = a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12)
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
