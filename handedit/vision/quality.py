"""Stage-quality metrics against ground truth (synthetic clips), shared by bench and tests.

Each metric answers one question of issue 5's "measured quality": how well the masks
match (IoU), how close the restored background is to the true one *inside the hole*
(PSNR, SSIM over hole pixels only: the rest is copied and would inflate the score), how
much the restoration disturbs the composite at the robot's silhouette (boundary error),
and how far harmonization moves the robot's mean Lab colour towards its surroundings.
"""

from __future__ import annotations

import cv2
import numpy as np


def iou(a: np.ndarray, b: np.ndarray) -> float:
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    u = (a | b).sum()
    return float((a & b).sum() / u) if u else 1.0


def psnr_in(pred: np.ndarray, ref: np.ndarray, region: np.ndarray) -> float:
    """PSNR (dB) over ``region`` pixels of (H,W,3) uint8 images."""
    region = np.asarray(region, bool)
    if not region.any():
        return float("inf")
    mse = float(np.mean((pred[region].astype(np.float64) - ref[region].astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse)


def ssim_in(pred: np.ndarray, ref: np.ndarray, region: np.ndarray, sigma: float = 1.5) -> float:
    """Mean of the grey-level SSIM map (Wang et al. 2004, Gaussian window) over ``region``."""
    x = cv2.cvtColor(pred, cv2.COLOR_RGB2GRAY).astype(np.float64)
    y = cv2.cvtColor(ref, cv2.COLOR_RGB2GRAY).astype(np.float64)
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    blur = lambda z: cv2.GaussianBlur(z, (0, 0), sigma)  # noqa: E731
    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    region = np.asarray(region, bool)
    return float(s[region].mean()) if region.any() else 1.0


def boundary_band(mask: np.ndarray, px: int = 3) -> np.ndarray:
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1, 2 * px + 1))
    m = np.asarray(mask, np.uint8)
    return cv2.dilate(m, k).astype(bool) & ~cv2.erode(m, k).astype(bool)


def boundary_error(image: np.ndarray, reference: np.ndarray, mask: np.ndarray, px: int = 3) -> float:
    """Mean |RGB difference| (grey levels) in a band of ``px`` around ``mask``'s silhouette."""
    band = boundary_band(mask, px)
    if not band.any():
        return 0.0
    return float(np.abs(image[band].astype(np.float64) - reference[band].astype(np.float64)).mean())


def lab_gap(image: np.ndarray, mask: np.ndarray, ring_px: int = 25) -> float:
    """CIE76 distance between the mean Lab of ``mask`` and of a ring of ``ring_px`` around it."""
    m = np.asarray(mask, bool)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * ring_px + 1, 2 * ring_px + 1))
    ring = cv2.dilate(m.astype(np.uint8), k).astype(bool) & ~m
    if not m.any() or not ring.any():
        return 0.0
    lab = cv2.cvtColor(image.astype(np.float32) / 255.0, cv2.COLOR_RGB2Lab)
    return float(np.linalg.norm(lab[m].mean(0) - lab[ring].mean(0)))
