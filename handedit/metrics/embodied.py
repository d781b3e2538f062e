"""Embodiment-aware metrics (paper eqs. S_rem, S_struct, S_ref, S_Lab, S_ID, S_int).

Notation: x source, y pseudo-GT, y_hat edited output, M = M_h | M_r the ROI (M_h the
source human hand / hand-arm mask, M_r the pseudo-GT robot mask), M_O the
object-contact region. Encoder inputs are the masked image cropped to the mask's
bounding box, so a small ROI fills the encoder's window (zeros outside the mask, as
``y_hat (.) M`` in the paper).
"""

from __future__ import annotations

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from handedit.metrics.encoders import LpipsNet, OnnxEncoder, cosine
from handedit.metrics.similarity import bbox
from handedit.vision.skin import prior_rule, to_ycrcb


class EmbodiedConfig(BaseModel):
    """Constants of the embodiment-aware metrics (paper values by default)."""

    VERSION: int = 1
    model_config = ConfigDict(frozen=True)
    id_lambda: float = Field(0.5, ge=0, le=1, description="weight of S_ref in S_ID")
    lab_tau: float = Field(25.0, gt=0, description="tau_Lab of S_Lab = exp(-dE/tau)")
    contact_dilate_px: int = Field(15, ge=0, description="dilation of the object mask around the contact area")
    contact_margin_px: int = Field(25, ge=0, description="how close to M object pixels must be to count as contact")


def masked_crop(image: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
    """``image (.) mask`` cropped to the mask's bounding box (None when the mask is empty)."""
    box = bbox(mask)
    if box is None:
        return None
    out = image[box] * np.asarray(mask, bool)[box][..., None]
    return np.ascontiguousarray(out.astype(np.uint8))


def removal(pred: np.ndarray, roi: np.ndarray) -> float:
    """S_rem = 1 - N_skin(y_hat; M) / N(M), skin by the fixed YCrCb chrominance rule."""
    m = np.asarray(roi, bool)
    n = int(m.sum())
    if n == 0:
        return float("nan")
    skin = prior_rule(to_ycrcb(pred)) & m
    return 1.0 - float(skin.sum()) / n


def struct_fidelity(dinov2: OnnxEncoder, pred: np.ndarray, gt: np.ndarray, roi: np.ndarray) -> float:
    """S_struct = (1 + cos(DINOv2(y_hat (.) M), DINOv2(y (.) M))) / 2."""
    a, b = masked_crop(pred, roi), masked_crop(gt, roi)
    if a is None:
        return float("nan")
    e = dinov2.embed([a, b])
    return 0.5 * (1.0 + cosine(e[0], e[1]))


_SRGB_TO_XYZ = np.array([[0.412453, 0.357580, 0.180423], [0.212671, 0.715160, 0.072169], [0.019334, 0.119193, 0.950227]])
_D65 = np.array([0.950456, 1.0, 1.088754])


def rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """uint8 sRGB -> CIELAB (D65, float64): L in [0,100]. Exact formulas (OpenCV's float
    path quantises a/b to 1/64, enough to move Delta E by ~0.1)."""
    c = np.asarray(rgb, np.float64) / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    xyz = lin @ _SRGB_TO_XYZ.T / _D65
    f = np.where(xyz > (6 / 29) ** 3, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], axis=-1)


def delta_e_lab(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """Mean CIE76 Delta E between two images over ``mask``."""
    m = np.asarray(mask, bool)
    if not m.any():
        return float("nan")
    d = rgb_to_lab(pred[m]) - rgb_to_lab(gt[m])  # only the masked pixels are converted
    return float(np.sqrt((d**2).sum(axis=-1)).mean())


def lab_score(delta_e: float, tau: float = 25.0) -> float:
    """S_Lab = exp(-Delta E / tau)."""
    return float(np.exp(-delta_e / tau))


def ref_score(clip: OnnxEncoder, pred: np.ndarray, robot_mask: np.ndarray,
              refs: list[np.ndarray], ref_masks: list[np.ndarray]) -> float:
    """S_ref = max_v (1 + cos(CLIP(y_hat (.) M_r), CLIP(I_v (.) M_v))) / 2."""
    q = masked_crop(pred, robot_mask)
    views = [c for c in (masked_crop(r, m) for r, m in zip(refs, ref_masks)) if c is not None]
    if q is None or not views:
        return float("nan")
    e = clip.embed([q, *views])
    return max(0.5 * (1.0 + cosine(e[0], v)) for v in e[1:])


def id_fidelity(s_ref: float, s_lab: float, lam: float = 0.5) -> float:
    """S_ID = lambda S_ref + (1 - lambda) S_Lab."""
    return lam * s_ref + (1.0 - lam) * s_lab


def contact_region(object_mask: np.ndarray, roi: np.ndarray, cfg: EmbodiedConfig) -> np.ndarray:
    """M_O: the object mask near the hand, dilated, minus the edited ROI itself.

    Object pixels within ``contact_margin_px`` of M are the contact area; dilating
    them by ``contact_dilate_px`` adds the local neighbourhood. The ROI is removed
    because the hand itself is meant to change (paper: interaction is not measured
    inside the edited hand). Falls back to the whole object when it never nears M.
    """
    obj = np.asarray(object_mask, bool)
    m = np.asarray(roi, bool)
    if not obj.any():
        return np.zeros_like(obj)

    def dil(mask: np.ndarray, r: int) -> np.ndarray:
        if r <= 0:
            return mask
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        return cv2.dilate(mask.astype(np.uint8), k).astype(bool)

    near = obj & dil(m, cfg.contact_margin_px)
    seed = near if near.any() else obj
    return dil(seed, cfg.contact_dilate_px) & ~m


def interaction(lpips: LpipsNet, src: np.ndarray, pred: np.ndarray, contact: np.ndarray) -> float:
    """S_int = 1 - LPIPS(x (.) M_O, y_hat (.) M_O), on the bounding box of M_O."""
    a, b = masked_crop(src, contact), masked_crop(pred, contact)
    if a is None:
        return float("nan")
    return 1.0 - lpips.distance(a, b)
