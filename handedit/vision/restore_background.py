"""Background restoration behind the removed hand: propagate from other frames, then inpaint.

Why: in a video the background behind the hand is usually *seen* in another frame of
the window (the hand moves, the head camera moves slowly), and a real pixel beats any
hallucinated one. So for each target frame, other frames of the window are aligned to it
by a homography fitted to ORB features on their visible background (a plane-induced
model: exact for a rotating camera or a distant/planar scene, close enough for slow
egocentric motion), checked by their photometric error on the shared background, gain
corrected, and their unmasked pixels vote (per-pixel median when >= 3 frames saw the
pixel, else the temporally nearest one). What no frame of the window saw is then taken from
frames of the rest of the clip (``clip_sources``, given by the caller): a hand that holds
still for a second is never seen behind within the window, but usually is later. Only what
no frame saw is inpainted (OpenCV Telea by default, or the contrib ``xphoto`` FSR /
shift-map inpainters).

This is the classical stand-in for ProPainter (the paper's default); ``method="onnx"``
with ``model_path`` runs a learned video inpainter instead (``handedit.models.inpainter``
documents its contract). Both paths end with the same automatic checks (paper's QC
table): ``RESIDUE`` when skin-coloured pixels remain in the restored region beyond what
its surroundings show, and ``GHOSTING`` when the restored region disagrees with what an
adjacent frame (homography-aligned) saw there: the median absolute grey difference over
the pixels both know exceeds ``ghost_threshold`` (a double image or a smeared hand; a
static object revealed correctly agrees with its neighbours to a few grey levels).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import ClassVar, Literal, Sequence

import cv2
import numpy as np
import pydantic
import xxhash

from handedit.models.runtime import OnnxRuntime
from handedit.images import pixels
from handedit.lru import MISSING, Lru
from handedit.reasons import STATUS_DTYPE, Reason
from handedit.metrics.similarity import bbox
from handedit.vision.masks import grow
from handedit.vision.skin import prior_rule, to_ycrcb


class RestoreConfig(pydantic.BaseModel):
    VERSION: ClassVar[int] = 7  # 6: residue judged after compositing (the hole stored); 7: the rest of the clip fills what the window never saw
    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    method: Literal["classical", "onnx"] = "classical"
    model_path: str | None = None  # ONNX video inpainter (method="onnx")
    onnx: OnnxRuntime = OnnxRuntime()  # how the model runs (providers, threads): part of the key
    work_max_side: int = pydantic.Field(640, ge=32)  # model input size when the model's is dynamic
    window: int = pydantic.Field(12, ge=0)  # frames each side of a target the caller should provide
    max_sources: int = pydantic.Field(8, ge=0)  # frames of the window used per target (spread evenly)
    clip_sources: int = pydantic.Field(8, ge=0, description=(
        "frames from the rest of the clip (spread evenly over it) the caller should provide: they fill only the "
        "pixels no frame of the window saw (a hand that holds still), nearest in time first"))
    clip_min_unseen: float = pydantic.Field(0.05, ge=0, le=1, description=(
        "the rest of the clip is searched only when at least this share of the hole was never seen in the window "
        "(thin slivers inpaint well, and each later frame costs an alignment per target)"))
    clip_agree: float = pydantic.Field(12.0, gt=0, description=(
        "a pixel from the rest of the clip needs two of its frames within this mean |RGB difference| of the value "
        "taken (the scene changes over a clip: an arm passing by, a moved object); their fill is then brought to the "
        "local brightness of its surroundings (the hands' shadows, exposure drift)"))
    dilate_px: int = pydantic.Field(6, ge=0)  # mask margin: segmentation edges and soft shadows
    align: Literal["homography", "identity"] = "homography"
    homography_fit: Literal["ransac", "usac_fast"] = pydantic.Field("ransac", description=(
        "robust fit of the matched features. cv2.USAC_FAST takes a tenth of cv2.RANSAC's time per fit and restores "
        "the demo clips as well (hand-arm hole 27.61 against 27.52 dB, predicted masks), but on the EgoDex clips it "
        "propagated less (58.1 against 59.8 % of the hole) and left 11 against 8 of 96 frames with RESIDUE"))
    feature_max_side: int = 640  # ORB runs at this resolution
    min_inliers: int = 20
    max_align_error: float = 6.0  # median |grey difference| on shared background, else skip the frame
    align_check_step: int = pydantic.Field(4, ge=1, description="the alignment check samples every this many pixels "
                                           "(demo and EgoDex clips: the same backgrounds and statuses at 4 as at 2, in half the warps' time)")
    gain_compensation: bool = True
    inpaint: Literal["telea", "ns", "fsr_fast", "shiftmap"] = "telea"
    inpaint_radius: int = 5
    inpaint_scale: float = pydantic.Field(0.5, gt=0, le=1, description="Telea/NS fill more than inpaint_full_scale_px unseen "
                                          "pixels at this scale: a smooth fill either way, at half size a tenth of the time")
    inpaint_full_scale_px: int = pydantic.Field(4096, ge=0, description="fills up to this many pixels stay at full scale (a "
                                                "few ms; their edge detail is most of them)")
    residue_threshold: float = 0.25  # skin-coloured fraction of the restored region (above the ring's) -> RESIDUE
    residue_after_composite: bool = pydantic.Field(
        True, description="leave RESIDUE to composite, which judges only the restored pixels a robot leaves visible (a "
        "hand that barely moves is never seen behind, but its robot covers most of the hole); False: judge it here")
    ghost_threshold: float = pydantic.Field(20.0, gt=0)  # median |grey diff| vs the best adjacent frame -> GHOSTING
    ghost_min_overlap: float = pydantic.Field(0.2, ge=0, le=1)  # fraction of the hole a neighbour must see to judge

    @pydantic.model_validator(mode="after")
    def _model_needs_path(self) -> "RestoreConfig":
        if self.method == "onnx" and not self.model_path:
            raise ValueError("restore_background: method='onnx' needs model_path (an ONNX video inpainter)")
        return self


@dataclass
class RestoreResult:
    background: np.ndarray  # (n,H,W,3) uint8
    status: np.ndarray  # (n,) int16 Reason
    filled_from_video: np.ndarray  # (n,) float32 fraction of hole pixels propagated (0 when no hole)
    method: str
    hole: np.ndarray | None = None  # (n,H,W) bool: the restored pixels (composite judges residue on them)


def _dilate(mask: np.ndarray, px: int) -> np.ndarray:
    return grow(mask, px) if px > 0 else mask.astype(bool)


_HOLES = Lru(max_bytes=64 << 20, size=lambda a: a.nbytes)  # ~120 dilated masks at 960x540


def _holes(masks: np.ndarray, px: int) -> list[np.ndarray]:
    """Each mask dilated by ``px`` (read-only), once per process for each mask's content: a
    chunk's window shares most of its frames with the neighbouring chunks' windows, and the
    hand-arm scope's features avoid the very holes the hand scope dilated."""
    out = []
    for mk in masks:
        mk = np.ascontiguousarray(mk, dtype=bool)
        key = (xxhash.xxh3_128_digest(memoryview(mk).cast("B")) + repr(mk.shape).encode(), px)
        hole = _HOLES.get(key, None)
        if hole is None:
            hole = _dilate(mk, px)
            hole.flags.writeable = False
            hole = _HOLES.put(key, hole)
        out.append(hole)
    return out


