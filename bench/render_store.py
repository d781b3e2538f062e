"""The render stage on a curated store's own joint tracks: ms per frame, both robots, as curation renders them.

    .venv/bin/python bench/render_store.py --store runs/lid94 [--embodiment kuka_sharpa ...] [--repeats 2] [--decimate 0.25]

``bench/render.py`` frames one robot at 640x480 in a fixed view; on real clips a hand-arm's two
robots are drawn at the working resolution from the head camera, their bases behind it and their
upper arms beside it, which is where the stage's time goes (issue 39's goal: <= 60 ms per frame
for every hand-arm at 960x540). This runs ``render.stage.render_stage`` on every clip's retarget
output (`bench/egodex.py --out DIR` makes such a store) in this process, after one warm-up pass
that builds the renderers, and prints per clip and embodiment: the warm ms per frame (median of
``--repeats``), each side's mean screen box as a share of the frame, and the load average. To
compare two commits, run it from each checkout on the same store, back to back; ``--decimate``
times the simplified meshes (``RenderConfig.decimate``).
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


def main() -> None:
    import numpy as np
    import zarr

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
    args = ap.parse_args()
    path = Path(args.store) / "handedit.zarr"
    if not (path / "zarr.json").exists():
        sys.exit(f"{path} is not a handedit store: run bench/egodex.py --out {args.store} first")
    root = zarr.open_group(str(path), mode="r")
    cfg = RenderConfig(decimate=args.decimate)
    print(f"load average {os.getloadavg()[0]:.2f}; decimate {args.decimate}")
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
            render_stage(emb, q, pose, ready, sides, intr, cfg)  # builds the renderers
            times = []
            for _ in range(args.repeats):
                t = time.perf_counter()
                render_stage(emb, q, pose, ready, sides, intr, cfg)
                times.append(1000 * (time.perf_counter() - t) / n)
            boxes = []
            for k, side in enumerate(sides):
                idx = np.flatnonzero(ready[:, k])
                if idx.size:
                    b = render_embodiment(emb, q[idx, k], pose[idx, k], intr, decimate=args.decimate, side=side).boxes
                    boxes.append(f"{side} {np.mean(b[:, 2] * b[:, 3]) / (intr.width * intr.height):.2f}")
            print(f"  {clip:<34} {emb:<20} {statistics.median(times):7.1f} ms/frame   box share {', '.join(boxes)}")


if __name__ == "__main__":
    main()
