"""The ``toolkit`` scoring protocol: each metric computed as the authors' toolkit computes it.

Published HandEdit numbers come from github.com/HandEdit/HandEdit (``handedit_eval``), so
``handedit bench evaluate --protocol toolkit`` (the default) reproduces its arithmetic on
the same files, step for step, while ``--protocol paper`` (``handedit.metrics.suite``)
keeps this project's reading of the paper's equations. Where they differ:

==========================  ===========================================  ==========================
step                        toolkit (here)                               paper protocol
==========================  ===========================================  ==========================
images                      PIL RGB, float32 / 255                       uint8
prediction of another size  bilinear resize to the GT (PIL, uint8         rejected: ``wrong_size``
                            round trip truncating), original size kept
masks                       luma / 255 > 0.5, nearest resize             > 127, sizes must match
ROI                         human | robot (+ optional disc dilation);    human | robot
                            neither given: the whole image
ROI metrics                 bbox + 8 px crop; ROI-PSNR = MSE over ROI    crop of the ROI bbox
                            pixels of the crop; SSIM/LPIPS of the crop
BG metrics                  full frames with the ROI zeroed (or           masked means
                            ``bg_mask_path``); BG-PSNR over BG pixels
SSIM                        skimage defaults (7x7 uniform window,         Gaussian window
                            sample covariance, 3 px border dropped)
FID                         clean-fid "clean": per-channel float PIL      OpenCV resize
                            bicubic to 299, ``scipy.linalg.sqrtm``;
                            pooled over the whole run (full frames as
                            files, ROI bbox crops saved as uint8)
Removal                     HSV skin rule on the prediction inside the   same rule
                            ROI; no embodied metric when ROI <= 10 px
Struct fidelity             DINOv2-base CLS of the unmasked padded ROI   masked crop
                            crop, HF preprocessing (shortest edge 256
                            bicubic, centre crop 224); (1 + cos) / 2
ID fidelity                 CLIP ViT-B/32 image features of the          per paper
                            prediction's robot-mask crop filled with
                            0.5 grey (test mask, else GT mask, else
                            whole image; HF preprocessing: shortest
                            edge 224) vs each reference view, best
                            (1 + cos) / 2; Lab: both crops resized to
                            224, mean Delta E (skimage D65) over both
                            masks, exp(-d / 25); 0.5 / 0.5 mix
Fidelity                    harmonic mean of Struct and ID               not reported
Interaction                 1 - LPIPS of the source vs prediction crop   masked LPIPS
                            (object mask dilated 12 px, else a 12 px
                            band around the ROI; bbox + 8; >= 64 px
                            bicubic)
==========================  ===========================================  ==========================

Neural terms need the ONNX encoders (``handedit.metrics.encoders``); without them every
non-neural metric is still computed and the neural ones (and the mixes that contain
them: ``Fidelity-ID``, ``Fidelity``) stay NaN, listed in the run's ``skipped``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image
from scipy.ndimage import binary_dilation, uniform_filter

from handedit.metrics.similarity import bbox, crop  # bbox + pad as slices, clipped to the image

if TYPE_CHECKING:
    from handedit.benchmark.manifest import ManifestItem

GENERIC_METRICS = ["Full-PSNR", "Full-SSIM", "Full-LPIPS", "ROI-PSNR", "ROI-SSIM", "ROI-LPIPS",
                   "BG-PSNR", "BG-SSIM", "BG-LPIPS"]
VLM_METRICS = ["VLM-SC", "VLM-PQ", "VLM", "VLM-robotness", "VLM-target_embodiment_match",
               "VLM-interaction_preservation", "VLM-scene_preservation", "VLM-naturalness", "VLM-artifact_absence",
               "VLM-local_coherence", "VLM-target_choice_correct", "VLM-correct_ref_alignment",
               "VLM-nearest_wrong_ref_alignment", "VLM-identity_margin"]
EMBODIED_METRICS = ["Removal", "Removal_pct", "Fidelity-Shape", "Fidelity-ID", "Fidelity-ID-clip",
                    "Fidelity-ID-clip-cos", "Fidelity-ID-lab", "Fidelity-ID-lab-dist", "Fidelity-ID-bank-size",
                    "Fidelity-ID-best-ref", "Fidelity-ID-margin", "Fidelity-ID-top1", "Fidelity-ID-rank-score",
                    "Fidelity", "Fidelity_pct", "Interaction", "Interaction_pct", "Interaction-LPIPS"]
# which encoder each neural column needs
NEURAL = {"lpips": ["Full-LPIPS", "ROI-LPIPS", "BG-LPIPS", "Interaction", "Interaction_pct", "Interaction-LPIPS"],
          "dinov2": ["Fidelity-Shape", "Fidelity", "Fidelity_pct"],
          "clip": ["Fidelity-ID-clip", "Fidelity-ID-clip-cos", "Fidelity-ID", "Fidelity", "Fidelity_pct"],
          "inception": ["Full-FID", "ROI-FID"]}

HF_DINOV2 = {"shortest_edge": 256, "crop": 224, "mean": (0.485, 0.456, 0.406), "std": (0.229, 0.224, 0.225)}
HF_CLIP = {"shortest_edge": 224, "crop": 224, "mean": (0.48145466, 0.4578275, 0.40821073),
           "std": (0.26862954, 0.26130258, 0.27577711)}
FID_SIZE = 299


@dataclass(frozen=True)
class ToolkitConfig:
    """The toolkit's ``EvalConfig`` / ``HandEditMetricConfig`` defaults."""

    roi_pad: int = 8
    roi_dilate_px: int = 0
    roi_dilate_ratio: float = 0.0
    contact_band_width_px: int = 12
    interaction_min_crop_size: int = 64
    lab_tau: float = 25.0
    lab_size: int = 224
    id_clip_weight: float = 0.5
    id_lab_weight: float = 0.5


