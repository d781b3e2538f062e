"""ONNX video inpainter plug-in (ProPainter-style): a window of frames + masks -> restored frames.

Contract (names exact; T, H, W dynamic or fixed):
    inputs   frames    float32 (1, T, 3, H, W)  RGB in [0, 1]
             masks     float32 (1, T, 1, H, W)  1 = hole to fill, 0 = known
    outputs  restored  float32 (1, T, 3, H, W)  RGB in [0, 1]

How it is driven: for each target frame, a window of T frames centred on it (clamped to
the chunk's window; T = the model's fixed T, else ``2 * window + 1`` capped at the frames
available) is resized to the model's H x W (fixed) or kept at ``work_max_side``; the
restored target is resized back and pasted **only inside the hole**: known pixels stay
bit-exact. The hole is the dilated mask, as in the classical path, and the same residue
and ghosting checks run on the result.

Exporting ProPainter: wrap ``InpaintGenerator`` (with its RAFT flow completion) in a
module whose ``forward(frames, masks)`` maps [0, 1] -> [-1, 1], computes flows with the
bundled RAFT, runs the propagation + transformer and maps back to [0, 1]; export with
``torch.onnx.export(m, (frames, masks), "propainter.onnx", input_names=["frames",
"masks"], output_names=["restored"], opset_version=17)`` at a fixed T (e.g. 10) and a
fixed size (e.g. 432 x 240; the wrapper resizes). Deformable convolutions need an opset
/ onnxruntime build that supports them (or ``torchvision.ops`` replaced by grid_sample).
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

from handedit.models.runtime import Contract, ModelContractError, TensorSpec, load_model

CONTRACT = Contract(
    kind="video inpainter",
    inputs=(
        TensorSpec("frames", 5, doc="(1,T,3,H,W) RGB in [0,1]"),
        TensorSpec("masks", 5, doc="(1,T,1,H,W) 1 = hole"),
    ),
    outputs=(TensorSpec("restored", 5, doc="(1,T,3,H,W) RGB in [0,1]"),),
)


def inpaint_onnx(frames: np.ndarray, holes: Sequence[np.ndarray], targets: np.ndarray, ok: np.ndarray, cfg) -> tuple[np.ndarray, str]:
    """Restored ``frames[targets]`` (uint8) and the provenance tag; holes: m (H,W) bool masks."""
    model = load_model(cfg.model_path, CONTRACT, cfg.onnx)
    m, H, W = frames.shape[:3]
    mh, mw = model.work_hw("frames", H, W, cfg.work_max_side)
    usable = np.flatnonzero(ok)
    T = model.fixed_dim("frames", 1) or min(2 * cfg.window + 1, max(1, len(usable)))
    small = {}

    def prep(j: int) -> tuple[np.ndarray, np.ndarray]:
        if j not in small:
            f = cv2.resize(frames[j], (mw, mh), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
            h = cv2.resize(holes[j].astype(np.uint8), (mw, mh), interpolation=cv2.INTER_NEAREST).astype(np.float32)
            small[j] = (f.transpose(2, 0, 1), h[None])
        return small[j]

    out = np.zeros((len(targets), H, W, 3), np.uint8)
    for k, t in enumerate(targets):
        t = int(t)
        if not holes[t].any():
            out[k] = frames[t]
            continue
        # T usable frames nearest to t, in time order; the target is always one of them
        pool = usable if ok[t] else np.array([t])
        pool = np.union1d(pool, [t])
        idx = sorted(pool[np.argsort(np.abs(pool - t), kind="stable")[:T]].tolist())
        while len(idx) < T:  # fewer frames than a fixed T: repeat the target
            idx.append(t)
            idx.sort()
        fr = np.stack([prep(j)[0] for j in idx])[None]
        mk = np.stack([prep(j)[1] for j in idx])[None]
        res = np.asarray(model.run({"frames": fr, "masks": mk})["restored"], np.float32)
        if res.shape != fr.shape:
            raise ModelContractError(f"video inpainter model {model.path} returned restored {res.shape}; expected {fr.shape}")
        r = res[0, idx.index(t)].transpose(1, 2, 0)
        r = cv2.resize(np.clip(r, 0, 1), (W, H), interpolation=cv2.INTER_LINEAR)
        img = frames[t].copy()
        img[holes[t]] = np.clip(np.round(r[holes[t]] * 255.0), 0, 255).astype(np.uint8)
        out[k] = img
    return out, f"onnx:video-inpainter:{model.tag}"
