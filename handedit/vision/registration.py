"""Registration of tracked hand keypoints to the pixels they should sit on.

Why: dataset keypoints and the image do not always agree. The Vision Pro that recorded
EgoDex composes its RGB view from several cameras, so the projected joints sit 20-40 px
(at 1920x1080) off the visible fingers on many frames. A robot retargeted to those
keypoints lands beside the hand it replaces and the hand shows next to it.

The misalignment is close to a rotation of the view about the camera centre, which moves
every image point by about the same number of pixels whatever its depth. So per frame and
per side we estimate a 2-D offset and apply it as that camera-frame rotation to the hand's
3-D joints (and its arm joints): depth, shape and metric size are unchanged, only where
the hand projects moves.

Estimating the offset (classical, per side, at ``work_max_side``):
1. a colour model of this hand: a YCrCb Gaussian of the pixels under its projected
   skeleton (thick bones + palm), against one of a ring around it; their log-likelihood
   ratio gives P(hand) per pixel (a beige table passes a skin-chroma test; it rarely looks
   like *this* hand more than like its own surroundings);
2. the skeleton template (points on thick bones and the palm) and a ring just outside it
   are slid over a grid of offsets within ``max_shift_px``; the score is the template's
   mean P(hand) minus the ring's (so a template cannot slide into a larger hand-coloured
   area), minus a small penalty per pixel of offset;
3. steps 1-2 are repeated once at the found offset (the colour model then comes from the
   right pixels); the offsets are median-filtered over neighbouring frames (per side), and
   a frame whose best score is weak keeps its neighbours' offset (or none).
Each side is searched in the box its masks and offsets can reach (``_search_box``), with its
disks dilated row by row (``_dilate_disk``): the same offsets as over the whole image, at
about a third of the time on the shared EgoDex clips (960x540).

A side is *present* in a frame when enough of its joints are valid and project inside the
image (``OK``). A side whose joints are valid but project outside the image is ``ABSENT``
(nothing to segment or replace there); a side without enough valid joints is
``NO_KEYPOINTS`` (a rejection of that side: its hand may be in view, but nothing can be
retargeted). The frame itself is always OK here: a source without keypoints still gets
its hand segmented (by skin colour) and removed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

import cv2
import numpy as np
import pydantic

from handedit.camera import Intrinsics, project
from handedit.keypoints import N_JOINTS, PARENT, WRIST
from handedit.reasons import STATUS_DTYPE, Reason
from handedit.vision.skin import colour_loglik, to_ycrcb

_PALM = (WRIST, 1, 5, 9, 13, 17)


class RegistrationConfig(pydantic.BaseModel):
    VERSION: ClassVar[int] = 1
    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    # auto: colour-align, except for sources whose keypoints are pixel-exact by construction
    # (ClipInfo.keypoints_exact: the synthetic oracle), which pass through unchanged
    method: Literal["auto", "colour-align", "none"] = "auto"
    work_max_side: int = pydantic.Field(480, ge=64)
    max_shift_px: float = pydantic.Field(56.0, ge=0, description="largest offset searched, px at 1920 wide (scaled with the image)")
    bone_width: float = pydantic.Field(0.16, gt=0, description="template bone thickness, x palm size")
    shift_penalty: float = pydantic.Field(0.08, ge=0, description="score lost at max_shift_px")
    scales: tuple[float, ...] = (0.9, 1.0, 1.12)  # image scales about the wrist tried (depth corrections)
    scale_penalty: float = pydantic.Field(0.1, ge=0, description="score lost per unit |log scale|")
    min_gain: float = pydantic.Field(0.04, ge=0, description="a move must beat staying put by this much score")
    min_score: float = pydantic.Field(0.15, description="weaker best scores keep the neighbours' offset")
    smooth_frames: int = pydantic.Field(5, ge=1, description="median filter length over frames (odd)")
    min_keypoints: int = pydantic.Field(6, ge=3, description="valid joints for a side to be present")
    min_inside: int = pydantic.Field(3, ge=1, description="valid joints inside the image for a side to be present")


@dataclass
class RegistrationResult:
    keypoints: np.ndarray  # (n,S,21,3) registered, camera frame
    keypoints_valid: np.ndarray  # (n,S,21)
    arm_keypoints: np.ndarray | None  # (n,S,3,3) moved with their hand
    offset_px: np.ndarray  # (n,S,2) the applied image offset (du, dv) at the clip's resolution
    scale: np.ndarray  # (n,S) the applied image scale about the wrist (1: depth unchanged)
    score: np.ndarray  # (n,S) alignment score at the chosen offset (nan: absent or not searched)
    hand_status: np.ndarray  # (n,S) OK | ABSENT | NO_KEYPOINTS
    status: np.ndarray  # (n,) OK (register never rejects a frame; see the module doc)
    method: str


def present_sides(uv: np.ndarray, valid: np.ndarray, width: int, height: int, cfg: RegistrationConfig) -> np.ndarray:
    """(n,S) bool: sides with enough valid joints, some of them inside the image."""
    inside = valid & np.isfinite(uv).all(-1) & (uv[..., 0] >= 0) & (uv[..., 0] < width) & (uv[..., 1] >= 0) & (uv[..., 1] < height)
    return valid[..., WRIST] & (valid.sum(-1) >= cfg.min_keypoints) & (inside.sum(-1) >= cfg.min_inside)


def _palm_size(pts: np.ndarray, valid: np.ndarray) -> float:
    spans = [np.linalg.norm(pts[a] - pts[b]) for a, b in ((WRIST, 9), (5, 17), (WRIST, 5)) if valid[a] and valid[b]]
    return max(4.0, max(spans) if spans else 0.5 * float(np.ptp(pts[valid], axis=0).max()))


def _template(shape: tuple[int, int], pts: np.ndarray, valid: np.ndarray, width: int) -> np.ndarray:
    m = np.zeros(shape, np.uint8)
    for j in range(1, N_JOINTS):
        p = PARENT[j]
        if valid[j] and valid[p]:
            cv2.line(m, tuple(np.round(pts[p]).astype(int)), tuple(np.round(pts[j]).astype(int)), 1, max(1, width))
    palm = [j for j in _PALM if valid[j]]
    if len(palm) >= 3:
        cv2.fillConvexPoly(m, cv2.convexHull(np.round(pts[palm]).astype(np.int32)), 1)
    return m.astype(bool)


def _hand_prob(ycc: np.ndarray, fg: np.ndarray, bg: np.ndarray) -> np.ndarray | None:
    if fg.sum() < 30 or bg.sum() < 30:
        return None
    x = ycc.astype(np.float32)
    llr = colour_loglik(x, x[fg], 16.0) - colour_loglik(x, x[bg], 16.0)
    return (1.0 / (1.0 + np.exp(-np.clip(llr, -20, 20)))).astype(np.float32)


def _search_box(shape: tuple[int, int], pts: np.ndarray, valid: np.ndarray, scales: tuple[float, ...],
                radius: float) -> tuple[slice, slice]:
    """Every pixel a side's search can read: its skeleton at any tried scale about the wrist,
    grown by the widest mask drawn around it (the colour model's ring, 0.6 palm) and the
    largest offset tried (the coarse grid's radius plus its refinement step). The search
    works in this box: the same result as on the whole image (its masks and reads stay
    inside), without dilating and scoring the rest of it (most of registration's time)."""
    wrist = pts[WRIST]
    p = np.concatenate([wrist + c * (pts[valid] - wrist) for c in (*scales, 1.0)])
    margin = 0.7 * max(scales + (1.0,)) * _palm_size(pts, valid) + radius + max(1, int(radius // 12)) + 4
    (x0, y0), (x1, y1) = np.floor(p.min(0) - margin).astype(int), np.ceil(p.max(0) + margin).astype(int)
    h, w = shape
    return slice(max(0, y0), min(h, y1 + 1)), slice(max(0, x0), min(w, x1 + 1))


def _disk(r: float) -> np.ndarray:
    r = max(1, int(round(r)))
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _dilate_disk(mask: np.ndarray, r: float) -> np.ndarray:
    """``cv2.dilate(mask, _disk(r))``, exactly, as one row-wise dilation per width of the
    disk's rows, shifted and OR-ed: a large disk's dilation cost most of registration's time."""
    k = _disk(r)
    half = k.shape[0] // 2
    m = mask.astype(np.uint8)
    h = m.shape[0]
    out = np.zeros_like(m)
    rows: dict[int, np.ndarray] = {}
    for i, width in enumerate(k.sum(1)):
        if abs(i - half) >= h:
            continue
        if width not in rows:
            rows[width] = cv2.dilate(m, np.ones((1, int(width)), np.uint8))
        src, dy = rows[width], i - half
        if dy >= 0:
            out[: h - dy] |= src[dy:]
        else:
            out[-dy:] |= src[: h + dy]
    return out.astype(bool)


def _ring(mask: np.ndarray, inner: float, outer: float) -> np.ndarray:
    """Pixels within ``outer`` of ``mask`` but not within ``inner`` (disks of those radii)."""
    return _dilate_disk(mask, outer) & ~_dilate_disk(mask, inner)


def _search(prob: np.ndarray, tmpl: np.ndarray, ring: np.ndarray, radius: float, penalty: float,
            centre: np.ndarray = np.zeros(2)) -> tuple[np.ndarray, float]:
    """Best integer offset (dx, dy) of the template over ``prob``, searched around ``centre``."""
    h, w = prob.shape
    ty, tx = np.nonzero(tmpl)
    ry, rx = np.nonzero(ring)
    rng = np.random.default_rng(0)
    if len(tx) > 400:
        k = rng.choice(len(tx), 400, replace=False)
        tx, ty = tx[k], ty[k]
    if len(rx) > 400:
        k = rng.choice(len(rx), 400, replace=False)
        rx, ry = rx[k], ry[k]
    flat = prob.ravel()
    best, best_d = -np.inf, centre.copy()
    for step, span, c in ((max(1, int(radius // 12)), radius, centre), (1, None, None)):
        if span is None:  # refine around the coarse optimum
            span, c = float(max(1, int(radius // 12))), best_d
        r = np.arange(-span, span + 1e-9, step)
        dx, dy = np.meshgrid(r + c[0], r + c[1])
        dx, dy = dx.ravel(), dy.ravel()
        keep = np.hypot(dx - centre[0], dy - centre[1]) <= radius + 1e-9
        dx, dy = dx[keep], dy[keep]
        whole = bool((dx == np.round(dx)).all() and (dy == np.round(dy)).all())  # the usual case: integer shifts

        def mean_at(xs, ys):
            if whole:  # no rounding needed; one flat gather
                X = np.clip(xs[None] + dx.astype(np.intp)[:, None], 0, w - 1)
                Y = np.clip(ys[None] + dy.astype(np.intp)[:, None], 0, h - 1)
                return flat[Y * w + X].mean(1)
            X = np.clip(np.round(xs[None] + dx[:, None]).astype(int), 0, w - 1)
            Y = np.clip(np.round(ys[None] + dy[:, None]).astype(int), 0, h - 1)
            return prob[Y, X].mean(1)

        score = mean_at(tx, ty) - mean_at(rx, ry) - penalty * np.hypot(dx, dy) / max(radius, 1e-6)
        i = int(np.argmax(score))
        if score[i] > best:
            best, best_d = float(score[i]), np.array([dx[i], dy[i]])
    return best_d, best


def estimate_offsets(frames: np.ndarray, uv: np.ndarray, valid: np.ndarray, present: np.ndarray,
                     cfg: RegistrationConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame, per-side image offsets (n,S,2) at full resolution, image scales about the
    wrist (n,S) and their scores (n,S)."""
    n, S = present.shape
    H, W = frames.shape[1:3]
    s = min(1.0, cfg.work_max_side / max(H, W))
    size = (max(1, round(W * s)), max(1, round(H * s)))
    radius = cfg.max_shift_px * W / 1920.0 * s
    off = np.zeros((n, S, 2))
    scl = np.ones((n, S))
    score = np.full((n, S), np.nan)
    for i in range(n):
        if not present[i].any():
            continue
        small = cv2.resize(frames[i], size, interpolation=cv2.INTER_AREA) if s < 1 else frames[i]
        ycc = to_ycrcb(small)
        for k in np.flatnonzero(present[i]):
            vk = valid[i, k]
            box = _search_box(ycc.shape[:2], uv[i, k] * s, vk, cfg.scales, radius)
            pts0 = uv[i, k] * s - [box[1].start, box[0].start]
            yb = ycc[box]
            wrist = pts0[WRIST]
            d, sc, best = np.zeros(2), 1.0, np.nan
            templates: dict[float, tuple[np.ndarray, np.ndarray]] = {}
            for it in range(2):
                pts = wrist + sc * (pts0 - wrist) + d
                scale = _palm_size(pts, vk)
                tmpl = _template(yb.shape[:2], pts, vk, int(round(cfg.bone_width * scale)))
                core = cv2.erode(tmpl.astype(np.uint8), _disk(1)).astype(bool)
                bg = _ring(tmpl, 0.25 * scale, 0.6 * scale)
                prob = _hand_prob(yb, core if core.sum() >= 30 else tmpl, bg)
                if prob is None:
                    break
                best, base = -np.inf, None
                for cand in (cfg.scales if it else (1.0,)):  # colour model first, then shift x scale
                    if cand not in templates:  # (the same on both rounds)
                        p = wrist + cand * (pts0 - wrist)
                        sz = _palm_size(p, vk)
                        t0 = _template(yb.shape[:2], p, vk, int(round(cfg.bone_width * sz)))
                        templates[cand] = t0, _ring(t0, 0.06 * sz, 0.2 * sz)
                    t0, ring0 = templates[cand]
                    dd, sco = _search(prob, t0, ring0, radius, cfg.shift_penalty)
                    sco -= cfg.scale_penalty * abs(np.log(cand))
                    if cand == 1.0:
                        base = _search(prob, t0, ring0, 0.0, 0.0)[1]  # the score of not moving at all
                    if sco > best:
                        best, d, sc = sco, dd, cand
                if it and base is not None and best - base < cfg.min_gain:
                    d, sc, best = np.zeros(2), 1.0, base  # not clearly better than where the data put it
            off[i, k], scl[i, k], score[i, k] = d / s, sc, best
    return off, scl, score


def _smooth(off: np.ndarray, score: np.ndarray, present: np.ndarray, cfg: RegistrationConfig) -> np.ndarray:
    """Median over ``smooth_frames`` neighbours per side (any trailing axes, e.g. offsets or
    scales); weak frames take their neighbours'."""
    n, S = present.shape
    good = present & np.isfinite(score) & (score >= cfg.min_score)
    out = np.zeros_like(off)
    half = cfg.smooth_frames // 2
    for k in range(S):
        idx = np.flatnonzero(good[:, k])
        for i in np.flatnonzero(present[:, k]):
            win = idx[np.abs(idx - i) <= half]
            if win.size == 0 and idx.size:  # no good frame nearby: the nearest good one
                win = idx[[np.argmin(np.abs(idx - i))]]
            if win.size:
                out[i, k] = np.median(off[win, k], axis=0)
            else:
                out[i, k] = off[i, k] * 0 + (1.0 if off.ndim == 2 else 0.0)
    return out


def rotation_for_offset(uv: np.ndarray, duv: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """The rotation about the camera centre that moves the ray through ``uv`` to ``uv + duv``."""
    K_inv = np.linalg.inv(intr.K)
    a = K_inv @ np.array([uv[0], uv[1], 1.0])
    b = K_inv @ np.array([uv[0] + duv[0], uv[1] + duv[1], 1.0])
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def register(frames: np.ndarray, keypoints: np.ndarray, keypoints_valid: np.ndarray, intr: Intrinsics,
             cfg: RegistrationConfig = RegistrationConfig(), arm_keypoints: np.ndarray | None = None,
             exact: bool = False) -> RegistrationResult:
    """Registered keypoints for a chunk (n,S,21,3) and the offsets applied (see module doc).
    ``exact``: the source's keypoints are pixel-exact (method "auto" then leaves them)."""
    kp = np.asarray(keypoints, np.float64)
    valid = np.asarray(keypoints_valid, bool) & np.isfinite(kp).all(-1)
    n, S = kp.shape[:2]
    uv = project(kp, intr)
    present = present_sides(uv, valid, intr.width, intr.height, cfg)
    tracked = valid[..., WRIST] & (valid.sum(-1) >= cfg.min_keypoints)
    hand_status = np.where(present, Reason.OK, np.where(tracked, Reason.ABSENT, Reason.NO_KEYPOINTS)).astype(STATUS_DTYPE)
    status = np.full(n, Reason.OK, STATUS_DTYPE)
    arms = None if arm_keypoints is None else np.asarray(arm_keypoints, np.float64).copy()
    skip = cfg.method == "none" or (cfg.method == "auto" and exact)
    if skip or not present.any():
        tag = ("none" if cfg.method == "none" else "none:keypoints-exact") if skip else "classical:colour-align:no-hand"
        return RegistrationResult(kp.astype(np.float32), valid, None if arms is None else arms.astype(np.float32),
                                  np.zeros((n, S, 2), np.float32), np.ones((n, S), np.float32),
                                  np.full((n, S), np.nan, np.float32), hand_status, status, tag)
    off, scl, score = estimate_offsets(np.asarray(frames), uv, valid, present, cfg)
    off = _smooth(off, score, present, cfg)
    scl = _smooth(scl, score, present, cfg)
    out = kp.copy()
    for i, k in zip(*np.nonzero(present)):
        if not off[i, k].any() and scl[i, k] == 1.0:
            continue
        # depth first (the hand slides along its wrist ray: image scale 1/lambda about the
        # wrist), then the rotation about the camera centre that moves the wrist's image
        w = kp[i, k, WRIST]
        moved = kp[i, k] + (1.0 / scl[i, k] - 1.0) * w
        R = rotation_for_offset(uv[i, k, WRIST], off[i, k], intr)
        out[i, k] = moved @ R.T
        if arms is not None:
            arms[i, k] = (arms[i, k] + (1.0 / scl[i, k] - 1.0) * w) @ R.T
    out[~valid] = 0.0
    return RegistrationResult(out.astype(np.float32), valid, None if arms is None else arms.astype(np.float32),
                          off.astype(np.float32), scl.astype(np.float32), score.astype(np.float32), hand_status, status,
                          "classical:colour-align")