# ---------------------------------------------------------------------------------------
# images and masks, exactly as the toolkit reads and resizes them

def load_rgb(path: str | Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB")).astype(np.float32) / 255.0


def load_mask(path: str | Path) -> np.ndarray:
    return ((np.asarray(Image.open(path).convert("L")).astype(np.float32) / 255.0) > 0.5).astype(np.uint8)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """The toolkit's float -> uint8 (truncating, as ``(clip(x) * 255).astype(uint8)``)."""
    return (np.clip(image, 0.0, 1.0) * 255).astype(np.uint8)


def resize_to_match(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``source`` at ``target``'s size (PIL bilinear on uint8), unchanged when equal."""
    if source.shape[:2] == target.shape[:2]:
        return source
    h, w = target.shape[:2]
    return np.asarray(Image.fromarray(to_uint8(source)).resize((w, h), resample=Image.BILINEAR)).astype(np.float32) / 255.0


def resize_mask(mask: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    h, w = hw
    if mask.shape[:2] == (h, w):
        return (mask > 0).astype(np.uint8)
    return (np.asarray(Image.fromarray((mask > 0).astype(np.uint8) * 255).resize((w, h), Image.NEAREST)) > 127).astype(np.uint8)


def crop_to_mask(image: np.ndarray, mask: np.ndarray, pad: int) -> np.ndarray:
    box = bbox(mask, pad)
    return image if box is None else crop(image, box)


def masked_crop(image: np.ndarray, mask: np.ndarray, pad: int, fill: float = 0.5) -> np.ndarray:
    """The mask's padded bbox with everything outside the mask painted ``fill``."""
    box = bbox(mask, pad)
    if box is None:
        return image
    c, m = crop(image, box), crop(mask.astype(np.uint8), box).astype(bool)
    return np.where(m[..., None], c, np.full_like(c, float(fill), dtype=np.float32))


def union(*masks: np.ndarray | None) -> np.ndarray | None:
    valid = [m.astype(np.uint8) for m in masks if m is not None]
    if not valid:
        return None
    out = valid[0].copy()
    for m in valid[1:]:
        out = np.maximum(out, m)
    return (out > 0).astype(np.uint8)


def dilate_disc(mask: np.ndarray, cfg: ToolkitConfig) -> np.ndarray:
    """The optional ROI dilation: a disc of ``roi_dilate_px`` (or a ratio of the short side)."""
    h, w = mask.shape[:2]
    r = int(round(min(h, w) * cfg.roi_dilate_ratio)) if cfg.roi_dilate_ratio > 0 else int(cfg.roi_dilate_px)
    if r <= 0:
        return mask
    yy, xx = np.ogrid[-r:r + 1, -r:r + 1]
    return binary_dilation(mask.astype(bool), structure=(xx * xx + yy * yy) <= r * r).astype(np.uint8)


def ensure_min_size(image: np.ndarray, min_size: int) -> np.ndarray:
    h, w = image.shape[:2]
    if h >= min_size and w >= min_size:
        return image
    s = float(min_size) / float(max(1, min(h, w)))
    size = (max(min_size, int(round(w * s))), max(min_size, int(round(h * s))))
    return np.asarray(Image.fromarray(to_uint8(image)).resize(size, Image.BICUBIC)).astype(np.float32) / 255.0


# ---------------------------------------------------------------------------------------
# non-neural metrics (skimage's definitions, written out so that no test-only package runs them)

def psnr(x: np.ndarray, y: np.ndarray, mask: np.ndarray | None = None) -> float:
    se = (x - y) ** 2
    if mask is None:
        mse = float(se.mean())
    else:
        valid = mask.astype(bool)
        if not valid.any():
            return float("nan")
        mse = float(se[valid].mean())
    return float("inf") if mse <= 0 else float(10.0 * np.log10(1.0 / mse))


def _ssim_channel(a: np.ndarray, b: np.ndarray, win: int = 7, data_range: float = 1.0) -> float:
    """skimage ``structural_similarity`` defaults: uniform 7x7 window, sample covariance,
    K1 0.01, K2 0.03, mean over the image without its (win-1)/2 border (float32 in, float32 math)."""
    a, b = a.astype(np.float32), b.astype(np.float32)
    n = win * win
    cov_norm = np.float32(n / (n - 1))
    ux, uy = uniform_filter(a, size=win), uniform_filter(b, size=win)
    uxx, uyy, uxy = uniform_filter(a * a, size=win), uniform_filter(b * b, size=win), uniform_filter(a * b, size=win)
    vx, vy, vxy = cov_norm * (uxx - ux * ux), cov_norm * (uyy - uy * uy), cov_norm * (uxy - ux * uy)
    c1, c2 = np.float32((0.01 * data_range) ** 2), np.float32((0.03 * data_range) ** 2)
    s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    p = (win - 1) // 2
    return float(s[p:-p, p:-p].astype(np.float64).mean())


def ssim_rgb(x: np.ndarray, y: np.ndarray) -> float:
    """Mean over channels; NaN where skimage would refuse (a side under 7 px)."""
    if min(x.shape[:2]) < 7:
        return float("nan")
    return float(np.mean([_ssim_channel(x[..., c], y[..., c]) for c in range(x.shape[-1])]))


def rgb_to_hsv(rgb: np.ndarray) -> np.ndarray:
    """skimage ``rgb2hsv``: h, s, v in [0, 1] (ties of the max: blue, then green, then red wins)."""
    arr = np.asarray(rgb, np.float32)
    v = arr.max(-1)
    delta = np.ptp(arr, -1)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = delta / v
        s[delta == 0.0] = 0
        h = np.zeros_like(v)
        r = arr[..., 0] == v
        h[r] = (arr[..., 1][r] - arr[..., 2][r]) / delta[r]
        g = arr[..., 1] == v
        h[g] = 2.0 + (arr[..., 2][g] - arr[..., 0][g]) / delta[g]
        bl = arr[..., 2] == v
        h[bl] = 4.0 + (arr[..., 0][bl] - arr[..., 1][bl]) / delta[bl]
    h = (h / 6.0) % 1.0
    h[delta == 0.0] = 0.0
    return np.stack([h, s, v], axis=-1)


def skin_mask(image: np.ndarray) -> np.ndarray:
    hsv = rgb_to_hsv(np.clip(image, 0.0, 1.0))
    h, s, v = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    return (((h <= 0.12) | (h >= 0.90)) & (s >= 0.20) & (s <= 0.75) & (v >= 0.20) & (v <= 0.98)).astype(np.uint8)


_XYZ_FROM_RGB = np.array([[0.412453, 0.357580, 0.180423], [0.212671, 0.715160, 0.072169],
                          [0.019334, 0.119193, 0.950227]])
_D65_2 = np.array([0.95047, 1.0, 1.08883])  # skimage's D65, 2 degree observer


def rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """skimage ``rgb2lab`` (sRGB, D65, 2 degree observer), in the input's float precision as it is."""
    arr = np.asarray(rgb)
    arr = arr.astype(np.float64) if arr.dtype not in (np.float32, np.float64) else arr
    dt = arr.dtype
    lin = np.where(arr > 0.04045, ((arr + 0.055) / 1.055) ** 2.4, arr / 12.92).astype(dt)
    xyz = (lin @ _XYZ_FROM_RGB.T.astype(dt)) / _D65_2.astype(dt)
    f = np.where(xyz > 0.008856, np.cbrt(xyz), 7.787 * xyz + 16.0 / 116.0).astype(dt)
    return np.stack([116.0 * f[..., 1] - 16.0, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])], -1)


def _resize_pair(image: np.ndarray, mask: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    img = np.asarray(Image.fromarray(to_uint8(image)).resize((size, size), Image.BILINEAR)).astype(np.float32) / 255.0
    m = np.asarray(Image.fromarray((mask > 0).astype(np.uint8) * 255).resize((size, size), Image.NEAREST)) > 127
    return img, m.astype(np.uint8)


def lab_similarity(pred: np.ndarray, pred_mask: np.ndarray, gt: np.ndarray, gt_mask: np.ndarray,
                   cfg: ToolkitConfig) -> tuple[float, float]:
    """(mean Delta E over both masks after both padded crops are resized to ``lab_size``, exp(-d/tau))."""
    pred_mask, gt_mask = resize_mask(pred_mask, pred.shape[:2]), resize_mask(gt_mask, gt.shape[:2])
    pb, gb = bbox(pred_mask, cfg.roi_pad), bbox(gt_mask, cfg.roi_pad)
    if pb is None or gb is None:
        return float("nan"), float("nan")
    pc, pm = _resize_pair(crop(pred, pb), crop(pred_mask, pb), cfg.lab_size)
    gc, gm = _resize_pair(crop(gt, gb), crop(gt_mask, gb), cfg.lab_size)
    valid = (pm > 0) & (gm > 0)
    if not valid.any():
        return float("nan"), float("nan")
    d = np.sqrt(((rgb_to_lab(np.clip(pc, 0, 1)) - rgb_to_lab(np.clip(gc, 0, 1))) ** 2).sum(-1))
    dist = float(d[valid].mean())
    return dist, float(np.clip(math.exp(-dist / max(cfg.lab_tau, 1e-6)), 0.0, 1.0))


def dilate_iter(mask: np.ndarray, width: int) -> np.ndarray:
    """scipy ``binary_dilation(iterations=width)`` with its default cross: what the toolkit uses for contact."""
    m = mask.astype(bool)
    return m.astype(np.uint8) if width <= 0 else binary_dilation(m, iterations=max(1, int(width))).astype(np.uint8)


def interaction_region(roi: np.ndarray, object_mask: np.ndarray | None, cfg: ToolkitConfig) -> np.ndarray:
    if object_mask is not None and object_mask.sum() > 0:
        return dilate_iter((object_mask > 0).astype(np.uint8), cfg.contact_band_width_px)
    grown = binary_dilation(roi.astype(bool), iterations=max(1, int(cfg.contact_band_width_px)))
    return (grown & ~roi.astype(bool)).astype(np.uint8)


def harmonic_mean(a: float, b: float) -> float:
    a, b = float(np.clip(a, 0.0, 1.0)), float(np.clip(b, 0.0, 1.0))
    return 0.0 if a <= 0.0 or b <= 0.0 else 2.0 * a * b / (a + b + 1e-8)


# ---------------------------------------------------------------------------------------
# neural preprocessing, as the Hugging Face processors and clean-fid do it

def hf_pixel_values(image: np.ndarray, spec: dict) -> np.ndarray:
    """(3,crop,crop) float32 as ``AutoImageProcessor`` gives it: uint8 (truncating) -> PIL
    bicubic resize of the shortest edge (the long one floored) -> centre crop -> /255 -> normalise."""
    im = Image.fromarray(to_uint8(image)) if image.dtype != np.uint8 else Image.fromarray(image)
    w, h = im.size
    s = spec["shortest_edge"]
    size = (s, int(s * h / w)) if w <= h else (int(s * w / h), s)
    x = np.asarray(im.resize(size, resample=Image.BICUBIC))
    c = spec["crop"]
    top, left = (x.shape[0] - c) // 2, (x.shape[1] - c) // 2
    x = x[top:top + c, left:left + c].astype(np.float64) * (1 / 255)
    x = ((x.astype(np.float32) - np.asarray(spec["mean"], np.float32)) / np.asarray(spec["std"], np.float32))
    return x.transpose(2, 0, 1).astype(np.float32)


def cleanfid_resize(image_u8: np.ndarray, size: int = FID_SIZE) -> np.ndarray:
    """clean-fid's "clean" resize: each channel as a float32 PIL image, bicubic, clipped to [0, 255]."""
    chans = []
    for c in range(3):
        ch = Image.fromarray(image_u8[..., c].astype(np.float32), mode="F").resize((size, size), resample=Image.BICUBIC)
        chans.append(np.asarray(ch).clip(0, 255).reshape(size, size, 1))
    return np.concatenate(chans, axis=2).astype(np.float32)


def frechet_distance_cleanfid(f1: np.ndarray, f2: np.ndarray) -> float:
    """clean-fid's ``frechet_distance`` on two (N,2048) feature sets (``scipy.linalg.sqrtm``)."""
    from scipy import linalg

    mu1, mu2 = f1.mean(0), f2.mean(0)
    s1, s2 = np.cov(f1, rowvar=False), np.cov(f2, rowvar=False)
    diff = mu1 - mu2
    covmean, _ = linalg.sqrtm(s1.dot(s2), disp=False)
    if not np.isfinite(covmean).all():
        offset = np.eye(s1.shape[0]) * 1e-6
        covmean = linalg.sqrtm((s1 + offset).dot(s2 + offset))
    if np.iscomplexobj(covmean):
        covmean = covmean.real
    return float(diff.dot(diff) + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean))


# ---------------------------------------------------------------------------------------
# one sample

def own_refs(item: "ManifestItem") -> list[tuple[str, str]]:
    """An item's own reference views as (image, mask or "") pairs (masks are optional)."""
    return list(zip(item.urdf_ref_paths, item.urdf_mask_paths + [""] * len(item.urdf_ref_paths)))


class Neural:
    """The encoders the neural terms use (any of them may be None) with the toolkit's preprocessing."""

    def __init__(self, encoders):
        self.enc = encoders
        self._ref_cache: dict[tuple, np.ndarray] = {}

    @staticmethod
    def _run(encoder, x: np.ndarray) -> np.ndarray:
        if encoder.static_hw is not None and tuple(encoder.static_hw) != x.shape[1:]:
            from handedit.metrics.encoders import EncoderError

            raise EncoderError(f"{encoder.path}: the toolkit protocol feeds {x.shape[1]}x{x.shape[2]} (as its model "
                               f"does), this graph takes {encoder.static_hw[0]}x{encoder.static_hw[1]}; re-export it "
                               f"with bench/export_encoders.py")
        return np.asarray(encoder.session.run(None, {encoder.input_name: x[None]})[0], np.float32).reshape(-1)

    @classmethod
    def _embed(cls, encoder, x: np.ndarray) -> np.ndarray:
        v = cls._run(encoder, x)
        return v / (float(np.linalg.norm(v)) + 1e-8)

    def lpips(self, a: np.ndarray, b: np.ndarray) -> float:
        if self.enc.lpips is None:
            return float("nan")
        return self.enc.lpips.distance(a * np.float32(255.0), b * np.float32(255.0))  # its [0,1] scaling

    def dinov2(self, image: np.ndarray) -> np.ndarray | None:
        return None if self.enc.dinov2 is None else self._embed(self.enc.dinov2, hf_pixel_values(image, HF_DINOV2))

    def clip(self, image: np.ndarray) -> np.ndarray | None:
        return None if self.enc.clip is None else self._embed(self.enc.clip, hf_pixel_values(image, HF_CLIP))

    def clip_reference(self, path: str, mask_path: str, cfg: ToolkitConfig) -> np.ndarray | None:
        key = (path, mask_path, cfg.roi_pad)
        if key not in self._ref_cache:
            image = load_rgb(path)
            mask = resize_mask(load_mask(mask_path), image.shape[:2]) if mask_path and Path(mask_path).exists() \
                else np.ones(image.shape[:2], np.uint8)
            self._ref_cache[key] = self.clip(masked_crop(image, mask, cfg.roi_pad, 0.5))
        return self._ref_cache[key]

    def inception(self, image_u8: np.ndarray) -> np.ndarray | None:
        enc = self.enc.inception
        if enc is None:
            return None
        x = (cleanfid_resize(image_u8) / 255.0).transpose(2, 0, 1).astype(np.float32)
        return self._run(enc, x).astype(np.float64)


def _cos(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.clip(np.dot(a, b), -1.0, 1.0))


def _mask(path: str, hw: tuple[int, int] | None = None) -> np.ndarray | None:
    if not path or not Path(path).exists():
        return None
    m = load_mask(path)
    return resize_mask(m, hw) if hw is not None else m


def score_sample(s: "ManifestItem", neural: Neural, cfg: ToolkitConfig = ToolkitConfig(),
                 refs: list[tuple[str, str]] | None = None) -> tuple[dict, dict]:
    """(the toolkit's per-sample row, Inception features for the pooled FID) of one manifest item
    (paths resolved); ``refs``: its reference views (default: its own, ``own_refs``)."""
    refs = own_refs(s) if refs is None else refs
    row: dict = {m: float("nan") for m in GENERIC_METRICS + VLM_METRICS + EMBODIED_METRICS}
    feats: dict = {}
    if not s.pred_path or not Path(s.pred_path).exists():
        row["error"] = f"Missing pred_path: {s.pred_path}"
        return row, feats
    pred = load_rgb(s.pred_path)
    src = load_rgb(s.src_path) if s.src_path and Path(s.src_path).exists() else None
    gt = load_rgb(s.gt_path) if s.gt_path and Path(s.gt_path).exists() else None
    row["pred_size"] = f"{pred.shape[1]}x{pred.shape[0]}"

    def roi_at(hw):
        merged = union(_mask(s.human_mask_path, hw), _mask(s.robot_mask_path, hw))
        return None if merged is None else dilate_disc(merged, cfg)

    roi = None
    if src is not None:
        pred = resize_to_match(pred, src)
        roi = roi_at(src.shape[:2])
    if gt is not None:
        pred = resize_to_match(pred, gt)
        if src is not None:
            src = resize_to_match(src, gt)
        roi = roi_at(gt.shape[:2])
    row["resized"] = row["pred_size"] != f"{pred.shape[1]}x{pred.shape[0]}"
    if roi is None:
        roi = np.ones(pred.shape[:2], np.uint8)
    if src is not None:
        row.update(_embodied(s, refs, src, pred, gt, roi, neural, cfg))
    if gt is None:
        return row, feats

    bg = _mask(s.bg_mask_path, gt.shape[:2])
    if bg is None:
        bg = (1 - roi).astype(np.uint8)
    row["Full-PSNR"], row["Full-SSIM"], row["Full-LPIPS"] = psnr(pred, gt), ssim_rgb(pred, gt), neural.lpips(pred, gt)
    box = bbox(roi, cfg.roi_pad)
    if box is not None:
        pr, gr = crop(pred, box), crop(gt, box)
        row["ROI-PSNR"], row["ROI-SSIM"], row["ROI-LPIPS"] = psnr(pr, gr, crop(roi, box)), ssim_rgb(pr, gr), neural.lpips(pr, gr)
    pb, gb = pred * bg.astype(np.float32)[..., None], gt * bg.astype(np.float32)[..., None]
    row["BG-PSNR"], row["BG-SSIM"], row["BG-LPIPS"] = psnr(pb, gb, bg), ssim_rgb(pb, gb), neural.lpips(pb, gb)

    # FID inputs: the files themselves (full), and the ROI crops saved as uint8 PNGs (ROI)
    f_gt = neural.inception(np.asarray(Image.open(s.gt_path).convert("RGB")))
    if f_gt is not None:
        feats["full_gt"] = f_gt
        feats["full_pred"] = neural.inception(np.asarray(Image.open(s.pred_path).convert("RGB")))
        if box is not None:
            feats["roi_gt"] = neural.inception(to_uint8(crop(gt, box)))
            feats["roi_pred"] = neural.inception(to_uint8(crop(pred, box)))
    return row, feats


def _embodied(s: "ManifestItem", refs: list[tuple[str, str]], src, pred, gt, roi, neural: Neural, cfg: ToolkitConfig) -> dict:
    roi = (roi > 0).astype(np.uint8)
    if roi.sum() <= 10:
        return {}
    out: dict = {}
    residual = float(np.logical_and(skin_mask(pred) > 0, roi > 0).sum())
    out["Removal"] = float(np.clip(1.0 - residual / (float(roi.sum()) + 1e-8), 0.0, 1.0))
    out["Removal_pct"] = 100.0 * out["Removal"]

    shape = float("nan")
    if gt is not None:
        a, b = neural.dinov2(crop_to_mask(pred, roi, cfg.roi_pad)), neural.dinov2(crop_to_mask(gt, roi, cfg.roi_pad))
        if a is not None:
            shape = 0.5 * (1.0 + _cos(a, b))
    out["Fidelity-Shape"] = shape

    test = _mask(s.test_mask_path, pred.shape[:2])
    gt_mask = _mask(s.gt_mask_path, gt.shape[:2]) if gt is not None else None
    if test is None:
        test = resize_mask(gt_mask, pred.shape[:2]) if gt_mask is not None else np.ones(pred.shape[:2], np.uint8)
    if gt is not None and gt_mask is None:
        gt_mask = np.ones(gt.shape[:2], np.uint8)

    clip_score, clip_cos, best, n_refs = float("nan"), float("nan"), "", 0.0
    pred_id = neural.clip(masked_crop(pred, test, cfg.roi_pad, 0.5)) if refs else None
    if pred_id is not None:
        best_score = -1.0
        for path, mask_path in refs:
            ref = neural.clip_reference(path, mask_path, cfg)
            c = _cos(pred_id, ref)
            if 0.5 * (1.0 + c) > best_score:
                best_score, clip_cos, best = 0.5 * (1.0 + c), c, path
        clip_score, n_refs = float(np.clip(best_score, 0.0, 1.0)), float(len(refs))
    out.update({"Fidelity-ID-clip": clip_score, "Fidelity-ID-clip-cos": clip_cos, "Fidelity-ID-best-ref": best,
                "Fidelity-ID-bank-size": n_refs if neural.enc.clip is not None else float("nan")})

    lab_dist = lab_sim = float("nan")
    if gt is not None:
        lab_dist, lab_sim = lab_similarity(pred, test, gt, gt_mask, cfg)
    out["Fidelity-ID-lab-dist"], out["Fidelity-ID-lab"] = lab_dist, lab_sim

    wsum = max(cfg.id_clip_weight + cfg.id_lab_weight, 1e-8)
    if neural.enc.clip is None:
        ident = float("nan")  # the toolkit always has CLIP: a lab-only ID would not be its number
    elif math.isfinite(clip_score) and math.isfinite(lab_sim):
        ident = float(np.clip(cfg.id_clip_weight / wsum * clip_score + cfg.id_lab_weight / wsum * lab_sim, 0.0, 1.0))
    elif math.isfinite(clip_score):
        ident = clip_score
    else:
        ident = lab_sim  # no reference view: the toolkit falls back to the Lab term
    out["Fidelity-ID"] = ident
    if math.isfinite(shape) and math.isfinite(ident):
        fidelity = harmonic_mean(shape, ident)
    elif neural.enc.dinov2 is None or neural.enc.clip is None:
        fidelity = float("nan")
    else:
        fidelity = ident if math.isfinite(ident) else shape
    out["Fidelity"], out["Fidelity_pct"] = fidelity, (100.0 * fidelity if math.isfinite(fidelity) else float("nan"))

    region = interaction_region(roi, _mask(s.object_mask_path, src.shape[:2]), cfg)
    inter = float("nan")
    if region.sum() > 0 and neural.enc.lpips is not None:
        box = bbox(region, cfg.roi_pad)
        a = ensure_min_size(crop(src, box), cfg.interaction_min_crop_size)
        b = ensure_min_size(crop(pred, box), cfg.interaction_min_crop_size)
        inter = float(np.clip(1.0 - neural.lpips(a, b), 0.0, 1.0))
    out["Interaction"] = inter
    out["Interaction_pct"] = 100.0 * inter if math.isfinite(inter) else float("nan")
    out["Interaction-LPIPS"] = 1.0 - inter if math.isfinite(inter) else float("nan")
    return out
