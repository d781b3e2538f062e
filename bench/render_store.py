"""The render stage on a curated store's own joint tracks: ms per frame, both robots, as curation renders them.

    .venv/bin/python bench/render_store.py --store runs/lid94 [--embodiment kuka_sharpa ...] [--repeats 2]
        [--decimate 0.25] [--lod-px 1.0 | --lod-px 0] [--against-full]

``bench/render.py`` frames one robot at 640x480 in a fixed view; on real clips a hand-arm's two
robots are drawn at the working resolution from the head camera, their bases behind it and their
upper arms beside it, which is where the stage's time goes (issue 39's goal: <= 60 ms per frame
for every hand-arm at 960x540). This runs ``render.stage.render_stage`` on every clip's retarget
output (`bench/egodex.py --out DIR` makes such a store) in this process, after one warm-up pass
that builds the renderers, and prints per clip and embodiment: the warm ms per frame (median of
``--repeats``), each side's mean screen box as a share of the frame, and the load average. To
compare two commits, run it from each checkout on the same store, back to back; ``--decimate``
times the simplified meshes (``RenderConfig.decimate``), ``--lod-px`` the levels of detail
(``RenderConfig.lod_px``; 0: the full meshes always). ``--against-full`` also times the full meshes
(``lod_px`` None, no decimation) in the same loop and prints the ratio, the silhouette IoU over the
frames either render shows (all and the worst frame) and the mean colour difference where both
show the robot.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _runs import open_run  # noqa: E402


def main() -> None:
    import numpy as np

    from handedit.camera import Intrinsics
    from handedit.reasons import Reason, gate
    from handedit.render import render_embodiment
    from handedit.render.stage import RenderConfig, render_stage
    from handedit.storage import Unit
    from handedit.storage.layout import clip_path

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--store", required=True, help="an output folder of bench/egodex.py or handedit curate")
    ap.add_argument("--embodiment", action="append", help="default: every embodiment in the store")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--decimate", type=float, default=None, help="RenderConfig.decimate (default: full meshes)")
    ap.add_argument("--lod-px", type=float, default=RenderConfig().lod_px,
                    help=f"RenderConfig.lod_px (default {RenderConfig().lod_px}; 0: full meshes always)")
    ap.add_argument("--against-full", action="store_true", help="also time the full meshes, side by side")
    args = ap.parse_args()
    root = open_run(args.store, "bench/render_store.py", f"bench/egodex.py --out {args.store}")
    cfg = RenderConfig(decimate=args.decimate, lod_px=args.lod_px or None)
    configs = {"full": RenderConfig(lod_px=None), "this": cfg} if args.against_full else {"this": cfg}
    print(f"load average {os.getloadavg()[0]:.2f}; decimate {cfg.decimate}; lod_px {cfg.lod_px}")
    for clip in sorted(root["clips"].group_keys()):
        ing = root[Unit("ingest", clip).path]
        intr = Intrinsics(**ing.attrs["info"]["intrinsics"])
        sides = tuple(ing.attrs["hands"])
        embs = root[f"{clip_path(clip)}/embodiments"]
        for emb in args.embodiment or sorted(embs.group_keys()):
            unit = Unit("retarget", clip, embodiment=emb)
            if unit.path not in root:
                print(f"  {clip:<34} {emb:<20} not in the store")
                continue
            ret = root[unit.path]
            q, pose, hs, st = ret["qpos"][:], ret["root_pose"][:], ret["hand_status"][:], ret["status"][:]
            ready = gate(st)[:, None] & (hs == Reason.OK)
            n = max(len(q), 1)
            out, times = {}, {name: [] for name in configs}
            for name, c in configs.items():
                out[name] = render_stage(emb, q, pose, ready, sides, intr, c)  # builds the renderers
            for _ in range(args.repeats):
                for name, c in configs.items():  # interleaved: both see the same load
                    t = time.perf_counter()
                    render_stage(emb, q, pose, ready, sides, intr, c)
                    times[name].append(1000 * (time.perf_counter() - t) / n)
            boxes = []
            for k, side in enumerate(sides):
                idx = np.flatnonzero(ready[:, k])
                if idx.size:
                    b = render_embodiment(emb, q[idx, k], pose[idx, k], intr, decimate=cfg.decimate, side=side,
                                          lod_px=cfg.lod_px).boxes
                    boxes.append(f"{side} {np.mean(b[:, 2] * b[:, 3]) / (intr.width * intr.height):.2f}")
            ms = statistics.median(times["this"])
            line = f"  {clip:<34} {emb:<20} {ms:7.1f} ms/frame   box share {', '.join(boxes)}"
            if args.against_full:
                full = statistics.median(times["full"])
                line += f"   full {full:.1f} ms/frame ({full / ms:.2f}x); {_agreement(out['full'].rgba, out['this'].rgba)}"
            print(line, flush=True)


def _agreement(full, this) -> str:
    """Silhouette IoU (all frames; the worst frame either render shows) and the mean colour
    difference (levels of 255) where both show the robot."""
    import numpy as np

    a, b = full[..., 3] > 0, this[..., 3] > 0
    both, either = (a & b).sum(axis=(1, 2)), (a | b).sum(axis=(1, 2))
    shown = either > 0
    worst = (both[shown] / either[shown]).min() if shown.any() else 1.0
    m = a & b
    diff = np.abs(full[..., :3].astype(np.int16) - this[..., :3].astype(np.int16))[m].mean() if m.any() else 0.0
    return f"IoU {both.sum() / max(either.sum(), 1):.4f} (worst frame {worst:.4f}), colour diff {diff:.2f}"


if __name__ == "__main__":
    main()
