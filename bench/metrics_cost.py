"""CPU cost of the metric arithmetic per item at a given resolution, side by side.

    .venv/bin/python bench/metrics_cost.py [--width 640 --height 480 --repeat 5]

Encoders are the tiny ONNX stand-ins of the tests (1x1 convs), so this measures what
handedit itself adds around real encoders (resizing, masking, SSIM windows, Lab), not
DINOv2/CLIP/Inception inference. Prints ms per metric group and the share of the item.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from _bench_onnx import write_encoders  # noqa: E402
from handedit.metrics import embodied, similarity  # noqa: E402
from handedit.metrics.encoders import load_encoders  # noqa: E402
from handedit.metrics.suite import ItemImages, score_item  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--repeat", type=int, default=5)
    a = p.parse_args()
    h, w = a.height, a.width
    r = np.random.default_rng(0)
    gt = r.integers(0, 256, (h, w, 3), dtype=np.uint8)
    pred = np.clip(gt.astype(int) + r.integers(-30, 31, gt.shape), 0, 255).astype(np.uint8)
    human = np.zeros((h, w), bool)
    human[h // 4: h // 2, w // 4: w // 2] = True
    robot = np.roll(human, 10, axis=1)
    obj = np.roll(human, h // 5, axis=0)
    roi = human | robot
    enc = load_encoders(write_encoders(Path(tempfile.mkdtemp())))
    items = ItemImages(gt, pred, gt, human, robot, obj, [gt[:128, :128]], [np.ones((128, 128), bool)])
    groups = {
        "psnr full+bg": lambda: (similarity.psnr(pred, gt), similarity.psnr(pred, gt, ~roi)),
        "ssim (full+bg, 1 map)": lambda: similarity.ssim_mean(similarity.ssim_map(pred, gt), ~roi),
        "lpips full+bg (tiny)": lambda: enc.lpips.full_and_masked(pred, gt, ~roi),
        "removal": lambda: embodied.removal(pred, roi),
        "lab dE": lambda: embodied.delta_e_lab(pred, gt, robot),
        "whole item": lambda: score_item(items, enc),
    }
    times = {}
    for name, fn in groups.items():
        fn()
        t = time.perf_counter()
        for _ in range(a.repeat):
            fn()
        times[name] = (time.perf_counter() - t) / a.repeat * 1000
    load = os.getloadavg()[0]
    print(f"{w}x{h}, {a.repeat} repeats, load average {load:.1f}")
    for name, ms in times.items():
        print(f"  {name:22s} {ms:8.1f} ms   {ms / times['whole item']:6.1%} of the item")


if __name__ == "__main__":
    main()
