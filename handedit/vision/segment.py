"""Hand and hand-arm segmentation, classical: keypoint-seeded GrabCut with a skin model.

Why this shape: the pipeline already has 21 hand keypoints per frame, so the hand's
skeleton (drawn thin) is a near-certain foreground seed and its hull bounds where the
hand can be. GrabCut then learns foreground/background colour mixtures per frame and
snaps to the real boundary. The forearm is not in the keypoints: it is searched in a
corridor from the wrist along the forearm direction (away from the knuckles) up to the
frame border and grown by the skin model; where the source tracks the arm in 3-D (EgoDex:
elbow, shoulder), the whole arm in view, skin or sleeve, is cut inside its projected
capsules instead (``_segment_arm``, ``handedit.vision.arm``). Where it does not (a video, the MANO
datasets) and the skin-grown arm stops inside the view (an arm always leaves the frame: a sleeve
starts there), the arm is followed by contrast with its flanks, not by colour, and cut with
GrabCut along that ray (``_segment_untracked_arm``). Without keypoints (a raw video) the skin
model alone proposes the largest skin components and GrabCut refines them; the hand is
then split from the arm at the narrowest point (the wrist) of the component's width
profile, which is a heuristic, so these frames get a lower confidence.

Temporal consistency across the chunk comes from (1) one skin model fitted to the
whole chunk, and (2) blending each frame's soft mask with its neighbours', warped by the
similarity transform between their keypoints (identity without keypoints).

Masks are computed at a working resolution (``work_max_side``) and brought back to full
resolution with a guided filter, which puts the edge on the image's real edge.

Confidence proxy (``SegmentResult.confidence``, in [0, 1]; not a calibrated probability):
    with keypoints:    0.3 * kp_cover + 0.45 * skin + 0.25 * stability
    without keypoints: no_keypoint_factor * (0.5 * skin + 0.5 * stability)
where ``kp_cover`` is the fraction of valid in-image keypoints that fall inside the
hand-arm mask (dilated by 2 px at working resolution), ``skin`` the fraction of the
hand mask inside the generic skin-chroma box (``skin.prior_rule``; deliberately not the
chunk-fitted model, which is fitted to the seeds and would confirm wrong keypoints;
gloved hands therefore score low and go to review), and ``stability`` the mean IoU of the
hand-arm mask with its warped neighbours in the chunk (0.75, "unknown", for a frame
without usable neighbours). Skin weighs most because keypoint seeds make ``kp_cover``
high almost by construction, even when the keypoints are wrong.
Frames below ``min_confidence`` (default 0.5) get ``Reason.LOW_CONFIDENCE``. Why 0.5 for
the proxy and not the paper's 0.75: on the synthetic oracle clips (exact masks) frames
with hand IoU >= 0.7 score 0.8-0.99, and wrong-keypoint / gloved frames fall to 0.3-0.5
(tests/test_vision.py), so 0.5 separates them; 0.75 is kept for a model's own score.

With ``method="onnx"`` and ``model_path`` a SAM-style model replaces all of this
(``handedit.models.segmenter``: contract, prompting, export notes); its score is checked
against ``min_model_confidence`` (0.75, the paper's threshold).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, ClassVar, Literal

import cv2
import numpy as np
import pydantic

from handedit.models.runtime import OnnxRuntime
from handedit.camera import Intrinsics, project
from handedit.keypoints import MCPS, N_JOINTS, PARENT, WRIST
from handedit.metrics.similarity import bbox
from handedit.vision.arm import capsule, clip_near, tracked
from handedit.vision.masks import disk, grow
from handedit.reasons import STATUS_DTYPE, Reason, per_frame
from handedit.vision.skin import SkinModel, colour_gaussian, gaussian_loglik, prior_rule, to_ycrcb

_TIP_JOINTS = frozenset((4, 8, 12, 16, 20))
_UNKNOWN_STABILITY = 0.75  # stability term for a frame without usable neighbours


class SegmentConfig(pydantic.BaseModel):
    VERSION: ClassVar[int] = 8  # 8: hand_reach (the hand's mask bounded per bone)
    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    method: Literal["classical", "onnx"] = "classical"
    model_path: str | None = None  # ONNX segmenter (method="onnx"), see handedit.models.segmenter
    onnx: OnnxRuntime = OnnxRuntime()  # how the model runs (providers, threads): part of the key
    min_model_confidence: float = pydantic.Field(0.75, ge=0, le=1)  # paper's QC threshold for a model's score
    work_max_side: int = pydantic.Field(480, ge=64)  # processing resolution (longest side)
    grabcut_iters: int = pydantic.Field(3, ge=1)
    grabcut_coarse_px: int = pydantic.Field(20_000, ge=0, description="GrabCut boxes larger than this are cut at half size "
                                            "first, then refined at full size near that boundary only")
    grabcut_band_px: int = pydantic.Field(4, ge=1, description="the refined band's half-width (working pixels)")
    min_keypoints: int = pydantic.Field(6, ge=3)  # valid joints (wrist included) to seed a frame
    skin_threshold: float = pydantic.Field(0.3, gt=0, lt=1)  # skin prob that marks "probably hand"
    roi_margin: float = 0.6  # hand region = keypoint hull grown by this x hand scale
    hand_reach: float = pydantic.Field(0.6, ge=0, description="the hand's mask ends this far past each bone, x the bone's "
                                       "projected length (0: unbounded): an object the fingers reach toward stays out")
    forearm_width: float = 1.0  # forearm corridor width, x hand scale
    arm_search_deg: float = pydantic.Field(60.0, ge=0, le=90)  # forearm direction searched this far around the keypoint guess
    colour_gate: bool = True  # "probably hand" also needs this frame's hand colour (see _handlike)
    wrist_margin: float = -0.1  # hand/arm cut this far (x hand scale) past the wrist joint; <0: proximal palm edge lies before it
    temporal_weight: float = pydantic.Field(0.2, ge=0, le=0.5)  # weight of each neighbour's soft mask
    guided_eps: float = pydantic.Field(0.1, gt=0)  # guided-filter regulariser, in units of full intensity
    min_area_frac: float = 0.001  # masks / skin components smaller than this fraction of the frame are empty
    max_components: int = pydantic.Field(2, ge=1)  # hands (arms) kept without keypoints
    wrist_factor: float = 1.4  # without keypoints: wrist cut this many palm radii past the palm
    blank_std: float = 2.0  # grey-level std below which a frame is blank
    min_confidence: float = 0.5
    seed_min_skin: float = pydantic.Field(0.1, ge=0, lt=1)  # skeleton seeds below this skin prob are not "sure"
    skin_gate: float = pydantic.Field(0.02, ge=0, lt=1)  # keypoint frames: fg pixels below this skin prob are dropped
    no_keypoint_factor: float = pydantic.Field(0.8, gt=0, le=1)
    # a tracked arm (the source's 3-D wrist, elbow, shoulder): capsule radii in metres (_segment_arm)
    arm_core_m: float = pydantic.Field(0.02, gt=0, description="sure arm: this close to the limb's axis")
    arm_core_start_m: float = pydantic.Field(0.04, ge=0, description="the sure core starts this far up from the wrist")
    arm_inner_m: float = pydantic.Field(0.05, gt=0, description="probably arm (a forearm with its sleeve)")
    arm_outer_m: float = pydantic.Field(0.12, gt=0, description="probably background out to here, background beyond")
    # an untracked arm (a video, the MANO datasets) whose skin stops inside the view: a sleeve (_segment_untracked_arm)
    untracked_arm: bool = True
    arm_contrast: float = pydantic.Field(14.0, gt=0, description="Lab distance from both flanks that marks a point as arm")
    arm_flank: float = pydantic.Field(1.0, gt=0, description="the flanks lie this far aside (x hand scale)")
    arm_min_votes: float = pydantic.Field(0.6, ge=0, le=1, description="share of a ray's points that must differ")

    @pydantic.model_validator(mode="after")
    def _model_needs_path(self) -> "SegmentConfig":
        if self.method == "onnx" and not self.model_path:
            raise ValueError("segment: method='onnx' needs model_path (an ONNX segmenter)")
        return self


@dataclass
class SegmentResult:
    hand_mask: np.ndarray  # (n,S,H,W) bool: wrist and distal, per hand
    handarm_mask: np.ndarray  # (n,S,H,W) bool: hand plus forearm, per hand
    confidence: np.ndarray  # (n,S) float32, see the module docstring
    hand_status: np.ndarray  # (n,S) int16 Reason per hand (ABSENT: not in view)
    status: np.ndarray  # (n,) int16: OK where any hand is OK (handedit.reasons.per_frame)
    method: str

    @property
    def union(self) -> tuple[np.ndarray, np.ndarray]:
        """(hand, hand-arm) masks of all hands together (n,H,W): what restoration removes."""
        return self.hand_mask.any(1), self.handarm_mask.any(1)


# ---------------------------------------------------------------------------------------
# keypoint geometry (working-resolution pixels)


def _usable(pts: np.ndarray, valid: np.ndarray, shape: tuple[int, int], cfg: SegmentConfig) -> bool:
    if not valid[WRIST] or valid.sum() < cfg.min_keypoints:
        return False
    h, w = shape
    p = pts[valid]
    inside = (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
    return int(inside.sum()) >= 3


def _hand_scale(pts: np.ndarray, valid: np.ndarray) -> float:
    """Palm size in pixels: max of wrist->middle-MCP and index-MCP->pinky-MCP spans."""
    cands = []
    for a, b, k in ((WRIST, 9, 1.0), (5, 17, 1.25), (WRIST, 5, 1.0), (WRIST, 17, 1.1)):
        if valid[a] and valid[b]:
            cands.append(k * float(np.linalg.norm(pts[a] - pts[b])))
    if not cands:
        p = pts[valid]
        cands.append(0.5 * float(np.linalg.norm(p.max(0) - p.min(0))))
    return max(4.0, max(cands))


def _forearm_dir(pts: np.ndarray, valid: np.ndarray) -> np.ndarray | None:
    """Unit vector from the knuckles through the wrist (points up the forearm)."""
    knuckles = [j for j in MCPS if valid[j]]
    ref = pts[knuckles].mean(0) if knuckles else pts[valid].mean(0)
    d = pts[WRIST] - ref
    n = float(np.linalg.norm(d))
    return d / n if n > 1e-3 else None


def _ipt(p: np.ndarray) -> tuple[int, int]:
    return int(round(float(p[0]))), int(round(float(p[1])))


def _draw_skeleton(shape: tuple[int, int], pts: np.ndarray, valid: np.ndarray, thickness: int, tip_frac: float) -> np.ndarray:
    """Bones as lines; tip bones stop at ``tip_frac`` so seeds stay off the boundary."""
    m = np.zeros(shape, np.uint8)
    for j in range(1, N_JOINTS):
        p = PARENT[j]
        if valid[j] and valid[p]:
            end = pts[p] + tip_frac * (pts[j] - pts[p]) if j in _TIP_JOINTS else pts[j]
            cv2.line(m, _ipt(pts[p]), _ipt(end), 1, max(1, thickness), cv2.LINE_8)
    palm = [j for j in (WRIST, 1, 5, 9, 13, 17) if valid[j]]
    if len(palm) >= 3:
        hull = cv2.convexHull(np.round(pts[palm]).astype(np.int32))
        cv2.fillConvexPoly(m, hull, 1)
    return m.astype(bool)


def _hand_reach(shape: tuple[int, int], pts: np.ndarray, valid: np.ndarray, frac: float, floor_px: float) -> np.ndarray:
    """Where a hand's pixels may lie: each bone a capsule of radius ``frac`` x its own
    projected length (at least ``floor_px``) and the palm's hull, so the region is narrow
    around fingers far from the lens and wide around a palm close to it."""
    m = np.zeros(shape, np.uint8)
    for j in range(1, N_JOINTS):
        p = PARENT[j]
        if valid[j] and valid[p]:
            r = int(round(max(frac * float(np.linalg.norm(pts[j] - pts[p])), floor_px)))
            cv2.line(m, _ipt(pts[p]), _ipt(pts[j]), 1, 2 * r + 1)
            for q in (pts[p], pts[j]):
                cv2.circle(m, _ipt(q), r, 1, -1)
    palm = [j for j in (WRIST, 1, 5, 9, 13, 17) if valid[j]]
    if len(palm) >= 3:
        cv2.fillConvexPoly(m, cv2.convexHull(np.round(pts[palm]).astype(np.int32)), 1)
    return m.astype(bool)


def _half_plane(shape: tuple[int, int], origin: np.ndarray, direction: np.ndarray, offset: float) -> np.ndarray:
    """Pixels with (p - origin) . direction <= offset (the distal side of the wrist line)."""
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    return (xs - origin[0]) * direction[0] + (ys - origin[1]) * direction[1] <= offset


# ---------------------------------------------------------------------------------------
# per-frame segmentation at working resolution


def _grabcut(bgr: np.ndarray, init: np.ndarray, cfg: SegmentConfig, coarse_to_fine: bool = True) -> np.ndarray:
    """GrabCut on the bounding box of the uncertain region; returns a bool fg mask. A box of
    more than ``cfg.grabcut_coarse_px`` pixels is cut coarse to fine (``_coarse_to_fine``)
    when the caller's seeds allow (the keypoint skeleton; from the skin components' seeds,
    without keypoints, the coarse cut fell below the no-keypoint hand IoU floor of 0.65)."""
    unsure = init != cv2.GC_BGD
    fg0 = (init == cv2.GC_FGD) | (init == cv2.GC_PR_FGD)
    if not unsure.any() or not fg0.any():
        return fg0
    ys, xs = np.nonzero(unsure)
    h, w = init.shape
    pad = max(8, int(0.1 * max(np.ptp(ys), np.ptp(xs))))
    y0, y1 = max(0, ys.min() - pad), min(h, ys.max() + pad + 1)
    x0, x1 = max(0, xs.min() - pad), min(w, xs.max() + pad + 1)
    m = init[y0:y1, x0:x1].copy()
    bg_any = ((m == cv2.GC_BGD) | (m == cv2.GC_PR_BGD)).any()
    if not bg_any:
        return fg0
    img = np.ascontiguousarray(bgr[y0:y1, x0:x1])
    try:
        fine = coarse_to_fine and m.size > cfg.grabcut_coarse_px
        fg = _coarse_to_fine(img, m, cfg) if fine else _cut(img, m, cfg.grabcut_iters)
    except cv2.error:  # degenerate colour statistics: keep the initial proposal
        return fg0
    out = np.zeros_like(fg0)
    out[y0:y1, x0:x1] = fg
    return out


def _colour_models() -> tuple[np.ndarray, np.ndarray]:
    """Empty (background, foreground) GMM buffers in OpenCV's layout, for grabCut to fill."""
    return np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)


