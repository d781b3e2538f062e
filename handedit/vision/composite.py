"""Composite the rendered robot over the restored background, respecting occluders.

Why: the pseudo-GT must show the robot exactly where the renderer put it, except where
the manipulated object is in front of it (the paper rejects "incorrect occlusion").
With per-pixel depth for both, the nearer surface wins; with only an occluder mask the
caller decides (``occluder_in_front_without_depth``) because a mask alone cannot say
who is in front. Occluded pixels keep the background bit-exactly. Edges are softened by
an inward feather (alpha times its own blur), which never spreads robot colour outside
the rendered silhouette or into occluded pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

import cv2
import numpy as np
import pydantic

from handedit.reasons import STATUS_DTYPE, Reason


class CompositeConfig(pydantic.BaseModel):
    VERSION: ClassVar[int] = 1
    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    method: Literal["classical"] = "classical"
    feather_px: float = pydantic.Field(1.0, ge=0)  # Gaussian sigma of the edge feather; 0 = hard edges
    depth_tolerance: float = pydantic.Field(0.005, ge=0)  # metres: occluder must be this much nearer
    occluder_in_front_without_depth: bool = False  # occluder mask without depth: occludes the robot?
    premultiplied: bool = False  # rgba colour already multiplied by alpha
    min_visible_px: int = pydantic.Field(1, ge=1)  # fewer visible robot pixels -> EMPTY_RENDER


@dataclass
class CompositeResult:
    image: np.ndarray  # (n,H,W,3) uint8
    robot_mask: np.ndarray  # (n,H,W) bool: visible robot pixels (alpha >= 0.5, not occluded)
    status: np.ndarray  # (n,) int16 Reason
    method: str


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
    robot_depth: np.ndarray,
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
    od = np.asarray(occluder_depth, np.float32)
    rd = _robot_depth_at_edges(np.asarray(robot_depth, np.float32), alpha)
    has_od = od > 0
    # no robot depth at an alpha pixel (even after borrowing): the occluder wins
    return occ & (~has_od & cfg.occluder_in_front_without_depth | has_od & ((rd <= 0) | (od < rd - cfg.depth_tolerance)))


def composite(
    background: np.ndarray,
    rgba: np.ndarray,
    depth: np.ndarray,
    occluder_mask: np.ndarray | None = None,
    occluder_depth: np.ndarray | None = None,
    cfg: CompositeConfig = CompositeConfig(),
) -> CompositeResult:
    """Alpha-composite robot renders over backgrounds (arrays per frame along axis 0)."""
    if cfg.method != "classical":
        raise ValueError(f"composite: unknown method {cfg.method!r}; this build has 'classical'")
    background = np.asarray(background)
    rgba = np.asarray(rgba)
    n, H, W = background.shape[:3]
    if background.shape != (n, H, W, 3) or rgba.shape != (n, H, W, 4) or np.shape(depth) != (n, H, W):
        raise ValueError(
            f"composite: background (n,H,W,3), rgba (n,H,W,4), depth (n,H,W); got {background.shape}, {rgba.shape}, {np.shape(depth)}"
        )
    image = np.empty_like(background)
    robot_mask = np.zeros((n, H, W), bool)
    status = np.full(n, Reason.OK, STATUS_DTYPE)
    for i in range(n):
        a = rgba[i, ..., 3].astype(np.float32) / 255.0
        occ = occlusion_mask(
            depth[i], a,
            None if occluder_mask is None else occluder_mask[i],
            None if occluder_depth is None else occluder_depth[i],
            cfg,
        )
        vis = np.where(occ, 0.0, a).astype(np.float32)
        robot_mask[i] = vis >= 0.5
        if cfg.feather_px > 0:
            soft = vis * cv2.GaussianBlur(vis, (0, 0), cfg.feather_px)
        else:
            soft = vis
        fg = rgba[i, ..., :3].astype(np.float32)
        if cfg.premultiplied:  # un-premultiply so the feathered alpha applies to true colour
            fg = np.where(a[..., None] > 0, fg / np.maximum(a[..., None], 1e-6), 0.0)
        bg = background[i].astype(np.float32)
        out = soft[..., None] * fg + (1.0 - soft[..., None]) * bg
        img = np.clip(np.round(out), 0, 255).astype(np.uint8)
        keep = soft <= 0  # exactly the background where no robot contributes (incl. occluded)
        img[keep] = background[i][keep]
        image[i] = img
        if int(robot_mask[i].sum()) < cfg.min_visible_px:
            status[i] = Reason.EMPTY_RENDER
    return CompositeResult(image, robot_mask, status, "classical:alpha-over+depth-occlusion")
