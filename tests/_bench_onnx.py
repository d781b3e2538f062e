"""Small ONNX encoders for the metric tests, built with onnx.helper (no weights to download).

- embedder(size, dim): 1x1 conv (fixed weights) -> global average pool -> (N, dim);
  with a static ``size`` input, so the production code must resize to it.
- lpips backbone: two feature maps, a 1x1 conv at full resolution and a 1x1 conv on a
  2x2 average pool, with a dynamic spatial size; plus non-negative linear heads.
Both are linear enough that the tests recompute the expected numbers in numpy.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

RNG = np.random.default_rng(1234)
EMB_W = {name: RNG.normal(size=(dim, 3)).astype(np.float32) for name, dim in (("dinov2", 6), ("clip", 5), ("inception", 4))}
LP_W0 = RNG.normal(size=(4, 3)).astype(np.float32)
LP_W1 = RNG.normal(size=(5, 3)).astype(np.float32)
LP_HEADS = [np.abs(RNG.normal(size=4)) + 0.1, np.abs(RNG.normal(size=5)) + 0.1]


def _save(graph, path: Path) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def embedder(path: Path, w: np.ndarray, size: int = 32) -> Path:
    dim = w.shape[0]
    x = helper.make_tensor_value_info("pixel_values", TensorProto.FLOAT, ["N", 3, size, size])
    y = helper.make_tensor_value_info("embedding", TensorProto.FLOAT, ["N", dim])
    nodes = [
        helper.make_node("Conv", ["pixel_values", "W"], ["c"]),
        helper.make_node("GlobalAveragePool", ["c"], ["p"]),
        helper.make_node("Flatten", ["p"], ["embedding"]),
    ]
    init = [numpy_helper.from_array(w.reshape(dim, 3, 1, 1), "W")]
    return _save(helper.make_graph(nodes, "embedder", [x], [y], init), path)


def lpips_backbone(path: Path) -> Path:
    x = helper.make_tensor_value_info("image", TensorProto.FLOAT, ["N", 3, "H", "W"])
    outs = [helper.make_tensor_value_info("feat0", TensorProto.FLOAT, ["N", 4, "H", "W"]),
            helper.make_tensor_value_info("feat1", TensorProto.FLOAT, ["N", 5, "h", "w"])]
    nodes = [
        helper.make_node("Conv", ["image", "W0"], ["feat0"]),
        helper.make_node("AveragePool", ["image"], ["pooled"], kernel_shape=[2, 2], strides=[2, 2]),
        helper.make_node("Conv", ["pooled", "W1"], ["feat1"]),
    ]
    init = [numpy_helper.from_array(LP_W0.reshape(4, 3, 1, 1), "W0"), numpy_helper.from_array(LP_W1.reshape(5, 3, 1, 1), "W1")]
    return _save(helper.make_graph(nodes, "lpips", [x], outs, init), path)


TOOLKIT_SIZES = {"dinov2": 224, "clip": 224, "inception": 299}  # what the toolkit protocol feeds


def write_encoders(folder: Path, skip: tuple[str, ...] = (), sizes: dict[str, int] | None = None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    names = {"dinov2": "dinov2.onnx", "clip": "clip_image.onnx", "inception": "inception.onnx"}
    for name, fname in names.items():
        if name not in skip:
            embedder(folder / fname, EMB_W[name], (sizes or {}).get(name, 32))
    if "lpips" not in skip:
        lpips_backbone(folder / "lpips_backbone.onnx")
        np.savez(folder / "lpips_heads.npz", lin0=LP_HEADS[0], lin1=LP_HEADS[1])
    return folder
