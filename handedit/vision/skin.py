"""Skin colour in the (Cr, Cb) plane: a fixed prior rule and a Gaussian fitted per chunk.

Chrominance separates skin from most indoor backgrounds nearly independently of
brightness, and skin tones of all ethnicities cluster tightly there (Chai & Ngan 1999),
so one 2-D Gaussian fitted to pixels we trust (keypoint seeds, or the prior rule) gives
a per-pixel skin probability that the segmenter and the residue check share.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

PRIOR_CR = (135, 180)
PRIOR_CB = (85, 135)
PRIOR_MIN_Y = 40  # very dark pixels have unreliable chroma


def to_ycrcb(rgb: np.ndarray) -> np.ndarray:
    """(H,W,3) uint8 RGB -> YCrCb uint8."""
    return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2YCrCb)


def colour_gaussian(px: np.ndarray, floor: float) -> tuple[np.ndarray, np.ndarray, float]:
    """(mean, inverse covariance, log det covariance) of a 3-D Gaussian fitted to pixels
    ``px`` (m,3), its covariance floored by ``floor`` x identity (``colour_loglik``; fit once,
    evaluate at many pixel sets with ``gaussian_loglik``)."""
    cov = np.cov(np.asarray(px).T) + np.eye(3) * floor
    return np.asarray(px).mean(0), np.linalg.inv(cov), float(np.log(np.linalg.det(cov)))


def gaussian_loglik(x: np.ndarray, gaussian: tuple[np.ndarray, np.ndarray, float], dtype=np.float64) -> np.ndarray:
    """Log-likelihood of colours ``x`` (...,3) under a fitted ``colour_gaussian``, in ``dtype``."""
    mean, icov, logdet = gaussian
    d = (x - mean).astype(dtype, copy=False)
    return -0.5 * ((d @ icov.astype(dtype)) * d).sum(-1) - 0.5 * logdet


def colour_loglik(x: np.ndarray, px: np.ndarray, floor: float, dtype=np.float64) -> np.ndarray:
    """Log-likelihood of colours ``x`` (...,3) under a 3-D Gaussian fitted to pixels ``px``
    (m,3), its covariance floored by ``floor`` x identity (a hand's own colour against its
    surroundings': the segmenter's colour gate, registration's hand probability, the
    composite's residue test), evaluated in ``dtype``."""
    return gaussian_loglik(x, colour_gaussian(px, floor), dtype)


def prior_rule(ycrcb: np.ndarray) -> np.ndarray:
    """Fixed chrominance box (Chai & Ngan): a generic, uncalibrated skin detector."""
    y, cr, cb = ycrcb[..., 0], ycrcb[..., 1], ycrcb[..., 2]
    return (
        (y >= PRIOR_MIN_Y)
        & (cr >= PRIOR_CR[0]) & (cr <= PRIOR_CR[1])
        & (cb >= PRIOR_CB[0]) & (cb <= PRIOR_CB[1])
    )


@dataclass(frozen=True)
class SkinModel:
    """Gaussian over (Cr, Cb); ``prob`` is exp(-d^2/2) with d the Mahalanobis distance."""

    mean: np.ndarray  # (2,)
    icov: np.ndarray  # (2,2)

    @classmethod
    def prior(cls) -> "SkinModel":
        mean = np.array([np.mean(PRIOR_CR), np.mean(PRIOR_CB)])
        cov = np.diag([((PRIOR_CR[1] - PRIOR_CR[0]) / 4.0) ** 2, ((PRIOR_CB[1] - PRIOR_CB[0]) / 4.0) ** 2])
        return cls(mean, np.linalg.inv(cov))

    @classmethod
    def fit(cls, crcb: np.ndarray, min_samples: int = 100, min_std: float = 2.5, inflate: float = 2.0) -> "SkinModel | None":
        """Robust fit to (N,2) samples: trim to 3 MAD-sigmas, inflate and floor the spread.

        Inflating the covariance tolerates the shading and chroma drift of skin across a
        chunk (palm vs. back of the hand, lit vs. shadowed); the floor keeps a model fitted on one flat-coloured synthetic blob (or a
        heavily compressed video) from rejecting the same skin a few levels away.
        """
        x = np.asarray(crcb, dtype=np.float64).reshape(-1, 2)
        if len(x) < min_samples:
            return None
        med = np.median(x, axis=0)
        mad = np.median(np.abs(x - med), axis=0) * 1.4826 + 1e-6
        keep = (np.abs(x - med) <= 3.0 * np.maximum(mad, min_std)).all(axis=1)
        x = x[keep]
        if len(x) < min_samples:
            return None
        cov = inflate * np.cov(x.T) + np.eye(2) * min_std**2
        return cls(x.mean(axis=0), np.linalg.inv(cov))

    def prob(self, ycrcb: np.ndarray) -> np.ndarray:
        """(..., 3) YCrCb -> (...) float32 skin probability in [0, 1]."""
        d = ycrcb[..., 1:3].astype(np.float32) - self.mean.astype(np.float32)
        ic = self.icov.astype(np.float32)
        m2 = d[..., 0] ** 2 * ic[0, 0] + 2.0 * d[..., 0] * d[..., 1] * ic[0, 1] + d[..., 1] ** 2 * ic[1, 1]
        p = np.exp(-0.5 * m2)
        p[ycrcb[..., 0] < PRIOR_MIN_Y] *= 0.25
        return p.astype(np.float32)
