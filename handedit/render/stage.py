"""The render stage: an embodiment at joint states -> RGBA, depth and a per-frame status."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from pydantic import BaseModel, Field

from handedit.camera import Intrinsics
from handedit.reasons import Reason


class RenderConfig(BaseModel):
    """Render settings; ``decimate`` trades mesh detail for speed (bench/render.py)."""

    VERSION: ClassVar[int] = 3  # 3: decimate only simplifies dense meshes, silhouette-checked
    decimate: float | None = Field(None, gt=0.0, le=1.0, description="fraction of faces kept")
    min_visible_pixels: int = Field(20, ge=0, description="fewer robot pixels than this -> EMPTY_RENDER")
    materials: dict[str, tuple[float, float, float, float]] | None = Field(
        None, description="link regex -> display RGBA in [0,1], tried before the roster's colours"
    )


@dataclass
class RenderStageResult:
    rgba: np.ndarray  # (n,H,W,4) uint8
    depth: np.ndarray  # (n,H,W) float32
    status: np.ndarray  # (n,) int16
    method: str


def render_stage(embodiment_id: str, qpos: np.ndarray, root_pose: np.ndarray, intr: Intrinsics, cfg: RenderConfig) -> RenderStageResult:
    from handedit.render import render_embodiment  # deferred: pyrender/EGL only where rendering happens

    out = render_embodiment(embodiment_id, qpos, root_pose, intr, decimate=cfg.decimate, materials=cfg.materials)
    visible = (out.rgba[..., 3] > 0).reshape(len(qpos), -1).sum(axis=1)
    status = np.where(visible >= cfg.min_visible_pixels, Reason.OK, Reason.EMPTY_RENDER).astype(np.int16)
    method = f"pyrender:egl{'' if cfg.decimate is None else f':decimate={cfg.decimate}'}"
    return RenderStageResult(out.rgba, out.depth, status, method)
