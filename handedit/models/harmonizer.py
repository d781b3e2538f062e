"""ONNX harmonizer plug-in (Harmonizer-style): composite + robot mask -> harmonized image.

Contract (names exact; H, W dynamic or fixed):
    inputs   composite   float32 (1, 3, H, W)  RGB in [0, 1]
             mask        float32 (1, 1, H, W)  1 = robot (foreground to adjust)
    outputs  harmonized  float32 (1, 3, H, W)  RGB in [0, 1]

How it is driven: per frame at the model's fixed size (or ``work_max_side``); the output
is resized back and blended into the original only over the robot mask dilated by
``edge_px`` with a weight fading across that band, so pixels outside it (the scene, the
geometry) never change, whatever the network does there.

Exporting Harmonizer (ZHKKKe/Harmonizer): its ``Harmonizer`` module predicts filter
arguments from (composite, mask) and applies them with ``restore_image``; wrap both in
one ``forward(composite, mask)`` returning the harmonized image and export with
``torch.onnx.export(m, (comp, mask), "harmonizer.onnx", input_names=["composite",
"mask"], output_names=["harmonized"], dynamic_axes={"composite": {2: "H", 3: "W"},
"mask": {2: "H", 3: "W"}, "harmonized": {2: "H", 3: "W"}})``.
"""

from __future__ import annotations

import cv2
import numpy as np

from handedit.models.runtime import Contract, ModelContractError, TensorSpec, load_model

CONTRACT = Contract(
    kind="harmonizer",
    inputs=(TensorSpec("composite", 4, doc="(1,3,H,W) RGB in [0,1]"), TensorSpec("mask", 4, doc="(1,1,H,W) 1 = robot")),
    outputs=(TensorSpec("harmonized", 4, doc="(1,3,H,W) RGB in [0,1]"),),
)


def harmonize_onnx_frame(model, image: np.ndarray, mask: np.ndarray, cfg) -> np.ndarray:
    H, W = image.shape[:2]
    mh, mw = model.work_hw("composite", H, W, cfg.work_max_side)
    comp = cv2.resize(image, (mw, mh), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    mk = cv2.resize(mask.astype(np.float32), (mw, mh), interpolation=cv2.INTER_LINEAR)
    feeds = {"composite": comp.transpose(2, 0, 1)[None], "mask": mk[None, None]}
    res = np.asarray(model.run(feeds)["harmonized"], np.float32)
    if res.shape != (1, 3, mh, mw):
        raise ModelContractError(f"harmonizer model {model.path} returned {res.shape}; expected {(1, 3, mh, mw)}")
    out = cv2.resize(np.clip(res[0].transpose(1, 2, 0), 0, 1), (W, H), interpolation=cv2.INTER_LINEAR) * 255.0
    dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 3)
    w = np.clip(1.0 - dist / (cfg.edge_px + 1.0), 0.0, 1.0)[..., None]
    blended = w * out + (1 - w) * image.astype(np.float32)
    result = image.copy()
    region = w[..., 0] > 0
    result[region] = np.clip(np.round(blended[region]), 0, 255).astype(np.uint8)
    return result


def load_harmonizer(path, runtime=None):
    return load_model(path, CONTRACT, runtime)
