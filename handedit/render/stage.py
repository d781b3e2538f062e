"""The render stage: an embodiment at joint states -> RGBA, depth and a per-frame status."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from handedit.camera import Intrinsics
from handedit.reasons import Reason


class RenderConfig(BaseModel):
    """Render settings. ``lod_px`` draws each link with no more triangles than its size on screen
    needs (a hand 0.4 m from the head camera is ~100 px across, its meshes 100k-500k faces);
    ``decimate`` simplifies every dense mesh whatever its size on screen (bench/render.py)."""

    model_config = ConfigDict(extra="forbid")

    VERSION: ClassVar[int] = 7  # 3: decimate only simplifies dense meshes, silhouette-checked; 4: stalled passes retried; 5: robot_arm;
    # 6: decimated meshes keep their creases (model.DECIMATE_CREASE_DEG); 7: levels of detail (lod_px), decimated
    # meshes without seams shade smooth
    decimate: float | None = Field(None, gt=0.0, le=1.0, description="fraction of faces kept")
    lod_px: float | None = Field(
        1.0, gt=0.0, description="levels of detail: each link drawn at the coarsest level whose outline moves at most "
        "this many pixels (RobotRenderer); None: the full meshes always")
    min_visible_pixels: int = Field(20, ge=0, description="fewer robot pixels than this -> EMPTY_RENDER")
    materials: dict[str, tuple[float, float, float, float]] | None = Field(
        None, description="link regex -> display RGBA in [0,1], tried before the roster's colours"
    )


@dataclass
class RenderStageResult:
    rgba: np.ndarray  # (n,H,W,4) uint8: every side's robot, nearest surface per pixel
    depth: np.ndarray  # (n,H,W) float32
    robot_side: np.ndarray  # (n,H,W) uint8: 0 no robot, k+1 the robot of hand k
    robot_arm: np.ndarray  # (n,H,W) bool: the visible robot surface is an arm link (hand-arm; else all False)
    hand_status: np.ndarray  # (n,S) int16
    status: np.ndarray  # (n,) int16 (OK where any side rendered)
    method: str


def render_stage(embodiment_id: str, qpos: np.ndarray, root_pose: np.ndarray, ready: np.ndarray, sides: tuple[str, ...],
                 intr: Intrinsics, cfg: RenderConfig) -> RenderStageResult:
    """Both robots in one frame: each side rendered with its URDF (left: the mirrored one),
    then merged by depth, so the nearer robot occludes the other exactly per pixel.

    qpos (n,S,dof), root_pose (n,S,4,4), ready (n,S): sides to render (others UPSTREAM)."""
    from handedit.render import embodiment_renderer  # deferred: pyrender/EGL only where rendering happens
    from handedit.reasons import per_frame

    n, S = np.asarray(ready).shape
    H, W = intr.height, intr.width
    rgba = np.zeros((n, H, W, 4), np.uint8)
    depth = np.zeros((n, H, W), np.float32)
    side_of = np.zeros((n, H, W), np.uint8)
    arm = np.zeros((n, H, W), bool)
    hs = np.full((n, S), Reason.UPSTREAM, np.int16)
    for k, side in enumerate(sides):
        idx = np.flatnonzero(ready[:, k])
        if not idx.size:
            continue
        renderer = embodiment_renderer(embodiment_id, W, H, decimate=cfg.decimate, materials=cfg.materials, side=side,
                                       lod_px=cfg.lod_px)
        visible = np.zeros(len(idx), np.int64)
        for j, (i, crop) in enumerate(zip(idx, renderer.crops(qpos[idx, k], root_pose[idx, k], intr))):
            box = crop.slices  # nothing of this side lies outside its box
            d, dd = crop.depth, depth[i][box]
            m = (d > 0) & ((dd <= 0) | (d < dd))  # this side's surface is the nearer one
            np.copyto(rgba[i][box], crop.rgba, where=m[..., None])
            np.copyto(dd, d, where=m)
            np.copyto(side_of[i][box], k + 1, where=m)
            if crop.arm is not None:
                np.copyto(arm[i][box], crop.arm, where=m)
            visible[j] = np.count_nonzero(crop.rgba[..., 3])
        hs[idx, k] = np.where(visible >= cfg.min_visible_pixels, Reason.OK, Reason.EMPTY_RENDER)
    method = (f"pyrender:egl{'' if cfg.decimate is None else f':decimate={cfg.decimate}'}"
              f"{'' if cfg.lod_px is None else f':lod_px={cfg.lod_px}'}")
    return RenderStageResult(rgba, depth, side_of, arm, hs, per_frame(hs), method)