def _cut(img: np.ndarray, labels: np.ndarray, iters: int, models: tuple[np.ndarray, np.ndarray] | None = None,
         frozen: bool = False) -> np.ndarray:
    """GrabCut from the labels (updated in place); the bool foreground. The colour models it
    learns are written into ``models`` when given; ``frozen``: one graph cut with ``models``
    as they are, not relearned."""
    bgd, fgd = models if models is not None else _colour_models()
    mode = cv2.GC_EVAL_FREEZE_MODEL if frozen else cv2.GC_INIT_WITH_MASK
    cv2.grabCut(img, labels, None, bgd, fgd, 1 if frozen else iters, mode)
    return (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)


def _coarse_to_fine(img: np.ndarray, labels: np.ndarray, cfg: SegmentConfig) -> np.ndarray:
    """GrabCut at half size, then one full-size graph cut only within ``grabcut_band_px`` of
    that cut's boundary, in the band's box (everything farther keeps the coarse label), with
    the colour models the coarse cut learned over the whole box. Most of a box is background
    far from the hand: the full-size graph is spent where the boundary is. Relearning the
    models in the band's box (k-means, then two learn-and-cut rounds) cost 24 of the 44 ms
    per frame and fitted them to pixels the cut can no longer change.
    Demo clips (640x480, 480 px working size): hand IoU 0.892 -> 0.895, hand-arm 0.949 -> 0.951,
    segment 226 -> 137 ms per frame; frozen models: hand IoU 0.895 -> 0.901, hand-arm
    0.950 -> 0.955, segment 64 -> 49 ms per frame (an idle machine)."""
    h, w = labels.shape
    sh, sw = (h + 1) // 2, (w + 1) // 2
    small = cv2.resize(img, (sw, sh), interpolation=cv2.INTER_AREA)
    blocks = np.pad(labels, ((0, 2 * sh - h), (0, 2 * sw - w)), mode="edge").reshape(sh, 2, sw, 2)
    coarse_labels = blocks[:, 0, :, 0].copy()
    coarse_labels[(blocks == cv2.GC_PR_FGD).any(axis=(1, 3)) & (coarse_labels != cv2.GC_FGD)] = cv2.GC_PR_FGD
    coarse_labels[(blocks == cv2.GC_FGD).any(axis=(1, 3))] = cv2.GC_FGD  # seeds are thin: a block with one keeps it
    models = _colour_models()
    coarse = _cut(small, coarse_labels, cfg.grabcut_iters, models)
    coarse = cv2.resize(coarse.view(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    band = grow(coarse, cfg.grabcut_band_px) & grow(~coarse, cfg.grabcut_band_px)
    decided = ~band & (labels != cv2.GC_BGD) & (labels != cv2.GC_FGD)
    labels[decided & coarse] = cv2.GC_FGD
    labels[decided & ~coarse] = cv2.GC_BGD
    fg = (coarse & (labels != cv2.GC_BGD)) | (labels == cv2.GC_FGD)
    win = bbox(band, 8)
    if win is not None:
        sub = np.ascontiguousarray(labels[win])
        fgs, bgs = (sub == cv2.GC_FGD) | (sub == cv2.GC_PR_FGD), (sub == cv2.GC_BGD) | (sub == cv2.GC_PR_BGD)
        if fgs.any() and bgs.any():
            fg[win] = _cut(np.ascontiguousarray(img[win]), sub, 1, models, frozen=True)
    return fg


def _keep_touching(mask: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Connected components of ``mask`` that touch ``seeds``."""
    n, lab = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return mask
    keep = np.unique(lab[seeds & mask])
    keep = keep[keep > 0]
    return np.isin(lab, keep)


@dataclass
class _KpFrame:
    pts: np.ndarray  # (21,2) working px
    valid: np.ndarray  # (21,) bool
    scale: float
    forearm: np.ndarray | None
    limb: np.ndarray | None = None  # (m,3) camera frame: wrist -> elbow -> ... when the source tracks the arm


def _handlike(ycc: np.ndarray, sure: np.ndarray, hand_roi: np.ndarray, s: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray] | None:
    """Whether pixels (rows, cols) look like *this* hand's colour more than its surroundings'.

    A 3-D YCrCb Gaussian of this frame's (skin-gated) seed pixels against one of the
    pixels around the hand's region: a skin-coloured table passes a chroma test but
    usually differs in brightness or saturation, and this test sees that. Evaluated only
    at the pixels asked about (the candidate foreground, the forearm rays), not the frame.
    """
    ring = grow(hand_roi, 0.5 * s) & ~hand_roi
    if sure.sum() < 20 or ring.sum() < 20:
        return None
    hand, around = (colour_gaussian(ycc[m].astype(np.float32), 9.0) for m in (sure, ring))

    def at(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        x = ycc[rows, cols].astype(np.float32)
        return gaussian_loglik(x, hand, np.float32) > gaussian_loglik(x, around, np.float32)

    return at


def _arm_direction(handlike: Callable[[np.ndarray, np.ndarray], np.ndarray] | None, kp: _KpFrame, cfg: SegmentConfig,
                   shape: tuple[int, int]) -> np.ndarray | None:
    """Forearm direction measured in the image, or the keypoint guess when the image is unsure.

    Knuckles->wrist only approximates the forearm: a flexed wrist (any grasp) bends it by
    tens of degrees, and a corridor along the guess then misses the arm. Rays from the
    wrist within ``arm_search_deg`` of the guess vote with their fraction of hand-like
    pixels (``_handlike``) over the first ``2 x hand scale``.
    """
    if kp.forearm is None or handlike is None:
        return kp.forearm
    s = kp.scale
    h, w = shape
    base = np.arctan2(kp.forearm[1], kp.forearm[0])
    r = np.linspace(0.4 * s, 2.0 * s, 24)
    best, best_dir = -1.0, kp.forearm
    for a in np.deg2rad(np.arange(-cfg.arm_search_deg, cfg.arm_search_deg + 1, 5.0)):
        d = np.array([np.cos(base + a), np.sin(base + a)])
        p = kp.pts[WRIST] + r[:, None] * d
        inside = (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
        if inside.sum() < 4:
            continue
        q = np.clip(np.round(p[inside]).astype(int), 0, [w - 1, h - 1])
        score = float(handlike(q[:, 1], q[:, 0]).mean()) - 0.002 * abs(float(np.rad2deg(a)))
        if score > best:
            best, best_dir = score, d
    return best_dir if best >= 0.5 else kp.forearm


def _segment_arm(bgr: np.ndarray, hand_fg: np.ndarray, kp: _KpFrame, intr: Intrinsics, cfg: SegmentConfig,
                 others: np.ndarray | None) -> np.ndarray:
    """The tracked arm in view, skin or cloth: GrabCut inside the projected 3-D capsules.

    A sleeve is not skin, so nothing here asks for skin colour: the arm's core (a thin
    capsule past the wrist) and the hand are sure foreground, a forearm-wide capsule is
    probably foreground, a wider one (sleeves, keypoint error) probably background, and
    everything beyond is background. The colour models GrabCut learns from these decide
    where the sleeve ends (``handedit.vision.arm`` for the capsules)."""
    shape = hand_fg.shape
    outer = capsule(kp.limb, intr, cfg.arm_outer_m, shape)
    if not outer.any():
        return hand_fg
    core = capsule(kp.limb, intr, cfg.arm_core_m, shape, start_m=cfg.arm_core_start_m) & ~hand_fg
    if not core.any():  # the forearm leaves the view right past the wrist: seed from the wrist on
        core = capsule(kp.limb, intr, cfg.arm_core_m, shape) & ~hand_fg
    if not core.any():
        return hand_fg
    return _cut_arm(bgr, hand_fg, outer, capsule(kp.limb, intr, cfg.arm_inner_m, shape), core, cfg, others)


def _cut_arm(bgr: np.ndarray, known: np.ndarray, outer: np.ndarray, inner: np.ndarray, core: np.ndarray,
             cfg: SegmentConfig, others: np.ndarray | None) -> np.ndarray:
    """GrabCut of an arm, tracked or not: ``known`` (the hand, or the hand and its skin) and
    ``core`` are sure arm, ``inner`` probably arm, ``outer`` probably background, background
    beyond; ``others`` (the other hands) background. ``known`` is arm too, but its skin must
    not teach the arm's colour model (a beige table is skin-like): it takes the core's median
    colour and stays sure foreground. Returns the arm's components touching the seeds."""
    init = np.full(known.shape, cv2.GC_BGD, np.uint8)
    init[outer] = cv2.GC_PR_BGD
    init[inner] = cv2.GC_PR_FGD
    init[core] = cv2.GC_FGD
    img = bgr.copy()
    img[known] = np.median(bgr[core], axis=0).astype(np.uint8)
    init[known] = cv2.GC_FGD
    if others is not None:
        init[others] = cv2.GC_BGD
    fg = _grabcut(img, init, cfg)
    fg = cv2.morphologyEx(fg.astype(np.uint8), cv2.MORPH_CLOSE, disk(1)).astype(bool)
    if others is not None:
        fg &= ~others
    return _keep_touching(fg | known, (core & fg) | known)


def _in_view(p: np.ndarray, w: int, h: int) -> np.ndarray:
    """(m,) bool: points (m,2) that round to a pixel of a w x h image."""
    return (p[:, 0] >= 0) & (p[:, 0] <= w - 1) & (p[:, 1] >= 0) & (p[:, 1] <= h - 1)


def _touches_border(mask: np.ndarray) -> bool:
    return bool(mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())


def _arm_ray(lab: np.ndarray, kp: _KpFrame, cfg: SegmentConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """The untracked arm's ray from the wrist, found by contrast, not colour: (direction,
    points along it that differ from both flanks), or None when no ray looks like an arm.

    An arm, skin or sleeve, is a band from the wrist to the frame border that differs from
    what lies on both sides of it; a ray over the table does not. Rays within
    ``arm_search_deg`` of the knuckles->wrist guess vote with the share of their points whose
    colour is ``arm_contrast`` (Lab) from both flanks (``arm_flank`` x hand scale aside)."""
    s = kp.scale
    h, w = lab.shape[:2]
    base = np.arctan2(kp.forearm[1], kp.forearm[0])
    r = np.arange(0.5 * s, float(h + w), 0.25 * s)
    best, best_score = None, cfg.arm_min_votes
    for a in np.deg2rad(np.arange(-cfg.arm_search_deg, cfg.arm_search_deg + 1, 5.0)):
        d = np.array([np.cos(base + a), np.sin(base + a)])
        p = kp.pts[WRIST] + r[:, None] * d
        inside = _in_view(p, w, h)
        n_in = int(np.argmin(inside)) if not inside.all() else len(inside)
        if n_in < 4 or not inside[0]:
            continue
        p = p[:n_in]
        centre = lab[np.round(p[:, 1]).astype(int), np.round(p[:, 0]).astype(int)]
        contrast = np.full(n_in, np.inf, np.float32)
        for side in (-1.0, 1.0):
            f = p + side * cfg.arm_flank * s * np.array([-d[1], d[0]])
            ok = _in_view(f, w, h)
            fc = lab[np.round(f[ok, 1]).astype(int), np.round(f[ok, 0]).astype(int)]
            contrast[ok] = np.minimum(contrast[ok], np.linalg.norm(centre[ok] - fc, axis=1))
        differs = contrast >= cfg.arm_contrast  # (no flank in view: the band fills the view across)
        score = float(differs.mean()) - 0.002 * abs(float(np.rad2deg(a)))
        if score > best_score:
            best, best_score = (d, p[differs]), score
    return best


def _segment_untracked_arm(bgr: np.ndarray, fg: np.ndarray, hand: np.ndarray, kp: _KpFrame, cfg: SegmentConfig,
                           others: np.ndarray | None) -> np.ndarray:
    """The arm beyond where the skin ends, where the source does not track it (a video, the
    MANO datasets): a sleeve is not skin, so the skin-grown arm stops at its cuff.

    An arm leaves the frame: a hand-arm mask whose arm part stays inside the view has lost
    it. Then the arm's ray is found by contrast (``_arm_ray``), its verified points are sure
    arm, a forearm-wide band along it probably arm, a wider one probably background, and
    GrabCut's colour models decide where the sleeve is, as for a tracked arm (``_cut_arm``)."""
    if _touches_border(fg & ~hand):
        return fg
    lab = cv2.cvtColor(cv2.medianBlur(bgr, 5), cv2.COLOR_BGR2LAB).astype(np.float32)
    ray = _arm_ray(lab, kp, cfg)
    if ray is None:
        return fg
    d, verified = ray
    s, shape = kp.scale, fg.shape
    wrist = kp.pts[WRIST]
    far = wrist + d * float(shape[0] + shape[1])

    def band(width: float) -> np.ndarray:
        m = np.zeros(shape, np.uint8)
        cv2.line(m, _ipt(wrist), _ipt(far), 1, max(2, int(round(width * s))))
        return m.astype(bool)

    core = np.zeros(shape, np.uint8)
    for p in verified:
        cv2.circle(core, _ipt(p), max(1, int(round(0.1 * s))), 1, -1)
    core = core.astype(bool) & ~fg
    if not core.any():
        return fg
    return _cut_arm(bgr, fg, band(2 * cfg.arm_flank + cfg.forearm_width), band(cfg.forearm_width), core, cfg, others)


def _segment_kp(bgr: np.ndarray, ycc: np.ndarray, prob: np.ndarray, kp: _KpFrame, cfg: SegmentConfig,
                others: np.ndarray | None = None, intr: Intrinsics | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(handarm, hand) bool masks for a frame seeded by its keypoints.

    ``others``: pixels of the frame's other hands (their skeletons), definite background
    here so one hand's mask never swallows the other. With a tracked arm (``kp.limb`` and the
    working-resolution ``intr``) the forearm is not searched by skin colour: the arm is cut
    inside its projected 3-D capsules whatever its colour (``_segment_arm``: sleeves).
    """
    shape = prob.shape
    s = kp.scale
    sure = _draw_skeleton(shape, kp.pts, kp.valid, int(round(0.08 * s)), tip_frac=0.7)
    sure = cv2.erode(sure.astype(np.uint8), disk(0.04 * s)).astype(bool) | _draw_skeleton(
        shape, kp.pts, kp.valid, 1, tip_frac=0.7
    )
    # Keypoints of fingers wrapped behind a grasped object project onto the object: seeding
    # those pixels would teach GrabCut the object's colours and it would swallow the object.
    # Seeds count only where the chunk's skin model agrees.
    skin_seed = prob >= cfg.seed_min_skin
    if (sure & skin_seed).sum() >= 0.2 * sure.sum():
        sure &= skin_seed
    likely = _draw_skeleton(shape, kp.pts, kp.valid, int(round(0.3 * s)), tip_frac=1.0)
    roi = grow(likely, cfg.roi_margin * s)
    corridor = np.zeros(shape, np.uint8)
    handlike = _handlike(ycc, sure, roi, s)
    tracked = kp.limb is not None and intr is not None
    arm_dir = kp.forearm if tracked or cfg.arm_search_deg <= 0 else _arm_direction(handlike, kp, cfg, shape)
    if arm_dir is not None:
        far = kp.pts[WRIST] + arm_dir * float(shape[0] + shape[1])
        cv2.line(corridor, _ipt(kp.pts[WRIST]), _ipt(far), 1, max(2, int(round(cfg.forearm_width * s))))
        roi |= grow(corridor, 0.3 * s)

    init = np.full(shape, cv2.GC_BGD, np.uint8)
    init[roi] = cv2.GC_PR_BGD
    skin = prob >= cfg.skin_threshold
    init[roi & skin] = cv2.GC_PR_FGD
    # Thick bones over clearly non-skin pixels would teach GrabCut's foreground model the
    # background's colours (it then swallows whole regions): those stay "probably bg".
    init[likely & (prob >= 0.05)] = cv2.GC_PR_FGD
    if handlike is not None and cfg.colour_gate:
        # (this frame's hand colour, not just skin chroma: keeps a skin-coloured table out)
        ys, xs = np.nonzero(init == cv2.GC_PR_FGD)
        other = ~handlike(ys, xs)
        init[ys[other], xs[other]] = cv2.GC_PR_BGD
    init[sure] = cv2.GC_FGD
    init[roi & (prob < cfg.skin_gate) & (init != cv2.GC_FGD)] = cv2.GC_BGD
    if others is not None:
        init[others & ~sure] = cv2.GC_BGD
    fg = _grabcut(bgr, init, cfg)
    fg = cv2.morphologyEx(fg.astype(np.uint8), cv2.MORPH_CLOSE, disk(1)).astype(bool)
    fg &= (prob >= cfg.skin_gate) | sure
    if others is not None:
        fg &= ~others
    if cfg.hand_reach > 0:
        # A hand ends a little past its bones: GrabCut's colour model swallows a skin-coloured
        # object the fingers reach toward (a white cup under warm light) unless it is cut here
        # (per bone: one palm scale is too coarse when the wrist is much nearer the lens).
        # The arm's side of the wrist is the arm's own cut's to bound.
        near = _hand_reach(shape, kp.pts, kp.valid, cfg.hand_reach, 0.1 * s)
        if kp.forearm is not None:
            near |= ~_half_plane(shape, kp.pts[WRIST], kp.forearm, cfg.wrist_margin * s)
        fg &= near
    fg = _keep_touching(fg, sure)
    if kp.forearm is None:
        return fg, fg
    hand = fg & _half_plane(shape, kp.pts[WRIST], kp.forearm, cfg.wrist_margin * s)
    if tracked:
        fg = _segment_arm(bgr, fg, kp, intr, cfg, others)
    elif cfg.untracked_arm:
        fg = _segment_untracked_arm(bgr, fg, hand, kp, cfg, others)
    return fg, hand


def _split_component(comp: np.ndarray, wrist_factor: float) -> np.ndarray:
    """Hand part of one skin component without keypoints (classic palm-circle cut).

    The arm enters from the frame border, so the component's principal axis, oriented
    away from where it touches the border, points from the forearm to the fingers.
    Walking from the distal end, fingers are thin and the palm is the first place where
    the largest inscribed circle (distance transform) reaches 80% of its maximum; the
    wrist is ``wrist_factor`` palm radii further toward the arm. A component that does
    not touch the border is all hand.
    """
    h, w = comp.shape
    ys, xs = np.nonzero(comp)
    border = (xs == 0) | (xs == w - 1) | (ys == 0) | (ys == h - 1)
    if border.sum() < 3 or len(xs) < 20:
        return comp
    pts = np.stack([xs, ys], 1).astype(np.float64)
    centre = pts.mean(0)
    evals, evecs = np.linalg.eigh(np.cov((pts - centre).T))
    axis = evecs[:, np.argmax(evals)]  # unit principal direction
    anchor = pts[border].mean(0)
    if (centre - anchor) @ axis < 0:
        axis = -axis  # now points from the border (arm) toward the fingers
    u = (pts @ axis).max() - pts @ axis  # 0 at the distal end, growing toward the arm
    dist = cv2.distanceTransform(np.pad(comp, 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1]
    dt = dist[ys, xs]
    bins = u.astype(int)
    prof = np.zeros(int(bins.max()) + 1)
    np.maximum.at(prof, bins, dt)
    prof = np.convolve(prof, np.ones(5) / 5.0, mode="same")
    palm_u = int(np.argmax(prof >= 0.8 * prof.max()))
    # the palm's circle: best radius within a palm radius past the first hit
    r = float(prof[palm_u : palm_u + int(prof[palm_u]) + 1].max())
    wrist_u = palm_u + wrist_factor * r
    if wrist_u >= u.max():
        return comp
    hand = np.zeros_like(comp)
    sel = u <= wrist_u
    hand[ys[sel], xs[sel]] = True
    return hand


def _segment_nokp(bgr: np.ndarray, ycc: np.ndarray, prob: np.ndarray, cfg: SegmentConfig) -> tuple[np.ndarray, np.ndarray]:
    shape = prob.shape
    area = shape[0] * shape[1]
    cand = ((prob >= 0.5 * (1 + cfg.skin_threshold)) | prior_rule(ycc)).astype(np.uint8)
    cand = cv2.morphologyEx(cand, cv2.MORPH_OPEN, disk(1))
    cand = cv2.morphologyEx(cand, cv2.MORPH_CLOSE, disk(2))
    n, lab, stats, _ = cv2.connectedComponentsWithStats(cand, connectivity=8)
    if n <= 1:
        empty = np.zeros(shape, bool)
        return empty, empty
    areas = stats[1:, cv2.CC_STAT_AREA]
    order = np.argsort(-areas)
    keep = [i + 1 for i in order[: cfg.max_components] if areas[i] >= max(cfg.min_area_frac * area, 0.25 * areas.max())]
    blobs = np.isin(lab, keep)
    if not blobs.any():
        return blobs, blobs
    diag = float(np.hypot(*shape))
    init = np.full(shape, cv2.GC_BGD, np.uint8)
    init[grow(blobs, 0.04 * diag)] = cv2.GC_PR_BGD
    init[blobs] = cv2.GC_PR_FGD
    core = cv2.erode(blobs.astype(np.uint8), disk(2)).astype(bool) & (prob >= 0.5)
    init[core] = cv2.GC_FGD
    fg = _grabcut(bgr, init, cfg, coarse_to_fine=False)
    fg = cv2.morphologyEx(fg.astype(np.uint8), cv2.MORPH_CLOSE, disk(1)).astype(bool)
    fg = _keep_touching(fg, core if core.any() else blobs)
    hand = np.zeros(shape, bool)
    n2, lab2 = cv2.connectedComponents(fg.astype(np.uint8), connectivity=8)
    for i in range(1, n2):
        comp = lab2 == i
        if comp.sum() >= cfg.min_area_frac * area:
            hand |= _split_component(comp, cfg.wrist_factor)
    return fg, hand


# ---------------------------------------------------------------------------------------
# chunk-level driver


def _fit_skin(ycc: list[np.ndarray], seeds: list[np.ndarray | None]) -> SkinModel:
    """One skin model for the chunk: keypoint seeds if any, else the prior rule's pixels."""
    rng = np.random.default_rng(0)
    samples = []
    for y, s in zip(ycc, seeds):
        if s is None or not s.any():
            continue
        # seeds on a grasped object (occluded fingers) are not skin: trust the prior rule's
        # pixels among them unless it rejects most (gloves, odd white balance)
        ok = s & prior_rule(y)
        samples.append(y[ok if ok.sum() >= 0.3 * s.sum() else s][:, 1:3])
    if not samples:
        samples = [y[prior_rule(y)][:, 1:3] for y in ycc]
    x = np.concatenate(samples) if samples else np.zeros((0, 2))
    if len(x) > 50_000:
        x = x[rng.choice(len(x), 50_000, replace=False)]
    return SkinModel.fit(x) or SkinModel.prior()


def _warp(mask: np.ndarray, A: np.ndarray | None) -> np.ndarray:
    if A is None:
        return mask
    h, w = mask.shape
    return cv2.warpAffine(mask, A, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def _kp_transform(a: _KpFrame | None, b: _KpFrame | None) -> np.ndarray | None:
    """Similarity taking frame a's keypoints onto frame b's (None: identity)."""
    if a is None or b is None:
        return None
    common = a.valid & b.valid
    if common.sum() < 3:
        return None
    A, _ = cv2.estimateAffinePartial2D(a.pts[common].astype(np.float32), b.pts[common].astype(np.float32))
    return A


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    u = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / u) if u else 1.0


def _upsample(soft: np.ndarray, guide: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """Full-resolution mask: the soft mask resized, then guided-filtered in its support's box.

    The guided filter's output is exactly 0 farther than 2 x radius from the support (its
    linear coefficients are 0 in every window without support), so the box grown by that
    gives the full frame's result."""
    h, w = guide.shape[:2]
    up = cv2.resize(soft.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    win = bbox(up > 0, 2 * radius + 2)
    if win is None:
        return np.zeros((h, w), bool)
    if hasattr(cv2, "ximgproc"):
        up[win] = cv2.ximgproc.guidedFilter(np.ascontiguousarray(guide[win]), np.ascontiguousarray(up[win]), radius,
                                            (eps * 255.0) ** 2)
    return up >= 0.5


def _split_overlaps(masks: list[np.ndarray | None], skeletons: list[np.ndarray | None]) -> list[np.ndarray | None]:
    """A pixel claimed by two hands goes to the one whose skeleton is nearer."""
    have = [k for k, m in enumerate(masks) if m is not None and skeletons[k] is not None]
    if len(have) < 2:
        return masks
    both = np.zeros(masks[have[0]].shape, np.int32)
    for k in have:
        both += masks[k]
    if not (both > 1).any():
        return masks
    dist = np.stack([cv2.distanceTransform((~skeletons[k]).astype(np.uint8), cv2.DIST_L2, 3) for k in have])
    owner = np.array(have)[np.argmin(dist, axis=0)]
    out = list(masks)
    for k in have:
        out[k] = masks[k] & ((both <= 1) | (owner == k))
    return out


def _frame_kp(pts: np.ndarray, valid: np.ndarray, limb: np.ndarray | None, intr: Intrinsics | None, shape,
              cfg: SegmentConfig) -> _KpFrame | None:
    if not _usable(pts, valid, shape, cfg):
        return None
    scale = _hand_scale(pts, valid)
    fore = _forearm_dir(pts, valid)
    line = None
    if limb is not None and intr is not None:
        part = tracked(limb)
        if len(part) >= 2:
            line = part
            seg = clip_near(line[0], line[1])  # the forearm's image direction, in front of the camera
            uv = None if seg is None else project(np.stack(seg), intr)
            d = None if uv is None else uv[1] - uv[0]
            if d is not None and np.isfinite(d).all() and np.linalg.norm(d) > 1e-3:
                fore = d / np.linalg.norm(d)
    return _KpFrame(np.nan_to_num(pts), valid.copy(), scale, fore, line)


def segment(
    frames: np.ndarray,
    keypoints_2d: np.ndarray | None,
    keypoints_valid: np.ndarray | None,
    cfg: SegmentConfig = SegmentConfig(),
    *,
    present: np.ndarray | None = None,
    limbs: np.ndarray | None = None,
    intr: Intrinsics | None = None,
) -> SegmentResult:
    """Per-hand hand and hand-arm masks for a chunk of frames (see the module doc).

    ``keypoints_2d`` (n,S,21,2) pixels and ``keypoints_valid`` (n,S,21): S hands per frame
    (None: no keypoints, one hand found by skin colour). ``present`` (n,S): sides in view
    (default: those with usable keypoints). ``limbs`` (n,S,m,3): the tracked arm as a
    camera-frame polyline wrist -> elbow -> shoulder (NaN past the last tracked joint), with
    the frames' ``intr``: the arm is then cut inside its projected capsules whatever its
    colour (sleeves), not searched by skin colour.
    """
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"segment: frames must be (n,H,W,3) uint8, got {frames.shape} {frames.dtype}")
    n, H, W = frames.shape[:3]
    if keypoints_2d is None or keypoints_valid is None:
        keypoints_2d = np.full((n, 1, N_JOINTS, 2), np.nan, np.float32)
        keypoints_valid = np.zeros((n, 1, N_JOINTS), bool)
        skin_only = True
    else:
        skin_only = False
    kp2d = np.asarray(keypoints_2d, dtype=np.float64)
    if kp2d.ndim != 4 or kp2d.shape[2:] != (N_JOINTS, 2):
        raise ValueError(f"segment: keypoints_2d must be (n,S,21,2), got {kp2d.shape}")
    S = kp2d.shape[1]
    kval = np.asarray(keypoints_valid, dtype=bool) & np.isfinite(kp2d).all(-1)
    if cfg.method == "onnx":
        from handedit.models.segmenter import segment_onnx

        per = [segment_onnx(frames, kp2d[:, k], kval[:, k], cfg) for k in range(S)]
        hands = _split_overlaps_all([p.hand_mask[:, 0] for p in per], kp2d, kval)
        arms = _split_overlaps_all([p.handarm_mask[:, 0] for p in per], kp2d, kval)
        hs = np.concatenate([p.hand_status for p in per], 1)
        if present is not None:
            hs[~np.asarray(present, bool)] = Reason.ABSENT
        return SegmentResult(np.stack(hands, 1), np.stack(arms, 1), np.concatenate([p.confidence for p in per], 1), hs,
                             per_frame(hs), per[0].method)

    s = min(1.0, cfg.work_max_side / max(H, W))
    ws = (max(1, int(round(W * s))), max(1, int(round(H * s))))
    small = [cv2.resize(f, ws, interpolation=cv2.INTER_AREA) if s < 1 else f for f in frames]
    ycc = [to_ycrcb(f) for f in small]
    bgr = [cv2.cvtColor(f, cv2.COLOR_RGB2BGR) for f in small]
    blank = np.array([float(y[..., 0].std()) < cfg.blank_std for y in ycc], bool)
    intr_s = None if limbs is None or intr is None else intr.scaled(*ws)
    limbs = None if intr_s is None else np.asarray(limbs, np.float64)

    kps: list[list[_KpFrame | None]] = []
    for i in range(n):
        row = []
        for k in range(S):
            ok = not blank[i] and (present is None or bool(present[i, k]))
            row.append(_frame_kp(kp2d[i, k] * s, kval[i, k], None if limbs is None else limbs[i, k], intr_s,
                                 ycc[i].shape[:2], cfg)
                       if ok else None)
        kps.append(row)
    # Without keypoints (one hand), the skin-components path finds it.
    use_skin = skin_only or (S == 1 and present is None)

    skel = [[_draw_skeleton(ycc[i].shape[:2], k.pts, k.valid, int(round(0.08 * k.scale)), 0.7) if k is not None else None
             for k in kps[i]] for i in range(n)]
    seeds = [np.any([sk for sk in row if sk is not None], axis=0) if any(sk is not None for sk in row) else None for row in skel]
    model = _fit_skin([y for y, b in zip(ycc, blank) if not b] or ycc, [sd for sd, b in zip(seeds, blank) if not b] or seeds)

    handarm = [[None] * S for _ in range(n)]
    hand = [[None] * S for _ in range(n)]
    for i in range(n):
        p = model.prob(ycc[i])
        if blank[i]:
            continue
        row = kps[i]
        if any(k is not None for k in row):
            thick = [grow(sk, 0.15 * row[k].scale) if sk is not None else None
                     for k, sk in enumerate(skel[i])]
            for k, kp in enumerate(row):
                if kp is None:
                    continue
                others = [t for j, t in enumerate(thick) if j != k and t is not None]
                a, b = _segment_kp(bgr[i], ycc[i], p, kp, cfg, np.any(others, axis=0) if others else None, intr_s)
                handarm[i][k], hand[i][k] = a, b
            handarm[i] = _split_overlaps(handarm[i], skel[i])
            hand[i] = [h & a if h is not None else None for h, a in zip(_split_overlaps(hand[i], skel[i]), handarm[i])]
        elif use_skin:
            handarm[i][0], hand[i][0] = _segment_nokp(bgr[i], ycc[i], p, cfg)

    # Temporal blending of soft masks with warped neighbours, per hand.
    wt = cfg.temporal_weight
    radius = max(2, int(np.ceil(2.0 / s)))
    out_hand = np.zeros((n, S, H, W), bool)
    out_arm = np.zeros((n, S, H, W), bool)
    conf = np.zeros((n, S), np.float32)
    hs = np.full((n, S), Reason.OK, STATUS_DTYPE)
    min_px = cfg.min_area_frac * H * W
    n_kp = 0
    for k in range(S):
        side_kps = [kps[i][k] for i in range(n)]
        n_kp += sum(x is not None for x in side_kps)
        prev_A = [None] + [_kp_transform(side_kps[i - 1], side_kps[i]) for i in range(1, n)]
        next_A = [_kp_transform(side_kps[i + 1], side_kps[i]) for i in range(n - 1)] + [None]
        for i in range(n):
            if blank[i]:
                hs[i, k] = Reason.BLANK_FRAME
                continue
            if handarm[i][k] is None:
                hs[i, k] = Reason.ABSENT if not use_skin or S > 1 else Reason.EMPTY_MASK
                continue
            acc_a = handarm[i][k].astype(np.float32)
            acc_h = hand[i][k].astype(np.float32)
            stability = _UNKNOWN_STABILITY
            if wt > 0:
                acc_a, acc_h = acc_a * (1 - 2 * wt), acc_h * (1 - 2 * wt)
                ious = []
                for j, A in ((i - 1, prev_A[i]), (i + 1, next_A[i])):
                    if 0 <= j < n and not blank[j] and handarm[j][k] is not None:
                        wa = _warp(handarm[j][k].astype(np.float32), A)
                        wh = _warp(hand[j][k].astype(np.float32), A)
                        ious.append(_iou(handarm[i][k], wa >= 0.5))
                    else:  # no neighbour: it votes like this frame
                        wa, wh = handarm[i][k].astype(np.float32), hand[i][k].astype(np.float32)
                    acc_a += wt * wa
                    acc_h += wt * wh
                stability = float(np.mean(ious)) if ious else _UNKNOWN_STABILITY
            soft_arm = cv2.GaussianBlur(acc_a, (3, 3), 0)
            soft_hand = cv2.GaussianBlur(acc_h, (3, 3), 0)
            arm_full = _upsample(soft_arm, frames[i], radius, cfg.guided_eps)
            hand_full = _upsample(soft_hand, frames[i], radius, cfg.guided_eps) & arm_full
            if hand_full.sum() < min_px:
                hs[i, k] = Reason.EMPTY_MASK
                continue
            out_arm[i, k], out_hand[i, k] = arm_full, hand_full
            arm_small, hand_small = soft_arm >= 0.5, soft_hand >= 0.5
            skin = float(prior_rule(ycc[i])[hand_small].mean()) if hand_small.any() else 0.0
            kp = kps[i][k]
            if kp is not None:
                grown = cv2.dilate(arm_small.astype(np.uint8), disk(2)).astype(bool)
                h, w = arm_small.shape
                pts = np.round(kp.pts[kp.valid]).astype(int)
                inside = (pts[:, 0] >= 0) & (pts[:, 0] < w) & (pts[:, 1] >= 0) & (pts[:, 1] < h)
                pts = pts[inside]
                cover = float(grown[pts[:, 1], pts[:, 0]].mean()) if len(pts) else 0.0
                conf[i, k] = 0.3 * cover + 0.45 * skin + 0.25 * stability
            else:
                conf[i, k] = cfg.no_keypoint_factor * (0.5 * skin + 0.5 * stability)
            if conf[i, k] < cfg.min_confidence:
                hs[i, k] = Reason.LOW_CONFIDENCE
    if S > 1:  # two upsampled masks can overlap again at their seam: the first side keeps it
        for i in range(n):
            taken = np.zeros((H, W), bool)
            for k in range(S):
                out_arm[i, k] &= ~taken
                out_hand[i, k] &= out_arm[i, k]
                taken |= out_arm[i, k]

    total = n * S
    if n_kp == total:
        method = "classical:grabcut+skin"
    elif n_kp == 0:
        method = "classical:skin-components+grabcut" if use_skin else "classical:no-hand"
    else:
        method = "classical:grabcut+skin|skin-components+grabcut" if use_skin else "classical:grabcut+skin"
    return SegmentResult(out_hand, out_arm, conf, hs, per_frame(hs), method)


def _split_overlaps_all(masks: list[np.ndarray], kp2d: np.ndarray, kval: np.ndarray) -> list[np.ndarray]:
    """Per-frame overlap split of per-side (n,H,W) masks by nearest skeleton (model path)."""
    if len(masks) < 2:
        return masks
    n, H, W = masks[0].shape
    out = [m.copy() for m in masks]
    for i in range(n):
        sk = [_draw_skeleton((H, W), np.nan_to_num(kp2d[i, k]), kval[i, k], 3, 1.0) if kval[i, k].sum() >= 3 else None
              for k in range(len(masks))]
        split = _split_overlaps([m[i] for m in masks], sk)
        for k in range(len(masks)):
            out[k][i] = split[k]
    return out
