"""Composite the rendered robots over the restored background, respecting occluders.

Why: the pseudo-GT must show each robot exactly where the renderer put it, except where
the manipulated object is in front of it (the paper rejects "incorrect occlusion").
Hands: restoration removed every hand; a hand whose robot is not drawn (its side failed
upstream) gets its own source pixels back (inside its dilated human mask), so a frame
never loses a hand it had: the pseudo-GT shows a robot where a side succeeded and the
human hand where it did not (what "kept" means then is the QC stage's keep policy).

Residue check (``HUMAN_VISIBLE``, per replaced side): human fingers left visible beside
the robot, where segmentation missed part of the hand. The side's registered finger
bones (sampled between its projected joints) should all lie in its human mask, which
restoration removed; a sample outside the mask (grown by 2 px), not covered by any robot,
whose colour in the composite matches *this hand* (a Gaussian of its source pixels along
the bones, against one of the scene around the hand) is visible human. More than
``residue_threshold`` of the finger samples visible rejects the side. Calibrated on the
real EgoDex clips (tests/test_egodex_curate.py): finger pixels the mask left out (its
erosion by a third of a finger's width) are flagged, the pipeline's own composites of
fully removed hands pass.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

import cv2
import numpy as np
import pydantic

from handedit.images import pixels
from handedit.keypoints import N_JOINTS, PARENT, WRIST
from handedit.reasons import STATUS_DTYPE, Reason, per_frame
from handedit.metrics.similarity import bbox
from handedit.vision.arm import CORRIDOR_FRAC, MAX_HAND_HIDDEN, MAX_OFF_ARM
from handedit.vision.masks import disk, grow
from handedit.vision.occluder import OccluderConfig
from handedit.vision.restore_background import restored_residue
from handedit.vision.skin import colour_loglik


class CompositeConfig(pydantic.BaseModel):
    VERSION: ClassVar[int] = 6  # 3: off-arm check; 4: residue; 5: image_occluder (what hid the fingers, opt-in); 6: hand hidden
    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    method: Literal["classical"] = "classical"
    feather_px: float = pydantic.Field(1.0, ge=0)  # Gaussian sigma of the edge feather; 0 = hard edges
    depth_tolerance: float = pydantic.Field(0.005, ge=0)  # metres: occluder must be this much nearer
    occluder_in_front_without_depth: bool = False  # occluder mask without depth: occludes the robot?
    premultiplied: bool = False  # rgba colour already multiplied by alpha
    min_visible_px: int = pydantic.Field(1, ge=1)  # fewer visible robot pixels -> EMPTY_RENDER
    paste_dilate_px: int = pydantic.Field(6, ge=0)  # a kept human hand comes back over its mask grown by this
    residue_threshold: float = pydantic.Field(0.05, description="share of finger samples visible as human -> HUMAN_VISIBLE")
    restored_residue_threshold: float = pydantic.Field(
        0.25, ge=0, le=1, description="skin-coloured share of the restored pixels left visible (above their surroundings' "
        "share) -> RESIDUE (restoration's check, judged where no robot covers the hole)")
    max_off_arm: float = pydantic.Field(MAX_OFF_ARM, ge=0, le=1, description="hand-arm: share of a robot's pixels outside the "
                                        "human arm's corridor (handedit.vision.arm) above which -> OFF_ARM")
    arm_corridor_frac: float = pydantic.Field(CORRIDOR_FRAC, ge=0, description="the corridor grows by this share of the image width")
    max_hand_hidden: float = pydantic.Field(MAX_HAND_HIDDEN, ge=0, le=1, description="hand-arm: share of a human hand's pixels "
                                            "that show a robot arm link (the robot's hand hidden behind an arm) above which "
                                            "-> HAND_HIDDEN")
    image_occluder: OccluderConfig | None = pydantic.Field(None, description=(
        "a source without an object mesh or mask: what hid the human fingers (handedit.vision.occluder) is drawn in "
        "front of the robot. Off by default: on the synthetic grasps (true masks) it finds the held object, but on the "
        "EgoDex clips most of what it finds is the hand's own fingers the mask left out, and their pixels in front of "
        "the robot reject 16 more frame-sides of 128 (HUMAN_VISIBLE)"))


@dataclass
class CompositeResult:
    image: np.ndarray  # (n,H,W,3) uint8
    robot_mask: np.ndarray  # (n,S,H,W) bool: visible robot pixels of each side (alpha >= 0.5, not occluded)
    hand_status: np.ndarray  # (n,S) int16 Reason
    status: np.ndarray  # (n,) int16 Reason
    method: str
    residue: np.ndarray | None = None  # (n,S) float32: the residue statistic (nan where not measured)
    restored_residue: np.ndarray | None = None  # (n,) bool: skin left in the restored pixels no robot covers (RESIDUE)

    @property
    def union(self) -> np.ndarray:
        """(n,H,W) every side's visible robot pixels (what harmonization adjusts)."""
        return self.robot_mask.any(axis=1)


