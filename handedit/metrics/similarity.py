"""PSNR and SSIM over the three regions of the paper: full image, background, ROI crop.

Region conventions (shared by every generic metric):
- full: the whole image;
- background (BG): pixels outside the ROI M = M_h | M_r, compared in place (a masked
  mean of the per-pixel error / SSIM map), so the scene around the edit counts;
- ROI: the bounding box of M, cropped from both images, so the edit fills the window.

SSIM follows Wang et al. 2004 with scikit-image's defaults (7x7 uniform window,
sample covariance, K1=0.01, K2=0.03, data range 255, mean over channels), so numbers
match ``skimage.metrics.structural_similarity`` exactly on full images.
"""

from __future__ import annotations

import cv2
import numpy as np

PSNR_CAP_DB = 100.0  # identical images: finite, so means over items stay finite
K1, K2, WIN = 0.01, 0.03, 7


def _check_pair(a: np.ndarray, b: np.ndarray) -> None:
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {a.shape} vs {b.shape}")


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, data_range: float = 255.0) -> float:
    """Peak signal-to-noise ratio in dB over all pixels, or those where ``mask`` is set."""
    _check_pair(a, b)
    d = (a.astype(np.float64) - b.astype(np.float64)) ** 2
    if mask is not None:
        m = np.asarray(mask, bool)
        if not m.any():
            return float("nan")
        d = d[m]
    mse = float(d.mean())
    if mse <= 0:
        return PSNR_CAP_DB
    return float(min(PSNR_CAP_DB, 10.0 * np.log10(data_range**2 / mse)))


def ssim_map(a: np.ndarray, b: np.ndarray, data_range: float = 255.0, win: int = WIN) -> np.ndarray:
    """(H,W) SSIM map averaged over channels (uniform ``win`` window, sample covariance)."""
    _check_pair(a, b)
    x = a.astype(np.float64)
    y = b.astype(np.float64)
    if x.ndim == 2:
        x, y = x[..., None], y[..., None]
    win = min(win, *(s if s % 2 else s - 1 for s in x.shape[:2]))
    if win < 3:
        raise ValueError(f"image {a.shape[:2]} is too small for SSIM (needs at least 3x3)")
    c1, c2 = (K1 * data_range) ** 2, (K2 * data_range) ** 2
    cov_norm = win * win / (win * win - 1.0)
    out = np.zeros(x.shape[:2])
    for c in range(x.shape[2]):
        xc, yc = x[..., c], y[..., c]
        f = lambda v: cv2.blur(v, (win, win), borderType=cv2.BORDER_REFLECT)  # noqa: E731  (= scipy's uniform_filter, ~5x faster)
        ux, uy = f(xc), f(yc)
        vx = cov_norm * (f(xc * xc) - ux * ux)
        vy = cov_norm * (f(yc * yc) - uy * uy)
        vxy = cov_norm * (f(xc * yc) - ux * uy)
        out += ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    return out / x.shape[2]


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, data_range: float = 255.0) -> float:
    """Mean SSIM; excludes the half-window border like scikit-image; ``mask`` restricts the mean."""
    return ssim_mean(ssim_map(a, b, data_range), mask)


def ssim_mean(s: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean of an SSIM map (one map serves both the full image and the background)."""
    pad = (min(WIN, *(n if n % 2 else n - 1 for n in s.shape)) - 1) // 2
    valid = np.zeros(s.shape, bool)
    valid[pad : s.shape[0] - pad, pad : s.shape[1] - pad] = True
    if mask is not None:
        valid &= np.asarray(mask, bool)
    if not valid.any():
        return float("nan")
    return float(s[valid].mean())


def bbox(mask: np.ndarray, margin: int = 0) -> tuple[slice, slice] | None:
    """Bounding box of a mask as slices (None when empty), grown by ``margin`` pixels and clipped.

    Also the window of the per-pixel stages (compositing, harmonization, the residue check):
    every neighbourhood operation they use reaches at most a known radius from the mask, so
    working inside its box grown by that radius gives the full frame's result exactly."""
    rows, cols = np.flatnonzero(np.any(mask, axis=1)), np.flatnonzero(np.any(mask, axis=0))
    if not len(rows):
        return None
    h, w = mask.shape[:2]
    return (slice(max(0, int(rows[0]) - margin), min(h, int(rows[-1]) + 1 + margin)),
            slice(max(0, int(cols[0]) - margin), min(w, int(cols[-1]) + 1 + margin)))


def crop(image: np.ndarray, box: tuple[slice, slice]) -> np.ndarray:
    return image[box[0], box[1]]
