"""Tiny reference models that satisfy each contract, built in code with ``onnx.helper``.

Why: tests (and anyone checking an export pipeline) need real ONNX files that go through
the full loading, contract check, pre- and post-processing path, without downloads.
They compute something simple but real: the segmenter thresholds redness (R - B), the
inpainter fills each hole pixel with the temporal mean of the window's known pixels
(grey where no frame saw it), the harmonizer pulls the robot towards the image mean.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17


def _save(graph: onnx.GraphProto, path: str | Path) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    path = Path(path)
    onnx.save(model, str(path))
    return path


def _const(name: str, value) -> onnx.TensorProto:
    return numpy_helper.from_array(np.asarray(value, np.float32), name)


def _f(name: str, shape: list) -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info(name, TensorProto.FLOAT, shape)


def make_segmenter(path, score: float = 0.9, threshold: float = 0.12, gain: float = 40.0,
                   image_hw: tuple[int, int] | None = None, image_name: str = "image") -> Path:
    """masks = gain * (R - B - threshold); scores = ``score`` (independent of the prompts)."""
    H, W = image_hw if image_hw else ("H", "W")
    nodes = [
        helper.make_node("Slice", [image_name, "s0", "s1", "ax1"], ["R"]),
        helper.make_node("Slice", [image_name, "s2", "s3", "ax1"], ["B"]),
        helper.make_node("Sub", ["R", "B"], ["rb"]),
        helper.make_node("Sub", ["rb", "thr"], ["rbt"]),
        helper.make_node("Mul", ["rbt", "gain"], ["masks"]),
        helper.make_node("ReduceMean", ["points"], ["pm"], keepdims=0),
        helper.make_node("ReduceMean", ["point_labels"], ["lm"], keepdims=0),
        helper.make_node("Add", ["pm", "lm"], ["plm"]),
        helper.make_node("Mul", ["plm", "zero"], ["z"]),
        helper.make_node("Add", ["score", "z"], ["scores"]),
    ]
    inits = [
        numpy_helper.from_array(np.array([0], np.int64), "s0"), numpy_helper.from_array(np.array([1], np.int64), "s1"),
        numpy_helper.from_array(np.array([2], np.int64), "s2"), numpy_helper.from_array(np.array([3], np.int64), "s3"),
        numpy_helper.from_array(np.array([1], np.int64), "ax1"),
        _const("thr", threshold), _const("gain", gain), _const("zero", 0.0), _const("score", [[score]]),
    ]
    graph = helper.make_graph(
        nodes, "toy_segmenter",
        [_f(image_name, [1, 3, H, W]), _f("points", [1, "N", 2]), _f("point_labels", [1, "N"])],
        [_f("masks", [1, 1, H, W]), _f("scores", [1, 1])], inits,
    )
    return _save(graph, path)


def make_inpainter(path, t_fixed: int | None = None) -> Path:
    """restored = known pixels, holes = temporal mean of known pixels (0.5 if none)."""
    T = t_fixed or "T"
    nodes = [
        helper.make_node("Sub", ["one", "masks"], ["known"]),
        helper.make_node("Mul", ["frames", "known"], ["fk"]),
        helper.make_node("ReduceMean", ["fk"], ["fk_m"], axes=[1], keepdims=1),
        helper.make_node("ReduceMean", ["known"], ["k_m"], axes=[1], keepdims=1),
        helper.make_node("Mul", ["k_m", "half_eps"], ["grey"]),
        helper.make_node("Add", ["fk_m", "eps_half"], ["num"]),
        helper.make_node("Add", ["k_m", "eps"], ["den"]),
        helper.make_node("Div", ["num", "den"], ["fill"]),
        helper.make_node("Mul", ["masks", "fill"], ["mf"]),
        helper.make_node("Add", ["fk", "mf"], ["restored"]),
    ]
    inits = [_const("one", 1.0), _const("eps", 1e-4), _const("eps_half", 0.5e-4), _const("half_eps", 0.0)]
    graph = helper.make_graph(
        nodes, "toy_inpainter",
        [_f("frames", [1, T, 3, "H", "W"]), _f("masks", [1, T, 1, "H", "W"])],
        [_f("restored", [1, T, 3, "H", "W"])], inits,
    )
    return _save(graph, path)


def make_harmonizer(path, pull: float = 0.3) -> Path:
    """harmonized = composite outside the mask; inside, moved ``pull`` towards the image mean."""
    nodes = [
        helper.make_node("ReduceMean", ["composite"], ["mu"], axes=[2, 3], keepdims=1),
        helper.make_node("Sub", ["mu", "composite"], ["d"]),
        helper.make_node("Mul", ["d", "pull"], ["pd"]),
        helper.make_node("Mul", ["pd", "mask"], ["mpd"]),
        helper.make_node("Add", ["composite", "mpd"], ["harmonized"]),
    ]
    graph = helper.make_graph(
        nodes, "toy_harmonizer",
        [_f("composite", [1, 3, "H", "W"]), _f("mask", [1, 1, "H", "W"])],
        [_f("harmonized", [1, 3, "H", "W"])], [_const("pull", pull)],
    )
    return _save(graph, path)