def _robot_depth_at_edges(depth: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Anti-aliased edge pixels may carry alpha but no depth: borrow the farthest neighbour's.

    Farthest (max) errs towards the occluder winning, which is the safe side.
    """
    missing = (alpha > 0) & (depth <= 0)
    if not missing.any():
        return depth
    grown = cv2.dilate(depth, np.ones((3, 3), np.uint8))
    out = depth.copy()
    out[missing] = grown[missing]
    return out


def occlusion_mask(
    robot_depth: np.ndarray | None,
    alpha: np.ndarray,
    occluder_mask: np.ndarray | None,
    occluder_depth: np.ndarray | None,
    cfg: CompositeConfig,
) -> np.ndarray:
    """(H,W) bool: pixels where the occluder hides the robot."""
    if occluder_mask is None:
        return np.zeros(alpha.shape, bool)
    occ = np.asarray(occluder_mask, bool)
    if occluder_depth is None:
        return occ.copy() if cfg.occluder_in_front_without_depth else np.zeros(alpha.shape, bool)
    if robot_depth is None:
        raise ValueError("composite: an occluder with depth needs the robot's depth")
    od = np.asarray(occluder_depth, np.float32)
    rd = _robot_depth_at_edges(np.asarray(robot_depth, np.float32), alpha)
    has_od = od > 0
    # no robot depth at an alpha pixel (even after borrowing): the occluder wins
    return occ & (~has_od & cfg.occluder_in_front_without_depth | has_od & ((rd <= 0) | (od < rd - cfg.depth_tolerance)))


def _bone_samples(pts: np.ndarray, valid: np.ndarray, per_bone: int = 8) -> np.ndarray:
    """(m,2) points along the finger bones (joints 1-20 and their parents)."""
    out = []
    t = np.linspace(0.15, 1.0, per_bone)[:, None]
    for j in range(1, N_JOINTS):
        p = PARENT[j]
        if p != WRIST and valid[j] and valid[p]:
            out.append(pts[p] + t * (pts[j] - pts[p]))
    return np.concatenate(out) if out else np.zeros((0, 2))


def human_residue(image: np.ndarray, source: np.ndarray, human: np.ndarray, robot: np.ndarray,
                  keypoints_2d: np.ndarray, keypoints_valid: np.ndarray) -> float:
    """The residue statistic of one side (see module doc); nan when it cannot be measured."""
    H, W = human.shape
    pts = _bone_samples(np.asarray(keypoints_2d, float), np.asarray(keypoints_valid, bool))
    area = int(human.sum())
    if len(pts) < 8 or area < 30:
        return float("nan")
    q = np.round(pts).astype(int)
    q = q[(q[:, 0] >= 0) & (q[:, 0] < W) & (q[:, 1] >= 0) & (q[:, 1] < H)]
    if len(q) < 8:
        return float("nan")
    scale = float(np.sqrt(area))
    r_out, r_in = max(1, int(round(0.5 * scale))), max(1, int(round(0.15 * scale)))
    ys, xs = bbox(human, r_out + 1)  # every neighbourhood below stays inside it
    h8 = human[ys, xs].astype(np.uint8)
    grown_w = cv2.dilate(h8, disk(2)).astype(bool)
    grown = np.zeros((H, W), bool)
    grown[ys, xs] = grown_w
    on_hand = q[grown[q[:, 1], q[:, 0]]]
    # the scene ring, r_in < distance to the hand <= r_out (one exact distance transform: a
    # dilation by a hand-arm-sized disk costs tens of ms)
    d = cv2.distanceTransform(1 - h8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    ring = (d <= r_out) & (d > r_in) & ~robot[ys, xs]
    if len(on_hand) < 8 or ring.sum() < 30:
        return float("nan")

    def ycrcb(rgb: np.ndarray) -> np.ndarray:  # per pixel, so only the pixels used are converted
        return cv2.cvtColor(np.ascontiguousarray(rgb.reshape(-1, 1, 3)), cv2.COLOR_RGB2YCrCb).reshape(-1, 3).astype(np.float32)

    hand_px = ycrcb(source[on_hand[:, 1], on_hand[:, 0]])
    ry, rx = np.nonzero(ring)
    pick = np.random.default_rng(0).choice(len(ry), min(len(ry), 4000), replace=False)  # converted: only those drawn
    scene_px = ycrcb(source[ys, xs][ry[pick], rx[pick]])
    out = q[~grown[q[:, 1], q[:, 0]] & ~robot[q[:, 1], q[:, 0]]]
    if not len(out):
        return 0.0
    x = ycrcb(image[out[:, 1], out[:, 0]])
    hand_like = colour_loglik(x, hand_px, 16.0) > colour_loglik(x, scene_px, 16.0)
    return float(hand_like.sum() / len(q))


def robot_windows(rgba: np.ndarray, cfg: CompositeConfig) -> list[tuple[slice, slice] | None]:
    """Per frame, the box of every rendered pixel grown by the feather's reach (the radius of
    cv2's float Gaussian kernel): all that compositing changes, and all of the occluder it
    reads (the drawn sides' pixels are a subset); None where nothing is rendered."""
    reach = max(1, (int(round(cfg.feather_px * 8 + 1)) | 1) // 2)
    H, W = rgba.shape[1:3]
    out = []
    for frame in rgba:
        x, y, w, h = cv2.boundingRect(cv2.extractChannel(frame, 3))  # of the non-zero alpha; (0,0,0,0) when none
        out.append(None if w == 0 else (slice(max(0, y - reach), min(H, y + h + reach)),
                                        slice(max(0, x - reach), min(W, x + w + reach))))
    return out


def composite(
    background: np.ndarray,
    rgba: np.ndarray,
    depth: np.ndarray | None,
    occluder_mask: np.ndarray | None = None,
    occluder_depth: np.ndarray | None = None,
    cfg: CompositeConfig = CompositeConfig(),
    *,
    robot_side: np.ndarray | None = None,
    replace: np.ndarray | None = None,
    source: np.ndarray | None = None,
    human_mask: np.ndarray | None = None,
    keypoints_2d: np.ndarray | None = None,
    keypoints_valid: np.ndarray | None = None,
    windows: list[tuple[slice, slice] | None] | None = None,
    out: np.ndarray | None = None,
    hole: np.ndarray | None = None,
) -> CompositeResult:
    """Alpha-composite robot renders over backgrounds (arrays per frame along axis 0).

    ``depth`` (n,H,W): the robot's, needed only with an ``occluder_depth`` (else None).

    ``robot_side`` (n,H,W) uint8: which hand's robot each rendered pixel is (0: none; None:
    one robot, side 0). ``replace`` (n,S) bool: sides whose robot is drawn (default: all).
    ``source`` (n,H,W,3) and ``human_mask`` (n,S,H,W): the source frames and each hand's
    human mask, for pasting back hands that are not replaced; ``keypoints_2d`` (n,S,21,2)
    and ``keypoints_valid`` (n,S,21): the registered joints, for the residue check.
    ``windows``: ``robot_windows(rgba, cfg)`` when the caller has them already. ``out``: where
    the composites go (may be ``background`` itself, which is then overwritten: no copy).
    ``hole`` (n,H,W): the pixels restoration filled; its skin-coloured residue is judged on
    the part no robot (rendered alpha) and no pasted-back hand covers (``RESIDUE``).
    """
    if cfg.method != "classical":
        raise ValueError(f"composite: unknown method {cfg.method!r}; this build has 'classical'")
    background = np.asarray(background)
    rgba = np.asarray(rgba)
    n, H, W = background.shape[:3]
    if background.shape != (n, H, W, 3) or rgba.shape != (n, H, W, 4) or depth is not None and np.shape(depth) != (n, H, W):
        raise ValueError(
            f"composite: background (n,H,W,3), rgba (n,H,W,4), depth (n,H,W); got {background.shape}, {rgba.shape}, {np.shape(depth)}"
        )
    S = replace.shape[1] if replace is not None else (human_mask.shape[1] if human_mask is not None else 1)
    replace = np.ones((n, S), bool) if replace is None else np.asarray(replace, bool)
    side_of = np.where(rgba[..., 3] > 0, 1, 0).astype(np.uint8) if robot_side is None else np.asarray(robot_side)
    image = np.empty_like(background) if out is None else out
    robot_mask = np.zeros((n, S, H, W), bool)
    hs = np.where(replace, Reason.OK, Reason.UPSTREAM).astype(STATUS_DTYPE)
    residue = np.full((n, S), np.nan, np.float32)
    restored = np.zeros(n, bool)
    windows = robot_windows(rgba, cfg) if windows is None else windows
    for i in range(n):
        bg = background[i]
        if hole is not None and replace[i].any() and hole[i].any():  # judged before ``out`` overwrites it
            covered = rgba[i, ..., 3] > 0
            if human_mask is not None:
                covered = covered | human_mask[i, ~replace[i]].any(axis=0)
            restored[i] = restored_residue(bg, hole[i], cfg.restored_residue_threshold, ~covered)
        if human_mask is not None and source is not None and (~replace[i]).any():
            keep = np.zeros((H, W), bool)
            for k in np.flatnonzero(~replace[i]):
                keep |= human_mask[i, k]
            if keep.any():
                keep = grow(keep, cfg.paste_dilate_px) if cfg.paste_dilate_px else keep
                bg = bg.copy()
                pixels(bg)[keep] = pixels(source[i])[keep]
        img = image[i]
        if not np.may_share_memory(img, bg):
            img[...] = bg  # exactly the background wherever no robot contributes
        visible = np.zeros((H, W), bool)
        n_visible = np.zeros(S, np.int64)
        if windows[i] is not None:
            ys, xs = windows[i]
            side = side_of[i][ys, xs]
            drawn = np.zeros(256, np.uint8)  # 255 for the labels of the sides drawn
            drawn[np.flatnonzero(replace[i]) + 1] = 255
            # alpha in [0, 1] where a drawn side's robot is, else 0
            a = np.multiply(cv2.bitwise_and(cv2.extractChannel(rgba[i, ys, xs], 3), cv2.LUT(side, drawn)), np.float32(1 / 255),
                            dtype=np.float32)
            occ = occlusion_mask(
                None if depth is None else depth[i][ys, xs], a,
                None if occluder_mask is None else occluder_mask[i][ys, xs],
                None if occluder_depth is None else occluder_depth[i][ys, xs],
                cfg,
            )
            vis = np.where(occ, np.float32(0), a)
            seen = vis >= 0.5
            visible[ys, xs] = seen
            for k in range(S):
                robot_mask[i, k, ys, xs] = mine = seen & (side == k + 1)
                n_visible[k] = np.count_nonzero(mine)
            soft = vis * cv2.GaussianBlur(vis, (0, 0), cfg.feather_px) if cfg.feather_px > 0 else vis
            fg = cv2.cvtColor(rgba[i, ys, xs], cv2.COLOR_RGBA2RGB)
            if cfg.premultiplied:  # un-premultiply so the feathered alpha applies to true colour
                fg = np.clip(np.round(np.where(a[..., None] > 0, fg / np.maximum(a[..., None], 1e-6), 0)), 0, 255).astype(np.uint8)
            # soft * fg + (1 - soft) * bg, rounded; exactly bg where soft is 0 (incl. occluded pixels)
            img[ys, xs] = cv2.blendLinear(fg, np.ascontiguousarray(bg[ys, xs]), soft, 1 - soft)
        for k in np.flatnonzero(replace[i]):
            if n_visible[k] < cfg.min_visible_px:
                hs[i, k] = Reason.EMPTY_RENDER
            elif human_mask is not None and source is not None and keypoints_2d is not None:
                residue[i, k] = human_residue(img, source[i], human_mask[i, k], visible, keypoints_2d[i, k], keypoints_valid[i, k])
                if residue[i, k] > cfg.residue_threshold:
                    hs[i, k] = Reason.HUMAN_VISIBLE
        if restored[i]:
            hs[i][(hs[i] == Reason.OK) & replace[i]] = Reason.RESIDUE
    method = "classical:alpha-over+depth-occlusion" + ("+paste-back+residue" if human_mask is not None else "")
    return CompositeResult(image, robot_mask, hs, per_frame(hs), method, residue, restored if hole is not None else None)