class _Features:
    """ORB features per frame on its visible background, the mutual matches between two
    frames and the homographies between them, each computed once (the ghosting check reuses
    the propagation's) and kept for the process (``_DETECTED``, ``_MATCHED``, ``_FITTED``),
    keyed by the content of the feature images: the hand and hand-arm scopes detect features
    on the same background (``feature_masks``), so the second scope fits none again, and the
    next chunk's window detects none on the frames it shares with this one. Mutual
    (cross-checked) matches are symmetric, so j -> t and t -> j share one matching."""

    def __init__(self, frames: np.ndarray, holes: Sequence[np.ndarray], max_side: int):
        self.frames, self.holes = frames, holes
        h, w = frames.shape[1:3]
        self.s = min(1.0, max_side / max(h, w))
        self.orb = cv2.ORB_create(nfeatures=2000, edgeThreshold=15, patchSize=15, fastThreshold=7)
        self._images: dict[int, tuple[np.ndarray, np.ndarray, bytes]] = {}
        self._cache: dict[int, tuple] = {}
        self.homographies: dict[tuple[int, int], np.ndarray | None] = {}

    def image(self, i: int) -> tuple[np.ndarray, np.ndarray, bytes]:
        """(grey, mask, content key) of frame i at the feature resolution."""
        if i not in self._images:
            g = cv2.cvtColor(self.frames[i], cv2.COLOR_RGB2GRAY)
            m = (~self.holes[i]).astype(np.uint8) * 255
            if self.s < 1:
                size = (int(round(g.shape[1] * self.s)), int(round(g.shape[0] * self.s)))
                g = cv2.resize(g, size, interpolation=cv2.INTER_AREA)
                m = cv2.resize(m, size, interpolation=cv2.INTER_NEAREST)
            h = xxhash.xxh3_128(f"{g.shape}{self.s}".encode())  # an in-process key
            h.update(g.data)
            h.update(m.data)
            self._images[i] = (g, m, h.digest())
        return self._images[i]

    def get(self, i: int) -> tuple:
        """(points in frame pixels, ORB descriptors or None) of frame i."""
        if i not in self._cache:
            g, m, key = self.image(i)
            found = _DETECTED.get(key, None)
            if found is None:
                kps, des = self.orb.detectAndCompute(g, m)
                found = _DETECTED.put(key, (np.array([k.pt for k in kps], np.float32).reshape(-1, 2) / self.s, des))
            self._cache[i] = found
        return self._cache[i]

    def matches(self, j: int, t: int) -> tuple[np.ndarray, np.ndarray]:
        """Indices (into j's, into t's features) of their mutual nearest neighbours (Hamming),
        in the order of j's features: exactly ``BFMatcher(crossCheck=True).match(j, t)``."""
        kj, kt = self.image(j)[2], self.image(t)[2]
        back = _MATCHED.get((kt, kj), None)
        if back is not None:
            return _reversed(*back)
        found = _MATCHED.get((kj, kt), None)
        if found is None:
            found = _MATCHED.put((kj, kt), _mutual_nearest(self.get(j)[1], self.get(t)[1]))
        return found


