"""onnxruntime wrappers for the frozen encoders the metric suite needs.

The user supplies ONNX files in one folder (``bench/export_encoders.py`` writes them
from public weights); nothing is downloaded at run time. Expected signatures (every
input is float32 NCHW RGB, already normalised by this module as (x01 - mean) / std):

=================  ======================  =====================  =========================
file               input                   output(s)              used by
=================  ======================  =====================  =========================
dinov2.onnx        (N,3,224,224)           (N,D) CLS embedding    Struct fidelity
clip_image.onnx    (N,3,224,224)           (N,D) image embedding  ID fidelity (S_ref)
inception.onnx     (N,3,299,299), [0,1]    (N,2048) pool feature  FID (full, ROI)
lpips_backbone     (N,3,H,W) any H,W>=32   L maps (N,C_l,h_l,w_l) LPIPS, Interaction
 .onnx             (LPIPS scaling folded   in layer order
                   into mean/std below)
lpips_heads.npz    --                      lin0..lin{L-1}: (C_l,) non-negative weights
=================  ======================  =====================  =========================

A static spatial size in the ONNX input is honoured (images are resized to it);
dynamic sizes use the spec's default (LPIPS: the image's own size). A missing file
disables only the metrics that need it; ``load_encoders`` reports which, loudly.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger("handedit.metrics")

IMAGENET_MEAN, IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
CLIP_MEAN, CLIP_STD = (0.48145466, 0.4578275, 0.40821073), (0.26862954, 0.26130258, 0.27577711)
# LPIPS ScalingLayer on [-1,1] inputs, (x - shift) / scale, rewritten for [0,1] inputs.
_LP_SHIFT, _LP_SCALE = np.array([-0.030, -0.088, -0.188]), np.array([0.458, 0.448, 0.450])
LPIPS_MEAN, LPIPS_STD = tuple((1 + _LP_SHIFT) / 2), tuple(_LP_SCALE / 2)


@dataclass(frozen=True)
class EncoderSpec:
    name: str
    filename: str
    size: int | None  # default square input side for dynamic models (None: keep image size)
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    metrics: tuple[str, ...]  # what is skipped when the file is missing


ENCODERS: dict[str, EncoderSpec] = {
    "dinov2": EncoderSpec("dinov2", "dinov2.onnx", 224, IMAGENET_MEAN, IMAGENET_STD, ("struct_fidelity",)),
    "clip": EncoderSpec("clip", "clip_image.onnx", 224, CLIP_MEAN, CLIP_STD, ("id_ref", "id_fidelity")),
    "inception": EncoderSpec("inception", "inception.onnx", 299, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), ("fid_full", "fid_roi")),
    "lpips": EncoderSpec("lpips", "lpips_backbone.onnx", None, LPIPS_MEAN, LPIPS_STD,
                         ("lpips_full", "lpips_bg", "lpips_roi", "interaction")),
}
LPIPS_HEADS = "lpips_heads.npz"
MIN_LPIPS_SIDE = 32


class EncoderError(RuntimeError):
    """An ONNX file that does not match the documented signature."""


@dataclass
class OnnxEncoder:
    """One ONNX session plus the preprocessing its signature expects."""

    spec: EncoderSpec
    path: Path
    session: object = field(repr=False)
    input_name: str = ""
    static_hw: tuple[int, int] | None = None

    @classmethod
    def load(cls, spec: EncoderSpec, path: Path) -> "OnnxEncoder":
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1  # one thread per Dask worker: the cluster is the parallelism
        opts.log_severity_level = 3
        try:
            sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:
            raise EncoderError(f"{path}: onnxruntime cannot load it ({exc}); re-export with bench/export_encoders.py") from None
        inputs = sess.get_inputs()
        if len(inputs) != 1 or len(inputs[0].shape) != 4:
            raise EncoderError(f"{path}: expected one NCHW image input, got {[(i.name, i.shape) for i in inputs]}")
        shp = inputs[0].shape
        static = (shp[2], shp[3]) if isinstance(shp[2], int) and isinstance(shp[3], int) else None
        return cls(spec, path, sess, inputs[0].name, static)

    def preprocess(self, images: list[np.ndarray]) -> np.ndarray:
        """uint8 (H,W,3) RGB images -> normalised float32 NCHW batch at the model's size."""
        if self.static_hw is not None:
            hw = self.static_hw
        elif self.spec.size is not None:
            hw = (self.spec.size, self.spec.size)
        else:
            hw = images[0].shape[:2]
            if any(im.shape[:2] != hw for im in images):
                raise ValueError("a dynamic-size encoder batch needs images of one size")
        out = np.empty((len(images), 3, hw[0], hw[1]), np.float32)
        mean, std = np.asarray(self.spec.mean, np.float32), np.asarray(self.spec.std, np.float32)
        for i, im in enumerate(images):
            x = im.astype(np.float32) / 255.0  # resize in float: no uint8 rounding of the averages
            if x.shape[:2] != hw:
                x = cv2.resize(x, (hw[1], hw[0]), interpolation=cv2.INTER_AREA if x.shape[0] > hw[0] else cv2.INTER_LINEAR)
            x = (x - mean) / std
            out[i] = x.transpose(2, 0, 1)
        return out

    def run(self, images: list[np.ndarray]) -> list[np.ndarray]:
        return self.session.run(None, {self.input_name: self.preprocess(images)})

    def embed(self, images: list[np.ndarray]) -> np.ndarray:
        """(N,D) float64 embeddings (first output, flattened per image)."""
        if not images:
            return np.zeros((0, 0))
        out = np.asarray(self.run(images)[0], np.float64)
        return out.reshape(out.shape[0], -1)


