"""What was in front of the human fingers, from the image: the occluder of a source without an object mesh.

Why: EgoDex (and any video) has no object geometry, so the robot used to be drawn over a
held object that hid the human fingers (the paper's "incorrect occlusion"). The hand's
keypoints, registered to the pixels, say where every finger bone is even where the finger
is hidden; where a bone's footprint lies outside the hand's mask, something in front of the
finger hid it there. Those pixels are the occluder: the robot is drawn behind them, so what
hid the human finger hides the robot's. Only what hid a finger is found (an object beside
the hand occludes nothing of the robot's that a human finger occupied): the robot's fingers
are where the human's were, give or take their size. With the frames, a hidden pixel that
looks like this hand rather than like the scene around it is a finger the mask missed, not
an occluder (composite's residue check judges those, by the same colour test).
"""

from __future__ import annotations

import cv2
import numpy as np
import pydantic

from handedit.camera import Intrinsics, project
from handedit.keypoints import PARENT, WRIST
from handedit.vision.masks import grow
from handedit.vision.skin import colour_loglik, to_ycrcb


class OccluderConfig(pydantic.BaseModel):
    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    finger_radius_m: float = pydantic.Field(0.008, gt=0, description="a finger's radius: each bone's footprint")
    mask_slack: float = pydantic.Field(0.5, ge=0, description=(
        "the hand mask grows by this many finger radii before a footprint pixel counts as hidden: a mask edge or "
        "a registration error of a few pixels is not an occluder"))
    min_share: float = pydantic.Field(0.25, ge=0, le=1, description=(
        "a bone counts as hidden only where at least this share of its footprint lies outside the grown mask (a "
        "fingertip a few pixels past the mask is not hidden)"))


def _bones(kp: np.ndarray, uv: np.ndarray, ok: np.ndarray, intr: Intrinsics, shape: tuple[int, int], radius_m: float):
    """Each tracked finger bone's footprint (bool (H,W)) of one hand: a line as wide as the finger at
    the bone's depth. ``kp`` (21,3) camera frame, ``uv`` (21,2) projected, ``ok`` (21,) usable."""
    for j, p in enumerate(PARENT):
        if p < 0 or p == WRIST or not (ok[j] and ok[p]):
            continue  # finger bones only: the palm's are the mask's own core
        bone = np.zeros(shape, np.uint8)
        r = max(1, int(round(intr.fx * radius_m / (0.5 * (kp[p, 2] + kp[j, 2])))))
        cv2.line(bone, tuple(int(v) for v in np.round(uv[p])), tuple(int(v) for v in np.round(uv[j])), 1, thickness=2 * r)
        yield bone.astype(bool)


def _usable(kp: np.ndarray, valid: np.ndarray, uv: np.ndarray) -> np.ndarray:
    return np.asarray(valid, bool) & (kp[:, 2] > 0.05) & np.isfinite(uv).all(-1)


def finger_footprint(keypoints: np.ndarray, valid: np.ndarray, intr: Intrinsics, shape: tuple[int, int],
                     cfg: OccluderConfig = OccluderConfig()) -> np.ndarray:
    """(n,H,W) bool: where the hands' finger bones are, visible or hidden (the region an occluder of the
    fingers lies in; the measure's truth is the object's pixels there)."""
    kp = np.asarray(keypoints, float)
    uv = project(kp, intr)
    out = np.zeros((len(kp), *shape), bool)
    for i, s in np.ndindex(*kp.shape[:2]):
        for foot in _bones(kp[i, s], uv[i, s], _usable(kp[i, s], valid[i, s], uv[i, s]), intr, shape, cfg.finger_radius_m):
            out[i] |= foot
    return out


def hidden_fingers(keypoints: np.ndarray, valid: np.ndarray, hand_mask: np.ndarray, intr: Intrinsics,
                   cfg: OccluderConfig = OccluderConfig(), frames: np.ndarray | None = None) -> np.ndarray:
    """(n,H,W) bool: pixels where a finger bone of some hand lies outside its mask (the occluder).

    ``keypoints`` (n,S,21,3) camera frame (metres), ``valid`` (n,S,21), ``hand_mask``
    (n,S,H,W) each hand's mask, ``intr`` at the masks' resolution; ``frames`` (n,H,W,3) RGB:
    leave out the hidden pixels coloured like the hand (see the module doc).
    """
    kp = np.asarray(keypoints, float)
    n, S, H, W = np.shape(hand_mask)
    out = np.zeros((n, H, W), bool)
    uv = project(kp, intr)
    for i, s in np.ndindex(n, S):
        ok = _usable(kp[i, s], valid[i, s], uv[i, s])
        if not ok[WRIST] or not hand_mask[i, s].any():
            continue
        r_px = intr.fx * cfg.finger_radius_m / np.median(kp[i, s, ok, 2])
        free = ~grow(hand_mask[i, s], max(1.0, cfg.mask_slack * r_px))
        found = np.zeros((H, W), bool)
        for foot in _bones(kp[i, s], uv[i, s], ok, intr, (H, W), cfg.finger_radius_m):
            hidden = foot & free
            if foot.any() and hidden.sum() >= cfg.min_share * foot.sum():
                found |= hidden
        if frames is not None and found.any():
            found &= ~_hand_coloured(frames[i], hand_mask[i, s], found, r_px)
        out[i] |= found
    return out


def _hand_coloured(frame: np.ndarray, hand: np.ndarray, pixels: np.ndarray, r_px: float) -> np.ndarray:
    """(H,W) bool: which of ``pixels`` are more likely under a colour model of this hand (its
    mask's pixels) than under one of the scene around it (a ring 2-6 finger radii out), YCrCb."""
    ring = grow(hand, 6 * r_px) & ~grow(hand, 2 * r_px)
    out = np.zeros(hand.shape, bool)
    if hand.sum() < 30 or ring.sum() < 30:
        return out
    rng = np.random.default_rng(0)

    def ycrcb(mask: np.ndarray, limit: int | None = 4000) -> np.ndarray:
        ys, xs = np.nonzero(mask)
        if limit is not None and len(ys) > limit:
            keep = rng.choice(len(ys), limit, replace=False)
            ys, xs = ys[keep], xs[keep]
        return to_ycrcb(frame[ys, xs].reshape(-1, 1, 3)).reshape(-1, 3).astype(np.float32)

    x = ycrcb(pixels, None)
    out[pixels] = colour_loglik(x, ycrcb(hand), 16.0) > colour_loglik(x, ycrcb(ring), 16.0)
    return out
