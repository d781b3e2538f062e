"""Export the metric encoders to the ONNX files ``handedit.metrics.encoders`` reads.

Needs the optional ``export`` extra (torch, transformers, lpips, clean-fid, pytorch-fid)
and the weights on disk or in the Hugging Face / clean-fid caches; nothing here is needed at
evaluation time. The defaults are exactly the models the authors' toolkit scores with (its
``EvalConfig``): DINOv2-base, CLIP ViT-B/32 image features, LPIPS AlexNet and clean-fid's
Inception (the TF FID graph as TorchScript):

    python bench/export_encoders.py --out models/ --dinov2 facebook/dinov2-base \
        --clip openai/clip-vit-base-patch32 --lpips alex --inception cleanfid
    python bench/export_encoders.py --check models/      # onnxruntime-only: signatures + one forward pass

Signatures written (see ``handedit/metrics/encoders.py``). The graphs hold no preprocessing:
the toolkit protocol (``handedit.metrics.toolkit``) does it in numpy as the Hugging Face
processors and clean-fid do (shortest-edge bicubic resize, centre crop, normalisation; the
float per-channel bicubic resize to 299), the paper protocol with the mean/std listed there:

- dinov2.onnx       (N,3,224,224) -> (N,768) CLS token of the last layer (after the final norm)
- clip_image.onnx   (N,3,224,224) -> (N,512) projected image features (``get_image_features``)
- inception.onnx    (N,3,299,299) in [0,1] -> (N,2048) pool3 features of the FID Inception
  (``cleanfid``: clean-fid's InceptionV3W fed x * 255, as its "clean" mode feeds it;
  ``pytorch-fid[:weights.pth]``: pytorch-fid's port, for the paper protocol's older runs)
- lpips_backbone.onnx (N,3,H,W) (LPIPS scaling folded into handedit's mean/std) -> the L
  feature maps LPIPS compares (alex: 5 ReLU outputs), and lpips_heads.npz with lin0..lin{L-1}

Not run on the project's CI machine (no torch, no network there); ``--check`` is.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

OPSET = 17


def _torch():
    try:
        import torch
    except ImportError:
        raise SystemExit("exporting needs torch: pip install 'handedit[export]' (torch, transformers, lpips, pytorch-fid)") from None
    return torch


def _export(module, example, path: Path, out_names: list[str], dynamic_hw: bool = False) -> None:
    torch = _torch()
    module.eval()
    axes = {"image": {0: "N", **({2: "H", 3: "W"} if dynamic_hw else {})}}
    axes.update({n: {0: "N"} for n in out_names})
    with torch.no_grad():
        torch.onnx.export(module, (example,), str(path), input_names=["image"], output_names=out_names,
                          dynamic_axes=axes, opset_version=OPSET, do_constant_folding=True)
    print(f"wrote {path}")


def export_dinov2(name: str, out: Path) -> None:
    torch = _torch()
    from transformers import AutoModel

    model = AutoModel.from_pretrained(name)

    class Cls(torch.nn.Module):
        def __init__(self, m):
            super().__init__()
            self.m = m

        def forward(self, x):
            return self.m(pixel_values=x).last_hidden_state[:, 0]

    _export(Cls(model), torch.zeros(1, 3, 224, 224), out / "dinov2.onnx", ["embedding"])


def export_clip(name: str, out: Path) -> None:
    torch = _torch()
    from transformers import CLIPVisionModelWithProjection

    model = CLIPVisionModelWithProjection.from_pretrained(name)

    class Emb(torch.nn.Module):
        def __init__(self, m):
            super().__init__()
            self.m = m

        def forward(self, x):
            return self.m(pixel_values=x).image_embeds  # = CLIPModel.get_image_features

    size = int(model.config.image_size)
    _export(Emb(model), torch.zeros(1, 3, size, size), out / "clip_image.onnx", ["embedding"])


def export_inception(kind: str, out: Path) -> None:
    """``cleanfid`` (the toolkit's FID network) or ``pytorch-fid[:weights.pth]``."""
    torch = _torch()
    name, _, weights = kind.partition(":")

    class Pool(torch.nn.Module):
        def __init__(self, m, scale):
            super().__init__()
            self.m, self.scale = m, scale

        def forward(self, x):
            y = self.m(x * self.scale)
            return (y[0] if isinstance(y, (list, tuple)) else y).flatten(1)

    if name == "cleanfid":
        import tempfile

        from cleanfid.inception_torchscript import InceptionV3W

        cache = weights or tempfile.mkdtemp(prefix="cleanfid-")  # a folder holding inception-2015-12-05.pt
        net, scale = InceptionV3W(cache, download=True, resize_inside=False), 255.0  # it takes [0, 255]
    elif name == "pytorch-fid":
        from pytorch_fid.inception import InceptionV3

        if weights:  # pytorch-fid loads FID_WEIGHTS_URL through torch.hub; point its cache at the file
            import pytorch_fid.inception as pi

            state = torch.load(weights, map_location="cpu")
            pi.load_state_dict_from_url = lambda *a, **k: state  # noqa: E731
        net, scale = InceptionV3([InceptionV3.BLOCK_INDEX_BY_DIM[2048]], resize_input=False, normalize_input=True), 1.0
    else:
        raise SystemExit(f"--inception {kind!r}: use cleanfid[:DIR] or pytorch-fid[:weights.pth]")
    _export(Pool(net, scale), torch.zeros(1, 3, 299, 299), out / "inception.onnx", ["features"])


def export_lpips(net_name: str, out: Path) -> None:
    torch = _torch()
    import lpips

    model = lpips.LPIPS(net=net_name, verbose=False)
    n_layers = len(model.chns)

    class Backbone(torch.nn.Module):
        def __init__(self, m):
            super().__init__()
            self.m = m

        def forward(self, x):
            return tuple(self.m.net(x))

    names = [f"feat{i}" for i in range(n_layers)]
    _export(Backbone(model), torch.zeros(1, 3, 64, 64), out / "lpips_backbone.onnx", names, dynamic_hw=True)
    heads = {f"lin{i}": lin.model[-1].weight.detach().numpy().reshape(-1) for i, lin in enumerate(model.lins)}
    np.savez(out / "lpips_heads.npz", **heads)
    print(f"wrote {out / 'lpips_heads.npz'}")


def check(folder: Path) -> int:
    """Load every encoder with onnxruntime and run one forward pass; print what is missing."""
    from handedit.metrics.encoders import load_encoders

    enc = load_encoders(folder)
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)
    b = np.clip(a.astype(int) + rng.integers(-20, 21, a.shape), 0, 255).astype(np.uint8)
    for name in ("dinov2", "clip", "inception"):
        e = getattr(enc, name)
        if e is not None:
            print(f"{name:10s} {e.path.name}: input {e.static_hw or 'dynamic'} -> embedding {e.embed([a]).shape[1]} dims")
    if enc.lpips is not None:
        print(f"lpips      {len(enc.lpips.heads)} layers; LPIPS(a, a+noise) = {enc.lpips.distance(a, b):.4f}, LPIPS(a, a) = {enc.lpips.distance(a, a):.4f}")
    for name, why in enc.missing.items():
        print(f"{name:10s} MISSING ({why})")
    return 1 if enc.missing else 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, help="folder to write the ONNX files into")
    p.add_argument("--dinov2", help="HF id or local folder, e.g. facebook/dinov2-base")
    p.add_argument("--clip", help="HF id or local folder; the toolkit's: openai/clip-vit-base-patch32")
    p.add_argument("--inception", nargs="?", const="cleanfid",
                   help="cleanfid[:DIR] (the toolkit's, default) or pytorch-fid[:weights.pth]")
    p.add_argument("--lpips", choices=("alex", "vgg", "squeeze"), help="LPIPS backbone")
    p.add_argument("--check", type=Path, help="verify an exported folder with onnxruntime only")
    args = p.parse_args(argv)
    if args.check:
        return check(args.check)
    if not args.out:
        p.error("--out is required when exporting")
    args.out.mkdir(parents=True, exist_ok=True)
    if args.dinov2:
        export_dinov2(args.dinov2, args.out)
    if args.clip:
        export_clip(args.clip, args.out)
    if args.inception is not None:
        export_inception(args.inception, args.out)
    if args.lpips:
        export_lpips(args.lpips, args.out)
    return check(args.out)


if __name__ == "__main__":
    sys.exit(main())
