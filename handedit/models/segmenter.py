"""ONNX segmenter plug-in (SAM-style): image + point/box prompts -> mask logits + score.

Contract (names are exact; N, K, h, w may be dynamic; H, W dynamic or fixed):
    inputs   image         float32 (1, 3, H, W)  RGB in [0, 1]
             points        float32 (1, N, 2)     prompt points (x, y) in pixels of ``image``
             point_labels  float32 (1, N)        1 = foreground, 0 = background, -1 = padding
    optional box           float32 (1, 4)        x0, y0, x1, y1 in pixels of ``image``
    outputs  masks         float32 (1, K, h, w)  mask logits (> 0 = object), any resolution
             scores        float32 (1, K)        predicted mask quality in [0, 1]

How it is driven: per frame, the hand call prompts the 21 projected keypoints as
foreground points and their padded bounding box; the hand-arm call adds the box
extended from the hand to the frame border along the forearm (knuckles -> wrist). The
best-scoring of the K masks is kept, its logits are resized bilinearly to the frame and
thresholded at 0, and pixels outside the prompt box are dropped. A frame without keypoints is prompted with the whole-frame box and no
points. The frame's confidence is min(hand score, hand-arm score), checked against the
paper's 0.75 (``SegmentConfig.min_model_confidence``).

Exporting SAM / SAM 2 / SAM 3 to this contract: wrap encoder and prompt decoder in one
``torch.nn.Module`` whose ``forward(image, points, point_labels, box)`` normalises the
[0, 1] image the way the model expects, resizes to its input size (rescale the prompts
by the same factor), appends the box as the two corner points with labels 2 and 3 (SAM's
convention), runs the mask decoder with ``multimask_output=True`` and returns
``(low_res_masks, iou_predictions)``; then
``torch.onnx.export(m, dummy, "sam.onnx", input_names=["image", "points", "point_labels",
"box"], output_names=["masks", "scores"], dynamic_axes={"points": {1: "N"},
"point_labels": {1: "N"}})``. The official ``segment_anything/utils/onnx.py`` exporter
covers the decoder half; a fixed image size is fine (the wrapper resizes to it).
"""

from __future__ import annotations

import cv2
import numpy as np

from handedit.keypoints import WRIST
from handedit.models.runtime import Contract, TensorSpec, load_model
from handedit.reasons import STATUS_DTYPE, Reason

CONTRACT = Contract(
    kind="segmenter",
    inputs=(
        TensorSpec("image", 4, doc="(1,3,H,W) RGB in [0,1]"),
        TensorSpec("points", 3, doc="(1,N,2) x,y pixels"),
        TensorSpec("point_labels", 2, doc="(1,N) 1 fg / 0 bg / -1 pad"),
    ),
    optional_inputs=(TensorSpec("box", 2, doc="(1,4) x0,y0,x1,y1 pixels"),),
    outputs=(TensorSpec("masks", 4, doc="(1,K,h,w) logits"), TensorSpec("scores", 2, doc="(1,K) in [0,1]")),
)


def _prompt_boxes(pts: np.ndarray, shape: tuple[int, int], pad: float) -> tuple[np.ndarray, np.ndarray]:
    """(hand box, hand-arm box) in pixels from valid keypoints (n,2)."""
    h, w = shape
    lo, hi = pts.min(0), pts.max(0)
    m = pad * max(float((hi - lo).max()), 8.0)
    hand = np.array([lo[0] - m, lo[1] - m, hi[0] + m, hi[1] + m])
    hand = np.clip(hand, 0, [w - 1, h - 1, w - 1, h - 1])
    return hand, hand.copy()


