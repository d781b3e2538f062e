"""One item's metric record: every per-image metric plus the features FID pools.

``score_item`` is what the evaluate flow runs per item (in chunks, on Dask workers);
FID is a set-level statistic, so items return Inception features and the driver
pools them per (editor, track). Metrics whose encoder is missing come back NaN and
are listed once in the run's ``skipped`` field by the caller.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from handedit.metrics import embodied, similarity
from handedit.metrics.embodied import EmbodiedConfig
from handedit.metrics.encoders import Encoders
from handedit.metrics.similarity import bbox, crop

# name -> (higher is better?, group) in the paper's table order
METRICS: dict[str, tuple[bool, str]] = {
    "psnr_full": (True, "generic"), "psnr_bg": (True, "generic"), "psnr_roi": (True, "generic"),
    "ssim_full": (True, "generic"), "ssim_bg": (True, "generic"), "ssim_roi": (True, "generic"),
    "lpips_full": (False, "generic"), "lpips_bg": (False, "generic"), "lpips_roi": (False, "generic"),
    "fid_full": (False, "generic"), "fid_roi": (False, "generic"),
    "removal": (True, "embodied"), "struct_fidelity": (True, "embodied"), "id_fidelity": (True, "embodied"),
    "interaction": (True, "embodied"),
    "vlm_sc": (True, "vlm"), "vlm_pq": (True, "vlm"), "vlm": (True, "vlm"),
}
# per-item extras kept in the item table (components of the headline metrics)
EXTRAS = ("id_ref", "id_lab", "delta_e")


@dataclass
class ItemImages:
    """Everything one item's metrics read; images uint8 (H,W,3), masks bool (H,W)."""

    src: np.ndarray
    pred: np.ndarray
    gt: np.ndarray | None  # None: every metric against the pseudo-GT is disabled (NaN)
    human_mask: np.ndarray
    robot_mask: np.ndarray
    object_mask: np.ndarray | None = None
    refs: list[np.ndarray] = field(default_factory=list)
    ref_masks: list[np.ndarray] = field(default_factory=list)

    @property
    def roi(self) -> np.ndarray:
        return self.human_mask | self.robot_mask

    def check(self) -> None:
        """Shape errors name what is wrong and what size was expected."""
        ref = self.gt if self.gt is not None else self.src
        h, w = ref.shape[:2]
        for name in ("src", "pred"):
            im = getattr(self, name)
            if im.shape != ref.shape:
                raise ValueError(f"{name} is {im.shape[1]}x{im.shape[0]}, the pseudo-GT is {w}x{h}: "
                                 f"the editor must return the source resolution")
        for name in ("human_mask", "robot_mask", "object_mask"):
            m = getattr(self, name)
            if m is not None and m.shape != (h, w):
                raise ValueError(f"{name} is {m.shape}, expected {(h, w)}")


def item_images(src: np.ndarray, pred: np.ndarray, gt: np.ndarray | None = None, human_mask: np.ndarray | None = None,
                robot_mask: np.ndarray | None = None, object_mask: np.ndarray | None = None,
                refs: list[np.ndarray] = (), ref_masks: list[np.ndarray | None] = ()) -> tuple[ItemImages, str]:
    """An item from whatever inputs it has, and what the missing ones disable, as the authors'
    toolkit does: no human/robot masks -> the ROI is the whole image; no object mask -> no
    Interaction; no pseudo-GT -> only Removal, ID (references) and Interaction; no
    references -> no S_ref; a reference without a mask -> its whole view."""
    hw = src.shape[:2]
    notes = []
    if human_mask is None and robot_mask is None:
        human_mask, robot_mask = np.ones(hw, bool), np.zeros(hw, bool)
        notes.append("no human/robot masks: ROI = whole image, no background metrics, no Lab term")
    elif human_mask is None or robot_mask is None:
        notes.append(f"no {'human' if human_mask is None else 'robot'} mask: ROI = the other one")
        human_mask = human_mask if human_mask is not None else np.zeros(hw, bool)
        robot_mask = robot_mask if robot_mask is not None else np.zeros(hw, bool)
    if gt is None:
        notes.append("no pseudo-GT: generic metrics, Struct and the Lab term disabled")
    if object_mask is None:
        notes.append("no object mask: no Interaction")
    if not refs:
        notes.append("no reference renders: no S_ref")
    masks = [m if m is not None else np.ones(r.shape[:2], bool)
             for r, m in zip(refs, [*ref_masks, *[None] * (len(refs) - len(ref_masks))])]
    return ItemImages(src, pred, gt, human_mask, robot_mask, object_mask, list(refs), masks), "; ".join(notes)


