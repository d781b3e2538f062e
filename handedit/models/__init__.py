"""Learned-model plug-ins run with onnxruntime, each behind a documented tensor contract.

``segmenter`` (SAM-style), ``inpainter`` (ProPainter-style video inpainting),
``harmonizer`` (Harmonizer-style). A stage uses one when its config says
``method="onnx"`` and ``model_path=...``; the flows do not change. ``runtime`` loads a
file, checks it against the contract (clear ``ModelContractError`` naming the file and
the expected signature) and hashes it for provenance (the stage's ``method`` string reads
``onnx:<kind>:<file>@sha256:<16 hex>``). The module docstrings say how to export the
paper's defaults (SAM 3, ProPainter, Harmonizer) to each contract.
"""

from handedit.models.runtime import Contract, LoadedModel, ModelContractError, TensorSpec, file_sha256, load_model

__all__ = ["Contract", "LoadedModel", "ModelContractError", "TensorSpec", "file_sha256", "load_model"]