def _reversed(it: np.ndarray, ij: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mutual matches (t's, j's) of t -> j as j -> t: (j's, t's) in the order of j's."""
    order = np.argsort(ij, kind="stable")
    return ij[order], it[order]


def _nearest(query: np.ndarray, train: np.ndarray) -> np.ndarray:
    """(len(query),) index of each query descriptor's nearest train descriptor (Hamming; the
    first on ties, as OpenCV's matchers take it)."""
    return cv2.batchDistance(query, train, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=1)[1].ravel()


def _mutual_nearest(dj: np.ndarray, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(into dj, into dt) of the mutual nearest neighbours, in dj's order: exactly
    ``BFMatcher(NORM_HAMMING, crossCheck=True).match(dj, dt)``, a fifth faster on the EgoDex
    clips. The way back is searched only from the train descriptors some query chose (the
    cross-check's second full pass searched from all), and the pairing is symmetric, so the
    smaller set queries (a pair is mutual iff each is the other's first nearest)."""
    if len(dj) > len(dt):
        return _reversed(*_mutual_nearest(dt, dj))
    fwd = _nearest(dj, dt)
    chosen = np.unique(fwd[fwd >= 0])
    back = np.full(len(dt), -1, np.int64)
    back[chosen] = _nearest(dt[chosen], dj)
    ij = np.flatnonzero((fwd >= 0) & (back[np.maximum(fwd, 0)] == np.arange(len(dj))))
    return ij.astype(np.int32), fwd[ij].astype(np.int32)


_ROBUST = {"usac_fast": cv2.USAC_FAST, "ransac": cv2.RANSAC}
_FITTED = Lru(max_items=50_000)  # homographies (or None: not trusted), 3x3 doubles each: a few MB
_DETECTED = Lru(max_items=256)  # frames' ORB points and descriptors; up to 2,000 features (40 B each): ~20 MB
_MATCHED = Lru(max_items=2048)  # frame pairs' mutual matches; up to 2,000 (8 B each) per pair: ~30 MB


def _homography(feats: _Features, j: int, t: int, cfg: RestoreConfig) -> np.ndarray | None:
    """3x3 taking frame j's pixels onto frame t's, or None when the fit is not trusted. (The
    inverse of t -> j is not used for it: it restored 0.1-0.2 dB worse on the demo clips.)"""
    if (j, t) not in feats.homographies:
        key = (feats.image(j)[2], feats.image(t)[2], cfg.min_inliers, cfg.homography_fit)
        fitted = _FITTED.get(key)
        if fitted is MISSING:
            fitted = _FITTED.put(key, _fit_homography(feats, j, t, cfg))
        feats.homographies[j, t] = fitted
    return feats.homographies[j, t]


def _into_box(Hm: np.ndarray, box: tuple[slice, slice], step: int = 1) -> np.ndarray:
    """Hm followed by the map from the frame onto ``box``'s pixels (every ``step``-th one):
    warping with it gives exactly the full warp's pixels there, at the box's cost."""
    S = np.array([[1.0 / step, 0.0, -box[1].start / step], [0.0, 1.0 / step, -box[0].start / step], [0.0, 0.0, 1.0]])
    return S @ Hm


def _size(box: tuple[slice, slice], step: int = 1) -> tuple[int, int]:
    """(width, height) of ``box`` sampled every ``step`` pixels, as cv2 takes it."""
    return len(range(box[1].start, box[1].stop, step)), len(range(box[0].start, box[0].stop, step))


def _median_u8(a: np.ndarray, mask: np.ndarray) -> float:
    """``np.median(a[mask])`` of a uint8 image, from its masked histogram (no gather, no sort)."""
    c = np.cumsum(cv2.calcHist([a], [0], mask.view(np.uint8), [256], [0, 256]).ravel())
    n = int(c[-1])
    return float(np.searchsorted(c, (n - 1) // 2, side="right") + np.searchsorted(c, n // 2, side="right")) / 2


def _fit_homography(feats: _Features, j: int, t: int, cfg: RestoreConfig) -> np.ndarray | None:
    pj, dj = feats.get(j)
    pt, dt = feats.get(t)
    if dj is None or dt is None or len(pj) < cfg.min_inliers or len(pt) < cfg.min_inliers:
        return None
    ij, it = feats.matches(j, t)
    if len(ij) < cfg.min_inliers:
        return None
    src, dst = pj[ij], pt[it]
    Hm, inl = cv2.findHomography(src, dst, _ROBUST[cfg.homography_fit], 3.0)
    if Hm is None or inl is None or int(inl.sum()) < cfg.min_inliers:
        return None
    det = float(np.linalg.det(Hm[:2, :2]))
    if not (0.5 < det < 2.0) or np.abs(Hm[2, :2]).max() > 2e-3:
        return None  # implausible for slow egocentric motion
    return Hm


def _sources(t: int, times: np.ndarray, cfg: RestoreConfig) -> tuple[list[int], list[int]]:
    """(window, rest): indices of the frames within ``cfg.window`` of t's time, spread evenly,
    and of the frames given beyond twice that (the rest of the clip: the frames just past the
    window saw what the window saw, a hand that held still, and the same mask errors); each
    nearest in time first."""
    near = np.abs(times - times[t]) <= cfg.window
    cand = [j for j in np.flatnonzero(near).tolist() if j != t]
    if len(cand) > cfg.max_sources:
        pick = np.linspace(0, len(cand) - 1, cfg.max_sources).round().astype(int)
        cand = [cand[k] for k in sorted(set(pick))]
    order = lambda j: (abs(int(times[j]) - int(times[t])), int(times[j]))  # noqa: E731
    far = np.abs(times - times[t]) > 2 * cfg.window
    return sorted(cand, key=order), sorted(np.flatnonzero(far).tolist(), key=order)


@lru_cache(maxsize=None)
def _sorting_network(k: int) -> tuple[tuple[int, int], ...]:
    """Batcher's odd-even merge sort: the compare-exchanges (a < b) that sort any k values."""
    n = 1 << max(0, (k - 1).bit_length())
    pairs, p = [], 1
    while p < n:
        d = p
        while d >= 1:
            for j in range(d % p, n - d, 2 * d):
                for i in range(min(d, n - j - d)):
                    if (i + j) // (2 * p) == (i + j + d) // (2 * p):
                        pairs.append((i + j, i + j + d))
            d //= 2
        p *= 2
    return tuple((a, b) for a, b in pairs if b < k)  # the padding sorts last: its exchanges never move a value


def _median_seen(C: np.ndarray, V: np.ndarray) -> np.ndarray:
    """(P,3) per-pixel median of the candidates (k,P,3) that saw the pixel (V (k,P)); the
    value ``np.nanmedian`` gives with the others NaN, without its masked-array path. The k
    (at most ``max_sources``) rows are sorted by a sorting network of elementwise min/max,
    unseen values last (a third faster than ``np.sort`` along the candidate axis)."""
    rows = [np.where(V[i][:, None], C[i], np.float32(np.inf)) for i in range(len(C))]
    for a, b in _sorting_network(len(rows)):
        lo = np.minimum(rows[a], rows[b])
        np.maximum(rows[a], rows[b], out=rows[b])
        rows[a] = lo
    s = np.stack(rows)
    c = V.sum(0)[None, :, None]
    lo = np.take_along_axis(s, (c - 1) // 2, 0)[0]
    hi = np.take_along_axis(s, c // 2, 0)[0]
    return (lo + hi) / 2


def _inpaint(img: np.ndarray, hole: np.ndarray, cfg: RestoreConfig) -> None:
    """Fill ``hole`` of ``img`` in place."""
    if cfg.inpaint not in ("telea", "ns"):
        img[hole] = _inpainted(img, hole, cfg)
        return
    # local methods: the hole's box grown past their reach is exact; below full scale a
    # small pixel is known only where all of its pixels are, and the fill is upsampled
    # (demo clips, hand-arm hole: 27.34 dB against 27.12 at full scale, predicted masks;
    # 24.30 against 24.21, true masks; the fill ~10x faster)
    s = cfg.inpaint_scale if cv2.countNonZero(hole.view(np.uint8)) > cfg.inpaint_full_scale_px else 1.0
    win = bbox(hole, int(np.ceil((cfg.inpaint_radius + 2) / s)) + 1)
    sub, hs = np.ascontiguousarray(img[win]), hole[win]
    if s >= 1:
        hs = np.ascontiguousarray(hs)
        img[win][hs] = _inpainted(sub, hs, cfg)
        return
    h, w = hs.shape
    size = (max(1, round(w * s)), max(1, round(h * s)))
    small = cv2.resize(sub, size, interpolation=cv2.INTER_AREA)
    small_hole = cv2.resize(hs.view(np.uint8) * np.uint8(255), size, interpolation=cv2.INTER_AREA) > 0
    filled = small.copy()
    filled[small_hole] = _inpainted(small, small_hole, cfg)  # the same radius in (coarser) pixels: the wider reach restored better
    img[win][hs] = cv2.resize(filled, (w, h), interpolation=cv2.INTER_LINEAR)[hs]


def _inpainted(img: np.ndarray, hole: np.ndarray, cfg: RestoreConfig) -> np.ndarray:
    """(P,3) the inpainter's values at the hole's pixels."""
    bgr = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    m8 = hole.astype(np.uint8) * 255
    out = None
    if cfg.inpaint in ("fsr_fast", "shiftmap") and hasattr(cv2, "xphoto"):
        algo = cv2.xphoto.INPAINT_FSR_FAST if cfg.inpaint == "fsr_fast" else cv2.xphoto.INPAINT_SHIFTMAP
        try:
            dst = np.zeros_like(bgr)
            cv2.xphoto.inpaint(bgr, 255 - m8, dst, algo)  # xphoto: non-zero = known pixel
            out = dst
        except cv2.error:
            out = None
    if out is None:
        flag = cv2.INPAINT_NS if cfg.inpaint == "ns" else cv2.INPAINT_TELEA
        out = cv2.inpaint(bgr, m8, cfg.inpaint_radius, flag)
    return out[hole][:, ::-1]  # BGR -> RGB


def restored_residue(img: np.ndarray, hole: np.ndarray, thr: float, visible: np.ndarray | None = None) -> bool:
    """Skin-coloured pixels left in the restored region, beyond what its surroundings show;
    with ``visible``, only the restored pixels that stay visible count, still as a share of the
    whole region (covering residue can only pass a frame, never reject one)."""
    win = bbox(hole, 15)  # the hole and its ring
    if win is None:
        return False
    img, hole = img[win], hole[win]
    skin = prior_rule(to_ycrcb(np.ascontiguousarray(img)))
    ring = _dilate(hole, 15) & ~hole
    ring_rate = float(skin[ring].mean()) if ring.any() else 0.0
    seen = skin & hole if visible is None else skin & hole & visible[win]
    return float(seen.sum()) / float(hole.sum()) > thr + ring_rate


def visible_residue(background: np.ndarray, hole: np.ndarray, covered: np.ndarray, thr: float) -> np.ndarray:
    """(n,) whether the restored pixels (``hole`` (n,H,W)) that the composite leaves visible
    (not ``covered`` (n,H,W): a robot, or a human hand pasted back) show skin-coloured residue
    beyond what the hole's surroundings show: the paper's residue check, where it matters."""
    return np.array([bool(h.any()) and restored_residue(b, h, thr, ~c) for b, h, c in zip(background, hole, covered)], bool)


def _checks(img, hole, t, neighbours, frames, holes, ok, feats, cfg: RestoreConfig) -> Reason:
    """The restored frame's automatic QC: residue first (unless composite judges it), then ghosting."""
    if not hole.any():
        return Reason.OK
    if not cfg.residue_after_composite and restored_residue(img, hole, cfg.residue_threshold):
        return Reason.RESIDUE
    ghost = _ghosting(img, hole, t, neighbours, frames, holes, ok, feats, cfg)
    if ghost is not None and ghost > cfg.ghost_threshold:
        return Reason.GHOSTING
    return Reason.OK


def _ghosting(img: np.ndarray, hole: np.ndarray, t: int, neighbours: Sequence[int], frames: np.ndarray,
              holes: Sequence[np.ndarray], ok: np.ndarray, feats: "_Features", cfg: RestoreConfig) -> float | None:
    """Median |grey diff| of the restored hole against the best-agreeing adjacent frame (``neighbours``: indices of
    the frames just before and after t)."""
    win = bbox(hole)  # only the hole's pixels are compared: warp into its box
    hole = hole[win]
    g = cv2.cvtColor(np.ascontiguousarray(img[win]), cv2.COLOR_RGB2GRAY)
    best = None
    for j in neighbours:
        if not ok[j]:
            continue
        Hm = np.eye(3) if cfg.align == "identity" else _homography(feats, j, t, cfg)
        Hb = _into_box(np.eye(3) if Hm is None else Hm, win)
        seen = cv2.warpPerspective((~holes[j]).view(np.uint8), Hb, _size(win), flags=cv2.INTER_NEAREST) > 0
        both = seen & hole
        if both.sum() < max(20, cfg.ghost_min_overlap * hole.sum()):
            continue
        gw = cv2.cvtColor(cv2.warpPerspective(frames[j], Hb, _size(win), flags=cv2.INTER_LINEAR), cv2.COLOR_RGB2GRAY)
        err = _median_u8(cv2.absdiff(gw, g), both)
        best = err if best is None else min(best, err)
    return best


def restore_background(
    frames: np.ndarray,
    masks: np.ndarray,
    targets: np.ndarray,
    cfg: RestoreConfig = RestoreConfig(),
    *,
    frame_ok: np.ndarray | None = None,
    feature_masks: np.ndarray | None = None,
    times: np.ndarray | None = None,
    arm_masks: np.ndarray | None = None,
) -> RestoreResult:
    """Background for ``frames[targets]`` with ``masks`` (hand/arm, bool) removed.

    ``frames`` is the window: the targets plus up to ``cfg.window`` frames each side, and
    optionally frames from the rest of the clip; ``times`` ((m,) int, default 0..m-1) are
    their frame numbers in the clip, increasing. Frames within ``cfg.window`` of a target
    vote for its hole; the others fill only what none of those saw, and never from their
    ``arm_masks`` ((m,H,W) bool, default ``masks``): over a clip the arms move, and a sleeve
    is not the background behind a hand.
    ``frame_ok`` (optional, (m,) bool) excludes undecodable frames as sources.
    ``feature_masks`` (optional, (m,H,W) bool, default ``masks``): what the alignment's
    features must avoid. The pipeline passes the hand masks for both scopes, so the hand-arm
    scope reuses the hand scope's homographies (``_FITTED``); on the demo clips that also
    restored the hand-arm hole better (27.40 against 27.34 dB with its own, arm-free features).
    """
    frames = np.asarray(frames)
    masks = np.asarray(masks, dtype=bool)
    targets = np.asarray(targets, dtype=int).reshape(-1)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or masks.shape != frames.shape[:3]:
        raise ValueError(f"restore_background: frames (m,H,W,3) uint8 and masks (m,H,W) bool, got {frames.shape}, {masks.shape}")
    m, H, W = frames.shape[:3]
    times = np.arange(m) if times is None else np.asarray(times, dtype=np.int64).reshape(-1)
    if len(times) != m or (m > 1 and np.any(np.diff(times) <= 0)):
        raise ValueError(f"restore_background: times must be {m} increasing frame numbers, got {times.tolist()}")
    ok = np.ones(m, bool) if frame_ok is None else np.asarray(frame_ok, bool)
    holes = _holes(masks, cfg.dilate_px)  # (m,) (H,W) bool, read-only
    if feature_masks is None or feature_masks is masks:  # (the hand scope passes its own masks)
        feature_holes = holes
    else:
        feature_masks = np.asarray(feature_masks, dtype=bool)
        if feature_masks.shape != masks.shape:
            raise ValueError(f"restore_background: feature_masks must be {masks.shape} like masks, got {feature_masks.shape}")
        feature_holes = _holes(feature_masks, cfg.dilate_px)
    feats = _Features(frames, feature_holes, cfg.feature_max_side)
    index = {int(f): i for i, f in enumerate(times)}

    def neighbours(t: int) -> list[int]:
        return [index[f] for f in (int(times[t]) - 1, int(times[t]) + 1) if f in index]

    n = len(targets)
    if cfg.method == "onnx":
        from handedit.models.inpainter import inpaint_onnx

        out, tag = inpaint_onnx(frames, holes, targets, ok, cfg)
        status = np.full(n, Reason.OK, STATUS_DTYPE)
        for k, t in enumerate(targets):
            status[k] = _checks(out[k], holes[t], int(t), neighbours(int(t)), frames, holes, ok, feats, cfg)
        return RestoreResult(out, status, np.zeros(n, np.float32), tag, _target_holes(holes, targets))
    out = np.empty((n, H, W, 3), np.uint8)  # every target's frame is written whole
    status = np.full(n, Reason.OK, STATUS_DTYPE)
    filled_frac = np.zeros(n, np.float32)
    propagate = _Propagation(frames, holes, ok, feats, cfg)
    arm_holes: list = []  # dilated arm masks, made when the rest of the clip is first searched
    from_clip = False  # whether the rest of the clip was given (the method says so)
    for k, t in enumerate(targets):
        img = out[k]  # restored in place
        img[...] = frames[t]
        hole = holes[t]
        if not hole.any():
            continue
        window, rest = _sources(int(t), times, cfg) if ok[t] else ([], [])
        filled = propagate(img, int(t), window, None)
        from_clip |= bool(rest and cfg.clip_sources)
        win = bbox(hole, 25)
        hy, hx = np.nonzero(hole[win])
        if rest and (~filled).mean() >= max(cfg.clip_min_unseen, 1e-9):  # what the window never saw, from the rest of the clip
            if not arm_holes:
                arm_holes[:] = holes if arm_masks is None else _holes(np.asarray(arm_masks, bool), cfg.dilate_px)
            late = propagate(img, int(t), rest[:cfg.clip_sources], ~filled, cfg.clip_agree, via=int(targets[0]),
                             occupied=arm_holes)
            filled |= late
        filled_frac[k] = float(filled.mean())
        left = np.zeros((H, W), bool)
        left[win][hy[~filled], hx[~filled]] = True
        if left.any():
            _inpaint(img, left, cfg)
        status[k] = _checks(img, hole, int(t), neighbours(int(t)), frames, holes, ok, feats, cfg)
    inp = {"telea": "telea", "ns": "ns", "fsr_fast": "xphoto-fsr", "shiftmap": "xphoto-shiftmap"}[cfg.inpaint]
    align = "homography" if cfg.align == "homography" else "identity"
    return RestoreResult(out, status, filled_frac, f"classical:propagate-{align}{'+clip' if from_clip else ''}+inpaint-{inp}",
                         _target_holes(holes, targets))


def _local_offset(target: np.ndarray, source: np.ndarray, both: np.ndarray, at: tuple[np.ndarray, np.ndarray],
                  step: int = 4) -> np.ndarray:
    """(P,3) target minus source at the pixels ``at`` (in the hole), as a smooth field: the
    difference where both know the pixel, carried into the hole from its nearest edge (Telea on
    a ``step`` times coarser grid). The hand's shadow around the hole and an exposure change
    between the two moments are taken from the hole's own rim; the texture stays the source's."""
    h, w = both.shape
    size = (max(1, -(-w // step)), max(1, -(-h // step)))
    m = cv2.resize(both.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    d = cv2.resize((target.astype(np.float32) - source) * both[..., None], size, interpolation=cv2.INTER_AREA)
    known = m > 0.5
    if not known.any():
        return np.zeros((len(at[0]), 3), np.float32)
    field = np.clip(d / np.maximum(m, 1e-6)[..., None] + 128.0, 0, 255).astype(np.uint8)
    field = cv2.inpaint(field, (~known).view(np.uint8), 3, cv2.INPAINT_TELEA)
    return cv2.resize(field, (w, h), interpolation=cv2.INTER_LINEAR)[at].astype(np.float32) - 128.0


class _Propagation:
    """Real background pixels for a target's hole from other frames, aligned, checked and
    gain corrected; the per-pixel median of >= 3 views, else the nearest frame's."""

    def __init__(self, frames: np.ndarray, holes: Sequence[np.ndarray], ok: np.ndarray, feats: _Features,
                 cfg: RestoreConfig):
        self.frames, self.holes, self.ok, self.feats, self.cfg = frames, holes, ok, feats, cfg
        self._grey: dict[int, np.ndarray] = {}

    def homography(self, j: int, t: int, via: int | None) -> np.ndarray | None:
        """j -> t, through ``via`` when both of its fits are trusted (the photometric check still
        judges the result), else fitted directly."""
        if via is not None and via not in (j, t):
            a, b = _homography(self.feats, j, via, self.cfg), _homography(self.feats, via, t, self.cfg)
            if a is not None and b is not None:
                return b @ a
        return _homography(self.feats, j, t, self.cfg)

    def grey(self, i: int) -> np.ndarray:
        if i not in self._grey:
            self._grey[i] = cv2.cvtColor(self.frames[i], cv2.COLOR_RGB2GRAY)
        return self._grey[i]

    def __call__(self, img: np.ndarray, t: int, sources: Sequence[int], only: np.ndarray | None,
                 agree: float | None = None, via: int | None = None, occupied: Sequence[np.ndarray] | None = None) -> np.ndarray:
        """Write into ``img`` (frame t, restored in place) the hole pixels ``sources`` saw,
        restricted to ``only`` ((P,) bool over the hole's pixels in ``bbox(hole, 25)`` order);
        with ``agree`` (the rest of the clip), only pixels two sources saw within that mean |RGB
        difference| of the value taken, each source first brought to the target's local
        brightness: the difference on the pixels both know (around the hole, and what the
        window filled), spread smoothly into the hole. ``via``: a frame near t the sources are
        aligned to first (their homographies onto it are shared by every target of a chunk, one
        fit each instead of one per target). ``occupied``: what each source may not give (default
        its own hole). Returns (P,) bool: the pixels written."""
        cfg, frames, H, W = self.cfg, self.frames, *self.frames.shape[1:3]
        hole = self.holes[t]
        full = (slice(0, H), slice(0, W))
        # the hole and its gain ring: the only pixels warped in colour (the alignment check
        # samples every align_check_step-th pixel of the frame, warped straight onto that
        # grid, in grey)
        win = bbox(hole, 25)
        ring = (_dilate(hole, 25) & ~hole)[win]
        hy, hx = np.nonzero(hole[win])
        st = cfg.align_check_step
        keep = ~hole[::st, ::st]
        target_grey = self.grey(t)[::st, ::st]
        if agree is not None:  # the target's own pixels, and what the window filled: where a later frame's offset is measured
            known = ~hole[win]
            if only is not None:
                known[hy[~only], hx[~only]] = True
        cands, valids = [], []
        for j in sources:
            if not self.ok[j]:
                continue
            Hm = np.eye(3) if cfg.align == "identity" else self.homography(j, t, via)
            if Hm is None:
                Hm = np.eye(3)  # textureless or static: identity, if the photometric check agrees
            visible = (~(self.holes if occupied is None else occupied)[j]).view(np.uint8)
            Hs = _into_box(Hm, full, st)
            shared = (cv2.warpPerspective(visible, Hs, _size(full, st), flags=cv2.INTER_NEAREST) > 0) & keep
            if cv2.countNonZero(shared.view(np.uint8)) < 25:
                continue
            gw = cv2.warpPerspective(self.grey(j), Hs, _size(full, st), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            if _median_u8(cv2.absdiff(gw, target_grey), shared) > cfg.max_align_error:
                continue  # misaligned, lighting jump or moving scene: would ghost
            Hb = _into_box(Hm, win)
            seen = cv2.warpPerspective(visible, Hb, _size(win), flags=cv2.INTER_NEAREST) > 0
            sv = seen[hy, hx] if only is None else seen[hy, hx] & only
            if not sv.any():
                continue  # sees none of the pixels still wanted
            warped = cv2.warpPerspective(frames[j], Hb, _size(win), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            vals = pixels(warped)[hy, hx].view(np.uint8).reshape(-1, 3).astype(np.float32)  # whole-pixel gather
            gain = np.ones(3, np.float32)
            if cfg.gain_compensation:
                near = (ring & seen).view(np.uint8)
                if cv2.countNonZero(near) >= 50:  # masked means (cv2: no gathers of the ring's pixels)
                    gain = np.array(cv2.mean(np.ascontiguousarray(img[win]), near)[:3]) / np.maximum(cv2.mean(warped, near)[:3], 1.0)
                    gain = np.clip(gain, 0.8, 1.25).astype(np.float32)
                    vals *= gain
            if agree is not None:
                vals += _local_offset(img[win], warped.astype(np.float32) * gain, seen & known, (hy, hx))
            cands.append(vals)
            valids.append(sv)
        filled = np.zeros(len(hy), bool)
        if cands:
            V = np.stack(valids)  # (k,P)
            C = np.stack(cands)  # (k,P,3)
            cnt = V.sum(0)
            filled = cnt > 0
            first = np.argmax(V, axis=0)  # nearest frame that saw the pixel
            val = C[first, np.arange(len(hy))]
            many = cnt >= 3
            if many.any():
                val[many] = _median_seen(C[:, many], V[:, many])
            if agree is not None:
                filled &= ((np.abs(C - val[None]).mean(-1) <= agree) & V).sum(0) >= 2
            pixels(img[win])[hy[filled], hx[filled]] = pixels(np.clip(np.round(val[filled]), 0, 255).astype(np.uint8))
        return filled


def _target_holes(holes: Sequence[np.ndarray], targets: np.ndarray) -> np.ndarray:
    """(n,H,W) the restored pixels of each target frame (stored: composite judges residue on them)."""
    return np.stack([holes[t] for t in targets])
