"""Reference-bank renders: V canonical views (RGB + mask) of one embodiment.

Feeds the benchmark's identity metric and editors' reference images; the frozen text
description travels with it (``Embodiment.description``). Storage is ``storage.bank``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, Field

from handedit.render.views import ELEVATION_DEG, FILL, HFOV_DEG, canonical_views


class BankConfig(BaseModel):
    views: int = Field(4, ge=1, le=64)
    width: int = Field(512, ge=16)
    height: int = Field(512, ge=16)
    seed: int = Field(0, ge=0, description="0: neutral pose; >0: seeded in-limit perturbation")
    decimate: float | None = Field(None, gt=0.0, le=1.0)

    def rig(self) -> dict:
        return {**self.model_dump(), "elevation_deg": ELEVATION_DEG, "hfov_deg": HFOV_DEG, "fill": FILL}


@dataclass
class BankRender:
    rgb: np.ndarray  # (V,H,W,3) uint8, black off the robot
    mask: np.ndarray  # (V,H,W) bool
    camera_from_root: np.ndarray
    qpos: np.ndarray
    K: np.ndarray


def render_bank_views(embodiment_id: str, cfg: BankConfig) -> BankRender:
    from handedit.render.cache import embodiment_renderer

    r = embodiment_renderer(embodiment_id, cfg.width, cfg.height, cfg.decimate)
    rig = canonical_views(r, cfg.views, seed=cfg.seed)
    out = r.render(rig.qpos, rig.camera_from_root, rig.intrinsics)
    return BankRender(out.rgba[..., :3].copy(), out.mask, rig.camera_from_root, rig.qpos, rig.intrinsics.K)