def _arm_box(hand_box: np.ndarray, wrist: np.ndarray, direction: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """Hand box grown to contain the ray from the wrist to the frame border."""
    h, w = shape
    if direction is None:
        return hand_box
    ts = []
    for c, d, lim in ((wrist[0], direction[0], w - 1), (wrist[1], direction[1], h - 1)):
        if abs(d) > 1e-6:
            ts.append(((lim if d > 0 else 0) - c) / d)
    t = max(0.0, min(ts)) if ts else 0.0
    end = wrist + t * direction
    box = np.array([min(hand_box[0], end[0]), min(hand_box[1], end[1]), max(hand_box[2], end[0]), max(hand_box[3], end[1])])
    return np.clip(box, 0, [w - 1, h - 1, w - 1, h - 1])


def _call(model, img: np.ndarray, pts: np.ndarray, labels: np.ndarray, box: np.ndarray, out_hw: tuple[int, int]) -> tuple[np.ndarray, float]:
    feeds = {
        "image": np.ascontiguousarray(img.transpose(2, 0, 1)[None], np.float32),
        "points": pts[None].astype(np.float32),
        "point_labels": labels[None].astype(np.float32),
        "box": box[None].astype(np.float32),
    }
    out = model.run(feeds)
    masks, scores = np.asarray(out["masks"], np.float32), np.asarray(out["scores"], np.float32).reshape(-1)
    if masks.ndim != 4 or masks.shape[1] < 1 or scores.size != masks.shape[1]:
        from handedit.models.runtime import ModelContractError

        raise ModelContractError(f"segmenter model {model.path} returned masks {masks.shape} and scores {scores.shape}; "
                                 f"expected masks (1,K,h,w) and scores (1,K) with the same K")
    k = int(np.argmax(scores))
    logits = cv2.resize(masks[0, k], (out_hw[1], out_hw[0]), interpolation=cv2.INTER_LINEAR)
    mask = logits > 0
    # a prompted model answers inside its box; anything outside it is a stray blob
    fy, fx = out_hw[0] / img.shape[0], out_hw[1] / img.shape[1]
    x0, y0 = int(np.floor(box[0] * fx)), int(np.floor(box[1] * fy))
    x1, y1 = int(np.ceil((box[2] + 1) * fx)), int(np.ceil((box[3] + 1) * fy))
    inside = np.zeros_like(mask)
    inside[max(0, y0):y1, max(0, x0):x1] = True
    return mask & inside, float(np.clip(scores[k], 0.0, 1.0))


def segment_onnx(frames: np.ndarray, kp2d: np.ndarray, kval: np.ndarray, cfg) -> "SegmentResult":  # noqa: F821
    """``segment`` of one hand with a model (``cfg.method == "onnx"``); same result type and
    statuses, hand axis of size 1 (``segment`` calls it once per hand)."""
    from handedit.vision.segment import SegmentResult, _forearm_dir

    model = load_model(cfg.model_path, CONTRACT, cfg.onnx)
    n, H, W = frames.shape[:3]
    mh, mw = model.work_hw("image", H, W, cfg.work_max_side)
    sx, sy = mw / W, mh / H
    hand = np.zeros((n, H, W), bool)
    arm = np.zeros((n, H, W), bool)
    conf = np.zeros(n, np.float32)
    status = np.full(n, Reason.OK, STATUS_DTYPE)
    for i in range(n):
        f = frames[i]
        if float(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY).std()) < cfg.blank_std:
            status[i] = Reason.BLANK_FRAME
            continue
        img = cv2.resize(f, (mw, mh), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        v = kval[i] & np.isfinite(kp2d[i]).all(-1)
        pts = kp2d[i][v] * [sx, sy] if v.sum() >= 3 else np.zeros((0, 2))
        if len(pts):
            labels = np.ones(len(pts), np.float32)
            hbox, _ = _prompt_boxes(pts, (mh, mw), 0.15)
            d = _forearm_dir(np.nan_to_num(kp2d[i] * [sx, sy]), v) if v[WRIST] else None
            abox = _arm_box(hbox, kp2d[i][WRIST] * [sx, sy], d, (mh, mw)) if d is not None else hbox
        else:
            pts, labels = np.zeros((1, 2)), -np.ones(1, np.float32)
            hbox = abox = np.array([0, 0, mw - 1, mh - 1], np.float64)
        h_mask, h_score = _call(model, img, pts, labels, hbox, (H, W))
        a_mask, a_score = _call(model, img, pts, labels, abox, (H, W)) if abox is not hbox else (h_mask, h_score)
        hand[i], arm[i] = h_mask, a_mask | h_mask
        conf[i] = min(h_score, a_score)
        if hand[i].sum() < cfg.min_area_frac * H * W:
            status[i] = Reason.EMPTY_MASK
            hand[i] = arm[i] = False
        elif conf[i] < cfg.min_model_confidence:
            status[i] = Reason.LOW_CONFIDENCE
    # one hand (the one the prompts point at): hand axis of size 1
    return SegmentResult(hand[:, None], arm[:, None], conf[:, None], status[:, None], status, f"onnx:segmenter:{model.tag}")