@dataclass
class LpipsNet:
    """LPIPS = sum_l mean_hw( w_l . (f0_l/|f0_l| - f1_l/|f1_l|)^2 ) (Zhang et al. 2018)."""

    backbone: OnnxEncoder
    heads: list[np.ndarray]

    @classmethod
    def load(cls, backbone: Path, heads: Path) -> "LpipsNet":
        enc = OnnxEncoder.load(ENCODERS["lpips"], backbone)
        try:
            with np.load(heads) as z:
                ws = [np.asarray(z[f"lin{i}"], np.float64).reshape(-1) for i in range(len(z.files))]
        except (OSError, KeyError, ValueError) as exc:
            raise EncoderError(f"{heads}: expected arrays lin0..lin(L-1) ({exc})") from None
        n_out = len(enc.session.get_outputs())
        if len(ws) != n_out:
            raise EncoderError(f"{heads} has {len(ws)} heads but {backbone} has {n_out} feature outputs")
        return cls(enc, ws)

    def layer_maps(self, a: np.ndarray, b: np.ndarray) -> list[np.ndarray]:
        """Per-layer (h_l, w_l) distance maps of one image pair."""
        if a.shape != b.shape:
            raise ValueError(f"LPIPS pair shapes differ: {a.shape} vs {b.shape}")
        a, b = _at_least(a, MIN_LPIPS_SIDE), _at_least(b, MIN_LPIPS_SIDE)
        feats = self.backbone.run([a, b])
        maps = []
        for f, w in zip(feats, self.heads):
            f = np.asarray(f, np.float64)
            if f.shape[1] != w.shape[0]:
                raise EncoderError(f"LPIPS head has {w.shape[0]} channels, backbone layer has {f.shape[1]}")
            n = f / (np.sqrt((f**2).sum(axis=1, keepdims=True)) + 1e-10)
            d = (n[0] - n[1]) ** 2
            maps.append(np.tensordot(w, d, axes=(0, 0)))
        return maps

    def distance(self, a: np.ndarray, b: np.ndarray) -> float:
        return float(sum(m.mean() for m in self.layer_maps(a, b)))

    def masked_distance(self, a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
        """LPIPS with each layer's map upsampled to the image and averaged over ``mask``."""
        return self.full_and_masked(a, b, mask)[1]

    def full_and_masked(self, a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
        """(LPIPS, LPIPS averaged over ``mask``) from one backbone pass."""
        maps = self.layer_maps(a, b)
        full = float(sum(lm.mean() for lm in maps))
        m = np.asarray(mask, bool)
        if not m.any():
            return full, float("nan")
        if min(m.shape) < MIN_LPIPS_SIDE:
            m = _at_least(m.astype(np.uint8), MIN_LPIPS_SIDE, nearest=True).astype(bool)
        h, w = m.shape
        total = 0.0
        for lm in maps:
            up = cv2.resize(lm.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
            total += float(up[m].mean())
        return full, total


def _at_least(im: np.ndarray, side: int, nearest: bool = False) -> np.ndarray:
    h, w = im.shape[:2]
    if min(h, w) >= side:
        return im
    s = side / min(h, w)
    size = (max(side, round(w * s)), max(side, round(h * s)))
    return cv2.resize(im, size, interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR)


@dataclass
class Encoders:
    """The loaded encoders (None where missing) and what that disables."""

    dinov2: OnnxEncoder | None = None
    clip: OnnxEncoder | None = None
    inception: OnnxEncoder | None = None
    lpips: LpipsNet | None = None
    missing: dict[str, str] = field(default_factory=dict)  # encoder -> why

    @property
    def skipped_metrics(self) -> list[str]:
        return [m for name in self.missing for m in ENCODERS[name].metrics]


def load_encoders(model_dir: str | Path | None) -> Encoders:
    """Load every encoder found in ``model_dir``; log an error for each one missing."""
    enc = Encoders()
    folder = Path(model_dir) if model_dir else None
    for name, spec in ENCODERS.items():
        path = folder / spec.filename if folder else None
        if path is None or not path.exists():
            enc.missing[name] = f"{path or spec.filename} not found"
            continue
        if name == "lpips":
            heads = folder / LPIPS_HEADS
            if not heads.exists():
                enc.missing[name] = f"{heads} not found (LPIPS needs the backbone and its linear heads)"
                continue
            enc.lpips = LpipsNet.load(path, heads)
        else:
            setattr(enc, name, OnnxEncoder.load(spec, path))
    for name, why in enc.missing.items():
        log.error("encoder %s missing (%s): skipping %s; export it with bench/export_encoders.py",
                  name, why, ", ".join(ENCODERS[name].metrics))
    return enc


def missing_encoders(model_dir: str | Path | None) -> dict[str, str]:
    """Encoder -> why it is unavailable, from file presence only (cheap; for the driver)."""
    folder = Path(model_dir) if model_dir else None
    out = {}
    for name, spec in ENCODERS.items():
        files = [spec.filename] + ([LPIPS_HEADS] if name == "lpips" else [])
        absent = [f for f in files if folder is None or not (folder / f).is_file()]
        if absent:
            out[name] = f"{', '.join(str(folder / f) if folder else f for f in absent)} not found"
    return out


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    a, b = np.asarray(a, np.float64).ravel(), np.asarray(b, np.float64).ravel()
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return 0.0
    return float(a @ b / (na * nb))