def score_item(items: ItemImages, enc: Encoders, cfg: EmbodiedConfig = EmbodiedConfig()) -> tuple[dict, dict]:
    """-> (metrics {name: float}, features {'full_pred','full_gt','roi_pred','roi_gt': (D,)})."""
    items.check()
    nan = float("nan")
    src, pred, gt, roi = items.src, items.pred, items.gt, items.roi
    bg = ~roi
    box = bbox(roi)
    if gt is None:  # no pseudo-GT: only what compares the prediction with the source and references
        return _without_gt(items, enc, cfg, roi), {}
    out: dict[str, float] = {}
    out["psnr_full"] = similarity.psnr(pred, gt)
    out["psnr_bg"] = similarity.psnr(pred, gt, bg)
    smap = similarity.ssim_map(pred, gt)  # one map: full and background are two means of it
    out["ssim_full"] = similarity.ssim_mean(smap)
    out["ssim_bg"] = similarity.ssim_mean(smap, bg)
    pred_roi = crop(pred, box) if box else None
    gt_roi = crop(gt, box) if box else None
    out["psnr_roi"] = similarity.psnr(pred_roi, gt_roi) if box else nan
    out["ssim_roi"] = similarity.ssim(pred_roi, gt_roi) if box and min(pred_roi.shape[:2]) >= 3 else nan
    if enc.lpips is not None and bg.any():
        out["lpips_full"], out["lpips_bg"] = enc.lpips.full_and_masked(pred, gt, bg)
        out["lpips_roi"] = enc.lpips.distance(pred_roi, gt_roi) if box else nan
    elif enc.lpips is not None:  # the ROI is the whole image: no background
        out["lpips_full"], out["lpips_bg"] = enc.lpips.distance(pred, gt), nan
        out["lpips_roi"] = enc.lpips.distance(pred_roi, gt_roi) if box else nan
    else:
        out["lpips_full"] = out["lpips_bg"] = out["lpips_roi"] = nan
    out["removal"] = embodied.removal(pred, roi)
    out["struct_fidelity"] = embodied.struct_fidelity(enc.dinov2, pred, gt, roi) if enc.dinov2 else nan
    de = embodied.delta_e_lab(pred, gt, items.robot_mask)
    out["delta_e"] = de
    out["id_lab"] = embodied.lab_score(de, cfg.lab_tau)
    if enc.clip is not None and items.refs:
        out["id_ref"] = embodied.ref_score(enc.clip, pred, items.robot_mask, items.refs, items.ref_masks)
    else:
        out["id_ref"] = nan
    out["id_fidelity"] = embodied.id_fidelity(out["id_ref"], out["id_lab"], cfg.id_lambda)
    if enc.lpips is not None and items.object_mask is not None and items.object_mask.any():
        contact = embodied.contact_region(items.object_mask, roi, cfg)
        out["interaction"] = embodied.interaction(enc.lpips, src, pred, contact) if contact.any() else nan
    else:
        out["interaction"] = nan
    feats: dict[str, np.ndarray] = {}
    if enc.inception is not None:
        ims = [pred, gt] + ([pred_roi, gt_roi] if box else [])
        e = enc.inception.embed(ims)
        feats = {"full_pred": e[0], "full_gt": e[1]}
        if box:
            feats.update(roi_pred=e[2], roi_gt=e[3])
    return out, feats


def _without_gt(items: ItemImages, enc: Encoders, cfg: EmbodiedConfig, roi: np.ndarray) -> dict:
    out = {m: float("nan") for m in METRICS if m not in ("vlm_sc", "vlm_pq", "vlm")}
    out.update({k: float("nan") for k in EXTRAS})
    out["removal"] = embodied.removal(items.pred, roi)
    if enc.clip is not None and items.refs:
        out["id_ref"] = embodied.ref_score(enc.clip, items.pred, items.robot_mask, items.refs, items.ref_masks)
    if enc.lpips is not None and items.object_mask is not None and items.object_mask.any():
        contact = embodied.contact_region(items.object_mask, roi, cfg)
        out["interaction"] = embodied.interaction(enc.lpips, items.src, items.pred, contact) if contact.any() else float("nan")
    return out
