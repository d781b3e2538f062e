"""ONNX hand-pose plug-in (HaMeR / WiLoR-style): a hand crop -> MANO-21 joints + a camera.

Contract (names exact; N and the crop size C may be dynamic or fixed):
    inputs   image   float32 (N, 3, C, C)  RGB in [0, 1], a square crop around one hand;
                                           left hands are mirrored left-right, so every crop
                                           shows a right hand (HaMeR's and WiLoR's convention)
    outputs  joints  float32 (N, 21, 3)    metres, MANO-21 order (``handedit.keypoints``), in
                                           the crop's camera axes (x right, y down, z forward),
                                           any origin (the camera below places them)
             camera  float32 (N, 3)        weak-perspective (s, tx, ty): a joint X projects to
                                           crop pixel C/2 * (1 + s * (X_x + tx, X_y + ty))

How it is used: MediaPipe still finds, tracks and labels the hands (``estimate_hands``);
for each found hand the square box around its landmark rectangle is cropped (mirrored for
a left hand), and the model's joints are placed in the camera like HaMeR's
``cam_crop_to_full``: the crop's weak-perspective scale gives depth
tz = 2 f / (s * b) (b: the box side in pixels), and the box centre's offset from the
principal point gives the lateral translation. A left hand's joints are mirrored back.

Exporting HaMeR: wrap the model so ``forward(image)`` normalises the [0, 1] crop with its
ImageNet mean/std at 256x256 and returns ``(pred_keypoints_3d[:, :21] in MANO-21 order,
pred_cam)``; ``torch.onnx.export(m, torch.rand(1, 3, 256, 256), "hamer.onnx",
input_names=["image"], output_names=["joints", "camera"], dynamic_axes={"image": {0: "N"}})``.
HaMeR's own joint order is OpenPose's, which is this one.
"""

from __future__ import annotations

import cv2
import numpy as np

from handedit.camera import Intrinsics
from handedit.models.runtime import Contract, TensorSpec, load_model

CONTRACT = Contract(
    kind="hand pose",
    inputs=(TensorSpec("image", 4, doc="(N,3,C,C) RGB in [0,1], right-hand view"),),
    outputs=(TensorSpec("joints", 3, doc="(N,21,3) metres, MANO-21"), TensorSpec("camera", 2, doc="(N,3) s, tx, ty")),
)
DEFAULT_CROP = 256


def square_box(box: np.ndarray, pad: float = 1.0) -> tuple[float, float, float]:
    """(cx, cy, side) of the square around an (x0, y0, x1, y1) box."""
    x0, y0, x1, y1 = (float(v) for v in box)
    return (x0 + x1) / 2, (y0 + y1) / 2, max(x1 - x0, y1 - y0) * pad


def crop(rgb: np.ndarray, centre_side: tuple[float, float, float], size: int, mirror: bool) -> np.ndarray:
    """(3, size, size) float crop of the square, mirrored left-right for a left hand."""
    cx, cy, b = centre_side
    s = size / b
    A = np.array([[s, 0, size / 2 - s * cx], [0, s, size / 2 - s * cy]])
    out = cv2.warpAffine(rgb, A, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    if mirror:
        out = out[:, ::-1]
    return np.ascontiguousarray(out.transpose(2, 0, 1), np.float32) / 255.0


def to_camera(joints: np.ndarray, camera: np.ndarray, centre_side: tuple[float, float, float], intr: Intrinsics,
              mirror: bool) -> np.ndarray:
    """The model's joints placed in the full image's camera frame (see the module doc)."""
    cx, cy, b = centre_side
    s, tx, ty = (float(v) for v in camera)
    J = np.asarray(joints, np.float64).copy()
    if mirror:  # back from the mirrored crop: x -> -x (and the crop's tx with it)
        J[:, 0] *= -1
        tx = -tx
    f = 0.5 * (intr.fx + intr.fy)
    tz = 2.0 * f / (max(abs(s), 1e-9) * b)
    t = np.array([tx + 2.0 * (cx - intr.cx) / (s * b), ty + 2.0 * (cy - intr.cy) / (s * b), tz])
    return J + t


class HandPoseLifter:
    """The plug-in as ``estimate_hands``'s lifter: (rgb, HandLandmarks, side) -> (21,3) camera joints."""

    def __init__(self, path, intr: Intrinsics, runtime=None):
        self.model = load_model(path, CONTRACT, runtime)
        hw = self.model.fixed_hw("image")
        self.size = hw[0] if hw else DEFAULT_CROP
        self.intr = intr

    @property
    def tag(self) -> str:
        return self.model.tag

    def __call__(self, rgb: np.ndarray, lm, side: int) -> np.ndarray:
        mirror = side == 0  # SIDES order: 0 left, 1 right
        box = square_box(lm.rect.box(), pad=1.0 / 1.3)  # the rectangle is 2-2.6x the hand: HaMeR-like margin
        out = self.model.run({"image": crop(rgb, box, self.size, mirror)[None]})
        return to_camera(out["joints"][0], out["camera"][0], box, self.intr, mirror)
