"""Colour harmonization of the composited robot towards its surroundings.

Why: the robot is rendered under a generic light and pasted into a real scene, so its
colour cast, brightness and contrast differ from the scene's (the paper's learned
Harmonizer fixes exactly this). The classical stand-in is a Reinhard-style statistics
transfer in CIE Lab: the robot region's per-channel mean and spread move towards those
of a ring of surrounding pixels, by ``strength`` in [0, 1] (0 = no change; 1 = full
transfer, which would also wash out the robot's own albedo, hence the default 0.35).
Only pixels of the slightly dilated robot mask change, with a weight that fades to 0
over the dilation band, so geometry (the silhouette and everything outside it) never
moves.

``method="onnx"`` with ``model_path`` runs a learned harmonizer instead
(``handedit.models.harmonizer``: contract and export notes), blended in over the same
dilated robot mask so geometry still never moves.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

import cv2
import numpy as np
import pydantic

from handedit.models.runtime import OnnxRuntime
from handedit.images import pixel_row, pixels
from handedit.reasons import STATUS_DTYPE, Reason
from handedit.metrics.similarity import bbox


_MIN_STAT_PX = 200  # robot / ring pixels the subsampled statistics need


class HarmonizeConfig(pydantic.BaseModel):
    VERSION: ClassVar[int] = 5  # 3: ring and edge weight from one distance transform; 4: statistics on every other pixel; 5: one affine map and blend (round-to-nearest)
    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    method: Literal["classical", "onnx"] = "classical"
    model_path: str | None = None  # ONNX harmonizer (method="onnx"), see handedit.models.harmonizer
    onnx: OnnxRuntime = OnnxRuntime()  # how the model runs (providers, threads): part of the key
    work_max_side: int = pydantic.Field(1024, ge=32)  # model input size when the model's is dynamic
    strength: float = pydantic.Field(0.35, ge=0.0, le=1.0)
    match_std: bool = True  # also move the spread (contrast), not just the mean
    std_ratio_limits: tuple[float, float] = (0.5, 2.0)  # clamp on the spread ratio
    ring_px: int = pydantic.Field(25, ge=1)  # width of the surrounding ring the statistics come from
    edge_px: int = pydantic.Field(2, ge=0)  # dilation of the robot mask; the weight fades over it
    min_ring_px: int = 50  # fewer ring pixels: fall back to the whole non-robot image

    @pydantic.model_validator(mode="after")
    def _model_needs_path(self) -> "HarmonizeConfig":
        if self.method == "onnx" and not self.model_path:
            raise ValueError("harmonize: method='onnx' needs model_path (an ONNX harmonizer)")
        return self


@dataclass
class HarmonizeResult:
    image: np.ndarray  # (n,H,W,3) uint8
    status: np.ndarray  # (n,) int16 Reason
    method: str


def _to_lab(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.divide(rgb, np.float32(255), dtype=np.float32), cv2.COLOR_RGB2Lab)


def _from_lab(lab: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(lab.astype(np.float32), cv2.COLOR_Lab2RGB) * 255.0


def harmonize_frame(image: np.ndarray, robot_mask: np.ndarray, cfg: HarmonizeConfig, out: np.ndarray | None = None) -> np.ndarray | None:
    """One frame, into ``out`` (a copy of ``image`` when None; ``image`` itself is fine); None
    when the robot mask is empty. Works in the robot's box grown by the ring
    (``handedit.metrics.similarity.bbox``), the whole frame only when the ring is too small."""
    mask = np.asarray(robot_mask, bool)
    win = bbox(mask, cfg.edge_px + cfg.ring_px + 1)
    if win is None:
        return None
    out = image.copy() if out is None else out
    if not _harmonize_in(image[win], mask[win], cfg, False, out[win]):
        # too few ring pixels around the robot: the statistics come from the whole frame
        _harmonize_in(image, mask, cfg, True, out)
    return out


def _harmonize_in(image: np.ndarray, mask: np.ndarray, cfg: HarmonizeConfig, fallback_ok: bool, out: np.ndarray) -> bool:
    """Over the window, written into ``out`` (False, nothing written, when the ring is too
    small and ``fallback_ok`` is not set): one exact distance to the robot gives the dilated
    region, the ring and the edge weight (a dilation by the ring's disk cost more than the
    rest together). Only the pixels used are converted to Lab: the robot's and the ring's
    on every other pixel for the statistics (all pixels when that leaves fewer than
    ``_MIN_STAT_PX``), then the region's, which one affine map (``cv2.transform``) and the
    edge weight's blend change."""
    m8 = mask.astype(np.uint8)
    dist = cv2.distanceTransform(1 - m8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    region = dist <= cfg.edge_px
    ring = (dist <= cfg.edge_px + cfg.ring_px) & ~region
    if cv2.countNonZero(ring.view(np.uint8)) < cfg.min_ring_px:
        if not fallback_ok:
            return False
        ring = ~region
    if not ring.any() or cfg.strength == 0:
        return True
    step = 2
    robot_s, ring_s = mask[::step, ::step], ring[::step, ::step]
    if min(np.count_nonzero(robot_s), np.count_nonzero(ring_s)) < _MIN_STAT_PX:
        step, robot_s, ring_s = 1, mask, ring
    sub = pixels(image[::step, ::step])
    mu_s, sd_s = (v.ravel() for v in cv2.meanStdDev(_to_lab(pixel_row(sub[robot_s]))))
    mu_r, sd_r = (v.ravel() for v in cv2.meanStdDev(_to_lab(pixel_row(sub[ring_s]))))
    ratio = np.clip(sd_r / np.maximum(sd_s, 1e-3), *cfg.std_ratio_limits) if cfg.match_std else np.ones(3)
    k = cfg.strength
    # Interpolate between identity and the full transfer, per channel:
    # new = (lab - mu_s) * scale + target_mean, i.e. lab * scale + (target_mean - mu_s * scale).
    scale = (1 - k) + k * ratio
    target_mean = (1 - k) * mu_s + k * mu_r
    affine = np.concatenate([np.diag(scale), (target_mean - mu_s * scale)[:, None]], 1)
    box = bbox(region)
    inside = region[box]
    lab = _to_lab(pixel_row(pixels(image[box])[inside]))  # only the pixels that change
    new = cv2.transform(lab, affine)
    np.clip(new[..., 0], 0, 100, out=new[..., 0])
    # Weight: 1 on the robot, fading to 0 across the dilation band (no visible seam).
    w = (np.clip(1.0 - dist[box][inside] / (cfg.edge_px + 1.0), 0.0, 1.0) if cfg.edge_px > 0
         else np.ones(inside.sum(), np.float32))[None]
    rgb = _from_lab(cv2.blendLinear(new, lab, w, 1 - w))
    np.maximum(rgb, 0, out=rgb)
    pixels(out[box])[inside] = pixels(cv2.convertScaleAbs(rgb))[0]  # rounded, saturated at 255
    return True


def harmonize(image: np.ndarray, robot_mask: np.ndarray, cfg: HarmonizeConfig = HarmonizeConfig(),
              out: np.ndarray | None = None) -> HarmonizeResult:
    """Harmonize composites (n,H,W,3) uint8 given visible robot masks (n,H,W) bool, into
    ``out`` (a copy of ``image`` when None; ``image`` itself is fine: harmonized in place)."""
    image = np.asarray(image)
    robot_mask = np.asarray(robot_mask, bool)
    if image.ndim != 4 or image.shape[-1] != 3 or robot_mask.shape != image.shape[:3]:
        raise ValueError(f"harmonize: image (n,H,W,3) and robot_mask (n,H,W); got {image.shape}, {robot_mask.shape}")
    if out is None:
        out = image.copy()
    elif out is not image:
        out[...] = image
    status = np.full(len(image), Reason.OK, STATUS_DTYPE)
    model = None
    if cfg.method == "onnx":
        from handedit.models.harmonizer import harmonize_onnx_frame, load_harmonizer

        model = load_harmonizer(cfg.model_path, cfg.onnx)
    for i in range(len(image)):
        if model is not None:
            res = harmonize_onnx_frame(model, image[i], robot_mask[i], cfg) if robot_mask[i].any() else None
            if res is not None:
                out[i] = res
        else:
            res = harmonize_frame(image[i], robot_mask[i], cfg, out=out[i])  # in place
        if res is None:
            status[i] = Reason.EMPTY_RENDER
    return HarmonizeResult(out, status, f"onnx:harmonizer:{model.tag}" if model is not None else "classical:lab-stats-transfer")
