"""estimate_hands: 3-D hand keypoints from RGB, for videos that come without any.

Per frame, a hand detector and landmark model (MediaPipe's, ``handedit.models.mediapipe_hands``)
give each visible hand's 21 landmarks in pixels, its landmarks in metres around the hand
(``world``), a presence score and a handedness probability. Three steps turn them into
what the dataset adapters provide, camera-frame MANO-order joints per side:

1. **Depth.** The 2-D landmarks fix each joint's ray; the depth along it is estimated.
   ``bones`` (default): each joint on its ray at a typical adult bone length from its
   parent, the wrist at the depth of the least foreshortened palm segment (``lift_bones``).
   ``pnp``: the model's metric, hand-centred world landmarks moved rigidly to reproject
   onto the 2-D ones (``cv2.solvePnP``, SQPnP then Levenberg-Marquardt). Both rest on a
   hand size, so depth is the weak part (``bench/estimate_hands.py`` measures it where
   ground truth exists; MediaPipe's world landmarks are nearly flat on egocentric views,
   which is why ``bones`` is the default). An ONNX plug-in (``handedit.models.hand_pose``:
   crop -> MANO-21 joints + weak-perspective camera, HaMeR/WiLoR-style) can replace this
   step; detection, tracking and handedness stay MediaPipe's.
2. **Sides.** A track is a hand followed from frame to frame by the landmark tracker.
   Each track takes the side its frames vote for (the sum of p_right - 0.5), so a flicker
   of the classifier never swaps a hand's side mid-track; when two tracks in one frame
   claim one side, the one with less evidence takes the other.
3. **Smoothing.** A one-euro filter per side and coordinate, restarted after a frame
   without that side (little lag when the hand moves fast, strong smoothing when it is
   still); the raw keypoints are kept beside.

QC per side and frame: not detected -> ``ABSENT`` (both sides ``NO_HAND_DETECTED`` when
no hand is found at all); presence below ``min_presence`` -> ``LOW_HAND_CONFIDENCE``; bone
lengths far from a human hand's, or a reprojection error above ``max_reprojection_px``
-> ``IMPLAUSIBLE_HAND``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Iterable, Literal

import cv2
import numpy as np
import pydantic

from handedit.models.runtime import OnnxRuntime
from handedit.camera import Intrinsics, project
from handedit.keypoints import N_JOINTS, PARENT, SIDES
from handedit.reasons import STATUS_DTYPE, Reason

# Typical adult bone lengths (m, rounded), MANO-21 order (joint j's bone ends at j); a bone
# outside [1/bone_ratio, bone_ratio] x these is implausible (the check is coarse on purpose).
HUMAN_BONES_M = np.array([
    0.0, 0.035, 0.034, 0.029, 0.026,   # thumb: cmc, mcp, ip, tip
    0.093, 0.040, 0.024, 0.022,         # index
    0.092, 0.045, 0.027, 0.023,         # middle
    0.086, 0.042, 0.026, 0.023,         # ring
    0.080, 0.033, 0.019, 0.021,         # pinky
])


class EstimateHandsConfig(pydantic.BaseModel):
    VERSION: ClassVar[int] = 1
    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    # auto: only for sources without keypoints; always: also replace a source's own keypoints
    mode: Literal["auto", "always", "never"] = "auto"
    model_dir: Path | None = pydantic.Field(None, description="folder of the MediaPipe hand models "
                                            "(default: $HANDEDIT_HAND_MODEL_DIR, else the cache `handedit models fetch` fills)")
    variant: Literal["full", "lite"] = "full"
    model_path: Path | None = pydantic.Field(None, description="optional ONNX hand-pose plug-in (handedit.models.hand_pose)")
    onnx: OnnxRuntime = OnnxRuntime()  # how the model runs (providers, threads): part of the key
    # depth of the hand: "bones" (a human hand's bone lengths on the landmarks' rays) or
    # "pnp" (the model's metric world landmarks fitted to the 2-D ones); see the module doc
    depth: Literal["bones", "pnp"] = "bones"
    hand_scale: float = pydantic.Field(1.0, gt=0.5, lt=1.5, description="the hands' size relative to a typical adult's (bones)")
    max_hands: int = pydantic.Field(2, ge=1, le=2)
    min_detection: float = pydantic.Field(0.5, gt=0, lt=1, description="palm detection score")
    min_presence: float = pydantic.Field(0.5, gt=0, lt=1, description="landmark model's hand presence score")
    bone_ratio: float = pydantic.Field(1.8, gt=1, description="a bone more than this factor off a human hand's is implausible")
    max_reprojection_px: float = pydantic.Field(12.0, gt=0, description="mean reprojection error of the 3-D hand, px at 640 wide")
    smooth: bool = True
    min_cutoff_hz: float = pydantic.Field(1.5, gt=0, description="one-euro: cutoff of a still hand")
    beta: float = pydantic.Field(8.0, ge=0, description="one-euro: cutoff growth per m/s of speed")

    def hand_model_dir(self) -> Path:
        if self.model_dir is not None:
            return Path(self.model_dir).expanduser()
        env = os.environ.get("HANDEDIT_HAND_MODEL_DIR")
        if env:
            return Path(env).expanduser()
        from handedit.models.fetch import default_model_dir

        return default_model_dir()

    def model_digests(self) -> dict[str, str]:
        """The hand model files this config runs, by content (``handedit.digests.model_digests``);
        "missing" when they are not there (the stage then says how to get them)."""
        from handedit.digests import file_digest
        from handedit.models.mediapipe_hands import HandModelError, HandModelFiles

        if self.mode == "never":
            return {}
        try:
            files = HandModelFiles.in_dir(self.hand_model_dir(), self.variant)
        except HandModelError:
            return {"hand_models": "missing"}
        return {"hand_models": "+".join(file_digest(p)[:16] for p in (files.palm, files.landmark))}


@dataclass
class HandEstimate:
    """Per frame and side (n,S) in ``SIDES`` order; keypoints camera frame, metres, MANO order."""

    keypoints: np.ndarray  # (n,S,21,3) float32, smoothed
    keypoints_raw: np.ndarray  # (n,S,21,3) float32
    keypoints_valid: np.ndarray  # (n,S,21) bool
    confidence: np.ndarray  # (n,S,21) float32: presence, 0 for joints outside the image
    box: np.ndarray  # (n,S,4) float32 x0,y0,x1,y1 px (the landmark rectangle's box)
    p_right: np.ndarray  # (n,S) float32, the classifier's raw right-hand probability
    reprojection_px: np.ndarray  # (n,S) float32
    hand_status: np.ndarray  # (n,S)
    details: dict[tuple[int, int], str]
    method: str
    stats: dict


# ----------------------------------------------------------------------------- lifting


def lift_pnp(image_xy: np.ndarray, world: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, float]:
    """Camera-frame joints (21,3): the world landmarks moved rigidly to reproject onto the
    2-D landmarks; and the mean reprojection error (px)."""
    obj = np.ascontiguousarray(world, np.float64)
    img = np.ascontiguousarray(image_xy, np.float64)
    K, dist = intr.K, np.zeros(5)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:  # fall back: translation only, world axes taken as the camera's
        rvec, tvec = np.zeros(3), _translation_only(img, obj, intr)
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec.reshape(3, 1).astype(np.float64), tvec.reshape(3, 1).astype(np.float64))
    R = cv2.Rodrigues(rvec)[0]
    cam = obj @ R.T + tvec.reshape(1, 3)
    if cam[:, 2].min() <= 0:  # the mirror solution behind the camera: keep the axes, solve depth only
        cam = obj + _translation_only(img, obj, intr)
    err = float(np.linalg.norm(project(cam, intr) - img, axis=1).mean())
    return cam, err


PALM_WIDTH_M = 0.068  # index knuckle to little-finger knuckle, typical adult hand


def lift_bones(image_xy: np.ndarray, world: np.ndarray, intr: Intrinsics, hand_scale: float = 1.0) -> tuple[np.ndarray, float]:
    """Camera-frame joints (21,3) on the rays of the 2-D landmarks with a human hand's bone
    lengths (x ``hand_scale``). Wrist depth: the palm segment that is least foreshortened
    (the smallest f L / l over wrist-knuckle bones and the palm width); then joint by joint
    down the tree, the point on the joint's ray at bone length from its parent, in front of
    or behind it as the model's relative depth says. Reprojection error is 0 unless a bone
    is too short to reach its ray (then the ray's closest point)."""
    uv = np.asarray(image_xy, np.float64)
    rays = np.c_[(uv[:, 0] - intr.cx) / intr.fx, (uv[:, 1] - intr.cy) / intr.fy, np.ones(len(uv))]
    bones = HUMAN_BONES_M * hand_scale
    f = 0.5 * (intr.fx + intr.fy)
    segs = [(0, j, bones[j]) for j in (5, 9, 13, 17)] + [(5, 17, PALM_WIDTH_M * hand_scale)]
    z = min(f * L / max(np.linalg.norm(uv[a] - uv[b]), 1e-6) for a, b, L in segs)
    cam = np.zeros((len(uv), 3))
    cam[0] = rays[0] * z
    for j in range(1, len(uv)):
        p = PARENT[j]
        P, r, L = cam[p], rays[j], bones[j]
        a, b, c = r @ r, -2 * (r @ P), P @ P - L * L
        disc = b * b - 4 * a * c
        if disc < 0:  # the bone cannot reach the ray: the ray's closest point
            cam[j] = r * (r @ P) / a
            continue
        roots = ((-b - np.sqrt(disc)) / (2 * a), (-b + np.sqrt(disc)) / (2 * a))
        want = world[j, 2] - world[p, 2]  # the model's depth of the joint relative to its parent
        t = min(roots, key=lambda t: abs(t * r[2] - P[2] - want))
        cam[j] = r * t
    return cam, float(np.linalg.norm(project(cam, intr) - uv, axis=1).mean())


def _translation_only(uv: np.ndarray, obj: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """t minimising the linearised reprojection error of obj + t (u - cx)(Z + tz) = fx (X + tx)."""
    a = (uv[:, 0] - intr.cx) / intr.fx
    b = (uv[:, 1] - intr.cy) / intr.fy
    n = len(uv)
    A = np.zeros((2 * n, 3))
    y = np.zeros(2 * n)
    A[:n, 0], A[:n, 2], y[:n] = 1.0, -a, a * obj[:, 2] - obj[:, 0]
    A[n:, 1], A[n:, 2], y[n:] = 1.0, -b, b * obj[:, 2] - obj[:, 1]
    return np.linalg.lstsq(A, y, rcond=None)[0]


def bone_lengths(kp: np.ndarray) -> np.ndarray:
    """(...,21) length of the bone ending at each joint (0 for the wrist)."""
    par = np.array([max(p, 0) for p in PARENT])
    return np.linalg.norm(kp - kp[..., par, :], axis=-1)


def implausible_bones(kp: np.ndarray, ratio: float) -> list[int]:
    """Joints whose bone is more than ``ratio`` off a human hand's."""
    r = bone_lengths(kp)[1:] / HUMAN_BONES_M[1:]
    return [int(j) + 1 for j in np.flatnonzero((r > ratio) | (r < 1.0 / ratio))]


def aligned_error_mm(est: np.ndarray, gt: np.ndarray) -> float:
    """Mean joint distance (mm) after the best rotation + translation of ``est`` onto ``gt``
    (Kabsch): the shape error, without the depth and pose an RGB estimate cannot pin down."""
    a, b = est - est.mean(0), gt - gt.mean(0)
    U, _, Vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(U @ Vt))
    R = (U @ np.diag([1, 1, d]) @ Vt).T
    return float(np.linalg.norm(a @ R.T - b, axis=1).mean() * 1000)


# ----------------------------------------------------------------------------- smoothing


def one_euro(x: np.ndarray, valid: np.ndarray, fps: float, min_cutoff: float, beta: float, d_cutoff: float = 1.0) -> np.ndarray:
    """One-euro filter along axis 0 of x (T, ...), restarted after every invalid frame."""
    out = np.array(x, np.float64, copy=True)
    dt = 1.0 / fps
    alpha = lambda fc: 1.0 / (1.0 + 1.0 / (2 * math.pi * fc * dt))  # noqa: E731
    prev = dprev = None
    for t in range(len(x)):
        if not valid[t]:
            prev = dprev = None
            continue
        if prev is None:
            prev, dprev = out[t].copy(), np.zeros_like(out[t])
            continue
        d = (out[t] - prev) / dt
        dprev = dprev + alpha(d_cutoff) * (d - dprev)
        speed = np.linalg.norm(dprev, axis=-1, keepdims=True)  # per point (m/s)
        a = 1.0 / (1.0 + 1.0 / (2 * math.pi * (min_cutoff + beta * speed) * dt))
        prev = prev + a * (out[t] - prev)
        out[t] = prev
    return out


# ----------------------------------------------------------------------------- the stage


@dataclass
class _Det:
    frame: int
    track: int
    xy: np.ndarray
    world: np.ndarray
    presence: float
    p_right: float
    box: np.ndarray
    cam: np.ndarray | None = None
    reproj: float = np.nan


def assign_sides(dets: list[_Det]) -> dict[int, int]:
    """track -> side index (SIDES order): each track takes the side its frames vote for
    (sum of p_right - 0.5, so a long, sure track outweighs a short one); when two tracks
    share a frame and a side, the one with less evidence for that side takes the other."""
    votes: dict[int, float] = {}
    for d in dets:
        votes[d.track] = votes.get(d.track, 0.0) + (d.p_right - 0.5)
    side = {t: int(v >= 0) for t, v in votes.items()}
    by_frame: dict[int, list[int]] = {}
    for d in dets:
        by_frame.setdefault(d.frame, []).append(d.track)
    for tracks in by_frame.values():
        if len(tracks) == 2 and side[tracks[0]] == side[tracks[1]]:
            weaker = min(tracks, key=lambda t: abs(votes[t]))
            side[weaker] = 1 - side[weaker]
    return side


def judge(d: _Det, cfg: EstimateHandsConfig, max_reprojection_px: float) -> tuple[Reason, str]:
    """One found hand's QC: (reason, detail; "" when OK)."""
    if d.presence < cfg.min_presence:
        return Reason.LOW_HAND_CONFIDENCE, f"hand presence {d.presence:.2f} < {cfg.min_presence}"
    bad = implausible_bones(d.cam, cfg.bone_ratio)
    if bad:
        return Reason.IMPLAUSIBLE_HAND, f"bone lengths off a human hand's by more than x{cfg.bone_ratio} at joints {bad}"
    if d.reproj > max_reprojection_px:
        return Reason.IMPLAUSIBLE_HAND, f"3-D hand reprojects {d.reproj:.1f} px from its landmarks (> {max_reprojection_px:.1f})"
    return Reason.OK, ""


def estimate_hands(frames: Iterable[np.ndarray], n_frames: int, intr: Intrinsics, fps: float,
                   cfg: EstimateHandsConfig = EstimateHandsConfig(), detector=None, lifter=None) -> HandEstimate:
    """Estimate both sides' keypoints over a clip's frames (an iterable, read in order).

    ``detector``: a callable rgb -> [(track, HandLandmarks)] (default: MediaPipe from
    ``cfg``); ``lifter``: optional (rgb, HandLandmarks, side) -> (21,3) camera-frame joints
    (the ONNX plug-in); default: ``cfg.depth``."""
    from handedit.models.mediapipe_hands import HandModelFiles, MediaPipeHands

    files = None
    if detector is None:
        files = HandModelFiles.in_dir(cfg.hand_model_dir(), cfg.variant)
        detector = MediaPipeHands(files, cfg.max_hands, cfg.min_detection, cfg.min_presence)
    S = len(SIDES)
    dets: list[_Det] = []
    t = 0
    for rgb in frames:
        for track, lm in detector(rgb):
            d = _Det(t, track, lm.image_xy, lm.world, lm.presence, lm.p_right, lm.rect.box())
            if lifter is not None:  # lifted now, while the frame is at hand (the plug-in flips left crops)
                d.cam = lifter(rgb, lm, int(lm.p_right >= 0.5))
            dets.append(d)
        t += 1
    if t != n_frames:
        raise ValueError(f"estimate_hands read {t} frames, expected {n_frames}")
    side = assign_sides(dets)
    n = n_frames
    raw = np.zeros((n, S, N_JOINTS, 3))
    valid = np.zeros((n, S, N_JOINTS), bool)
    conf = np.zeros((n, S, N_JOINTS), np.float32)
    box = np.zeros((n, S, 4), np.float32)
    pr = np.full((n, S), np.nan, np.float32)
    reproj = np.full((n, S), np.nan, np.float32)
    status = np.full((n, S), Reason.ABSENT, STATUS_DTYPE)
    details: dict[tuple[int, int], str] = {}
    for d in dets:
        k = side[d.track]
        if status[d.frame, k] != Reason.ABSENT:  # a second hand on one side in one frame: keep the first
            continue
        if d.cam is None:
            d.cam = (lift_pnp(d.xy, d.world, intr) if cfg.depth == "pnp" else lift_bones(d.xy, d.world, intr, cfg.hand_scale))[0]
        d.reproj = float(np.linalg.norm(project(d.cam, intr) - d.xy, axis=1).mean())
        raw[d.frame, k] = d.cam
        pr[d.frame, k], box[d.frame, k], reproj[d.frame, k] = d.p_right, d.box, d.reproj
        inside = (d.xy[:, 0] >= 0) & (d.xy[:, 0] < intr.width) & (d.xy[:, 1] >= 0) & (d.xy[:, 1] < intr.height)
        conf[d.frame, k] = np.where(inside, d.presence, 0.0)
        status[d.frame, k], why = judge(d, cfg, cfg.max_reprojection_px * intr.width / 640.0)
        valid[d.frame, k] = status[d.frame, k] == Reason.OK
        if why:
            details[(d.frame, k)] = why
    nothing = (status == Reason.ABSENT).all(axis=1)
    status[nothing] = Reason.NO_HAND_DETECTED
    for i in np.flatnonzero(nothing):
        for k in range(S):
            details[(int(i), k)] = "no hand detected in the frame"
    smooth = raw.copy()
    if cfg.smooth:
        for k in range(S):
            ok = valid[:, k, 0]
            smooth[:, k] = one_euro(raw[:, k], ok, fps, cfg.min_cutoff_hz, cfg.beta)
    raw[~valid], smooth[~valid] = 0.0, 0.0
    method = "mediapipe-hands:" + (cfg.variant if files is None else f"{files.palm.name}+{files.landmark.name}")
    method += "+" + ("onnx-plugin" if lifter is not None else cfg.depth) + ("+one-euro" if cfg.smooth else "")
    stats = {"tracks": len(side), "palm_calls": int(getattr(detector, "palm_calls", -1)),
             "sides": {SIDES[k]: int((status[:, k] == Reason.OK).sum()) for k in range(S)}}
    return HandEstimate(smooth.astype(np.float32), raw.astype(np.float32), valid, conf, box, pr, reproj, status,
                        details, method, stats)
