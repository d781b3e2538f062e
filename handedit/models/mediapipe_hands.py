"""MediaPipe's hand models (palm detection + hand landmarks, Apache-2.0), run without mediapipe.

Why not the ``mediapipe`` package: 0.10.21, the last release whose wheel ships the hand
models, pins ``numpy<2`` and pulls the non-headless ``opencv-contrib-python`` (it clashes
with the headless build this project uses), jax and matplotlib. The two ``.tflite`` files
are taken out of that wheel once (``handedit models fetch``: sha256-checked, licence
recorded) and run unmodified by LiteRT (``ai-edge-litert``, Google's TFLite runtime,
numpy-2 compatible), so there is no conversion to vouch for. The same models converted
to ONNX (e.g. ``tf2onnx --tflite``) run through onnxruntime: the runner is chosen by the
file's suffix, the tensors are the same.

What is reimplemented here is the graph around the two networks, following MediaPipe's
hand-tracking graph: letterboxed 192x192 palm detection, SSD anchor decoding and
weighted NMS; the rotated hand rectangle from the palm's wrist and middle-knuckle
keypoints (x2.6, shifted along the hand); the 224x224 rotated crop for the landmark
model; landmarks mapped back to pixels; the next frame's rectangle from the landmarks
(tracking, so palm detection runs only while fewer hands than wanted are tracked).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

PALM_SIZE = 192
LANDMARK_SIZE = 224
# palm_detection_full: SSD anchors (4 layers, strides 8,16,16,16, two anchors per cell and layer, fixed size)
_STRIDES = (8, 16, 16, 16)
_PALM_KEYPOINTS = 7  # 0: wrist centre, 2: middle-finger knuckle
# landmarks used for the tracked rectangle (MediaPipe's HandLandmarksToRect subset)
_RECT_SUBSET = (0, 1, 2, 3, 5, 6, 9, 10, 13, 14, 17, 18)


class HandModelError(ValueError):
    """The hand model files are missing or unreadable; the message names the file and the fix."""


@dataclass(frozen=True)
class Rect:
    """A rotated rectangle in pixels: centre, size, rotation (radians, image y down)."""

    cx: float
    cy: float
    w: float
    h: float
    rotation: float

    def crop_from_image(self, size: int) -> np.ndarray:
        """2x3 affine map from crop pixels (0..size) to image pixels."""
        c, s = math.cos(self.rotation), math.sin(self.rotation)
        sx, sy = self.w / size, self.h / size
        A = np.array([[c * sx, -s * sy], [s * sx, c * sy]])
        t = np.array([self.cx, self.cy]) - A @ np.array([size / 2.0, size / 2.0])
        return np.hstack([A, t[:, None]])

    def box(self) -> np.ndarray:
        """Axis-aligned (x0, y0, x1, y1) around the rotated rectangle."""
        c, s = abs(math.cos(self.rotation)), abs(math.sin(self.rotation))
        hw, hh = (self.w * c + self.h * s) / 2, (self.w * s + self.h * c) / 2
        return np.array([self.cx - hw, self.cy - hh, self.cx + hw, self.cy + hh])


@dataclass
class HandLandmarks:
    """One hand found in one frame."""

    image_xy: np.ndarray  # (21,2) pixels, MANO/MediaPipe order
    image_z: np.ndarray  # (21,) relative depth (pixels-ish, wrist-relative), as the model gives it
    world: np.ndarray  # (21,3) metres, hand-centred, image-aligned axes (x right, y down)
    presence: float  # hand presence score in [0, 1]
    p_right: float  # probability that this is a right hand (unmirrored image)
    rect: Rect  # the rectangle the landmarks were read in


def _normalize_angle(a: float) -> float:
    return a - 2 * math.pi * math.floor((a + math.pi) / (2 * math.pi))


@lru_cache(maxsize=1)
def palm_anchors() -> np.ndarray:
    """(2016,2) anchor centres in [0,1] (x, y) of palm_detection_full."""
    out = []
    i = 0
    while i < len(_STRIDES):
        stride, n = _STRIDES[i], 0
        while i < len(_STRIDES) and _STRIDES[i] == stride:  # layers sharing a stride share a grid
            n += 2
            i += 1
        g = int(math.ceil(PALM_SIZE / stride))
        ys, xs = np.meshgrid((np.arange(g) + 0.5) / g, (np.arange(g) + 0.5) / g, indexing="ij")
        out.append(np.repeat(np.stack([xs.ravel(), ys.ravel()], 1), n, axis=0))
    return np.concatenate(out)


class _Runner:
    """One network: LiteRT for .tflite, onnxruntime for .onnx; NHWC float32 in, outputs in model order."""

    def __init__(self, path: Path):
        self.path = path
        if path.suffix == ".onnx":
            import onnxruntime as ort

            opts = ort.SessionOptions()
            opts.intra_op_num_threads = 1
            opts.log_severity_level = 3
            self._sess = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
            self._in = self._sess.get_inputs()[0].name
            self._outs = [o.name for o in self._sess.get_outputs()]
            self.run = lambda x: self._sess.run(self._outs, {self._in: x})
        else:
            from ai_edge_litert.interpreter import Interpreter

            self._it = Interpreter(model_path=str(path), num_threads=1)
            self._it.allocate_tensors()
            self._in = self._it.get_input_details()[0]["index"]
            self._outs = [d["index"] for d in self._it.get_output_details()]
            self.run = self._run_tflite

    def _run_tflite(self, x: np.ndarray) -> list[np.ndarray]:
        self._it.set_tensor(self._in, x)
        self._it.invoke()
        return [self._it.get_tensor(i).copy() for i in self._outs]


@dataclass(frozen=True)
class HandModelFiles:
    palm: Path
    landmark: Path

    @classmethod
    def in_dir(cls, directory: Path, variant: str = "full") -> "HandModelFiles":
        d = Path(directory).expanduser()
        files = cls(*(d / f"{n}_{variant}{_suffix(d, n, variant)}" for n in ("palm_detection", "hand_landmark")))
        missing = [p for p in (files.palm, files.landmark) if not p.is_file()]
        if missing:
            raise HandModelError(
                f"MediaPipe hand model file {missing[0]} not found. Run `handedit models fetch` (takes the Apache-2.0 "
                f".tflite files out of the mediapipe 0.10.21 wheel on PyPI into {d}), or point "
                f"estimate_hands.model_dir (HANDEDIT_HAND_MODEL_DIR) at a folder holding palm_detection_{variant}.tflite "
                f"and hand_landmark_{variant}.tflite (or their .onnx conversions).")
        return files


def _suffix(d: Path, name: str, variant: str) -> str:
    return ".onnx" if (d / f"{name}_{variant}.onnx").is_file() and not (d / f"{name}_{variant}.tflite").is_file() else ".tflite"


class PalmDetector:
    def __init__(self, path: Path, min_score: float = 0.5, nms_iou: float = 0.3):
        self.net = _Runner(path)
        self.min_score, self.nms_iou = min_score, nms_iou

    def __call__(self, rgb: np.ndarray) -> list[tuple[float, np.ndarray, np.ndarray]]:
        """[(score, box (x0,y0,x1,y1) px, keypoints (7,2) px)] of the palms in an RGB frame."""
        H, W = rgb.shape[:2]
        s = PALM_SIZE / max(H, W)  # letterbox: keep the aspect ratio, pad with zeros
        nh, nw = int(round(H * s)), int(round(W * s))
        canvas = np.zeros((PALM_SIZE, PALM_SIZE, 3), np.float32)
        py, px = (PALM_SIZE - nh) // 2, (PALM_SIZE - nw) // 2
        canvas[py:py + nh, px:px + nw] = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        raw, logits = self.net.run(canvas[None])
        raw, logits = raw.reshape(-1, 18), logits.reshape(-1)
        score = 1.0 / (1.0 + np.exp(-np.clip(logits, -100, 100)))
        keep = np.flatnonzero(score >= self.min_score)
        if keep.size == 0:
            return []
        a = palm_anchors()[keep]
        r = raw[keep] / PALM_SIZE
        centre = r[:, 0:2] + a
        half = r[:, 2:4] / 2
        boxes = np.concatenate([centre - half, centre + half], 1)
        kps = r[:, 4:4 + 2 * _PALM_KEYPOINTS].reshape(-1, _PALM_KEYPOINTS, 2) + a[:, None]
        # letterbox removal: [0,1] of the padded square -> pixels of the frame
        to_px = lambda q: (q * PALM_SIZE - np.array([px, py])) / s  # noqa: E731
        boxes = np.concatenate([to_px(boxes[:, :2]), to_px(boxes[:, 2:])], 1)
        kps = to_px(kps)
        return _weighted_nms(score[keep], boxes, kps, self.nms_iou)


def _iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    x0 = np.maximum(box[0], boxes[:, 0])
    y0 = np.maximum(box[1], boxes[:, 1])
    x1 = np.minimum(box[2], boxes[:, 2])
    y1 = np.minimum(box[3], boxes[:, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area = lambda b: np.clip(b[..., 2] - b[..., 0], 0, None) * np.clip(b[..., 3] - b[..., 1], 0, None)  # noqa: E731
    return inter / np.maximum(area(box) + area(boxes) - inter, 1e-9)


def _weighted_nms(score, boxes, kps, thresh) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """MediaPipe's weighted NMS: each cluster's boxes and keypoints averaged by score."""
    order = np.argsort(-score)
    out = []
    while order.size:
        best = order[0]
        overlap = _iou(boxes[best], boxes[order]) > thresh
        members = order[overlap]
        w = score[members][:, None]
        out.append((float(score[best]), (boxes[members] * w).sum(0) / w.sum(), (kps[members] * w[:, :, None]).sum(0) / w.sum()))
        order = order[~overlap]
    return out


def palm_rect(kps: np.ndarray, box: np.ndarray) -> Rect:
    """The hand rectangle of one palm detection (rotation from wrist to middle knuckle)."""
    (x0, y0), (x1, y1) = kps[0], kps[2]
    rot = _normalize_angle(math.pi / 2 - math.atan2(-(y1 - y0), x1 - x0))
    w, h = box[2] - box[0], box[3] - box[1]
    return _transform(Rect((box[0] + box[2]) / 2, (box[1] + box[3]) / 2, w, h, rot), scale=2.6, shift_y=-0.5)


def landmarks_rect(xy: np.ndarray) -> Rect:
    """The next frame's rectangle from this frame's landmarks (tracking)."""
    x0, y0 = xy[0]
    mid = (xy[5] + xy[13]) / 2
    x1, y1 = (mid + xy[9]) / 2
    rot = _normalize_angle(math.pi / 2 - math.atan2(-(y1 - y0), x1 - x0))
    pts = xy[list(_RECT_SUBSET)]
    c, s = math.cos(rot), math.sin(rot)
    R = np.array([[c, s], [-s, c]])  # image -> rectangle axes
    local = pts @ R.T
    lo, hi = local.min(0), local.max(0)
    centre = R.T @ ((lo + hi) / 2)
    w, h = hi - lo
    return _transform(Rect(centre[0], centre[1], w, h, rot), scale=2.0, shift_y=-0.1)


def _transform(r: Rect, scale: float, shift_y: float) -> Rect:
    c, s = math.cos(r.rotation), math.sin(r.rotation)
    dx, dy = -r.h * shift_y * s, r.h * shift_y * c
    side = max(r.w, r.h) * scale  # square on the long side
    return Rect(r.cx + dx, r.cy + dy, side, side, r.rotation)


class LandmarkModel:
    def __init__(self, path: Path):
        self.net = _Runner(path)

    def __call__(self, rgb: np.ndarray, rect: Rect) -> HandLandmarks:
        A = rect.crop_from_image(LANDMARK_SIZE)
        crop = cv2.warpAffine(rgb, A, (LANDMARK_SIZE, LANDMARK_SIZE), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REPLICATE)
        outs = self.net.run((crop.astype(np.float32) / 255.0)[None])
        screen, presence, handed, world = (np.asarray(o, np.float64).reshape(-1) for o in outs)
        screen, world = screen.reshape(21, 3), world.reshape(21, 3)
        xy = screen[:, :2] @ A[:, :2].T + A[:, 2]
        c, s = math.cos(rect.rotation), math.sin(rect.rotation)
        Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])  # world landmarks into image-aligned axes
        # handedness: the model's label 0 ("Left") assumes a mirrored (selfie) image, i.e. is a right hand here
        return HandLandmarks(xy, screen[:, 2] * rect.w / LANDMARK_SIZE, world @ Rz.T, float(presence[0]),
                             float(handed[0]), rect)


class MediaPipeHands:
    """Palm detection + landmarks with tracking across consecutive frames (MediaPipe's loop)."""

    def __init__(self, files: HandModelFiles, max_hands: int = 2, min_detection: float = 0.5, min_presence: float = 0.5,
                 report_floor: float = 0.2):
        """Hands with presence >= ``min_presence`` are tracked into the next frame; those
        >= ``report_floor`` are reported (the caller decides what a weak one is worth)."""
        self.palm = PalmDetector(files.palm, min_detection)
        self.landmarks = LandmarkModel(files.landmark)
        self.max_hands, self.min_presence, self.report_floor = max_hands, min_presence, min(report_floor, min_presence)
        self._tracked: list[tuple[int, Rect]] = []
        self._next_id = 0
        self.palm_calls = 0

    def reset(self) -> None:
        self._tracked = []

    def __call__(self, rgb: np.ndarray) -> list[tuple[int, HandLandmarks]]:
        """[(track id, landmarks)] of the hands in this frame; ids persist while a hand is tracked."""
        rois = list(self._tracked)
        if len(rois) < self.max_hands:
            self.palm_calls += 1
            for score, box, kps in self.palm(rgb):
                r = palm_rect(kps, box)
                if all(_iou(r.box(), t.box()[None])[0] < 0.5 for _, t in rois):
                    rois.append((self._next_id, r))
                    self._next_id += 1
        found: list[tuple[int, HandLandmarks]] = []
        for tid, r in rois:
            lm = self.landmarks(rgb, r)
            if lm.presence < self.report_floor:
                continue
            if any(_iou(lm.rect.box(), o.rect.box()[None])[0] > 0.5 and _overlap(lm, o) for _, o in found):
                continue  # the same hand reached from two rectangles
            found.append((tid, lm))
        found = found[: self.max_hands]
        self._tracked = [(tid, landmarks_rect(lm.image_xy)) for tid, lm in found if lm.presence >= self.min_presence]
        return found


def _overlap(a: HandLandmarks, b: HandLandmarks) -> bool:
    scale = np.linalg.norm(a.image_xy[9] - a.image_xy[0]) + 1e-6
    return float(np.linalg.norm(a.image_xy - b.image_xy, axis=1).mean()) < 0.3 * scale
