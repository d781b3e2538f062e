"""Every stage's cost per frame in one process, its share, the speed goals, and the quality it keeps.

    .venv/bin/python bench/stages.py [--clips 2] [--frames 32] [--size 640x480]
                                     [--embodiment allegro --embodiment xarm_ability] [--egodex 0:32 | --no-egodex]

Runs the demo's synthetic clips (and, when ``../shared/data/egodex`` is there, frames A:B of
its EgoDex episodes at their 960x540 working resolution, with the decoder's cost per frame and
whether any frame was decoded twice) through the real task bodies (``handedit.tasks.clip``:
ingest -> registration -> segment -> restore_background -> retarget -> render -> composite ->
harmonize -> qc, chunk reads and writes included) in this one process, one thread, into a
temporary store. Per stage it prints ms per frame (per source frame up to restoration, per
frame and embodiment from retargeting on) from the chunks' own provenance timings and the
stage's share of the total; then each speed goal of issue 17 as a measured ratio, and the
quality of the same run on the synthetic clips (hand and hand-arm mask IoU against the exact
masks, restored-background PSNR inside the true hand-arm hole).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("HANDEDIT_ASSET_DIRS", str(ROOT.parent / "shared" / "assets" / "robots"))

import numpy as np  # noqa: E402

PER_SOURCE = ("ingest", "registration", "segment", "restore_background")
PER_EMBODIMENT = ("retarget", "render", "composite", "harmonize", "qc")
EGODEX = ROOT.parent / "shared" / "data" / "egodex"


def run(specs, embodiments: list[str], out: Path) -> float:
    from handedit.flows.config import CurateConfig
    from handedit.flows.curate import code_version, plan_embodiments
    from handedit.storage import Location, create_or_open_store
    from handedit.tasks.clip import ClipJob, EmbodimentJob, run_clip, run_embodiment

    cfg = CurateConfig(out=str(out), clips=list(specs), embodiments=embodiments)
    loc = Location(cfg.out)
    create_or_open_store(loc, cfg.frames_per_chunk, "bench")
    embs = [asdict(e) for e in plan_embodiments(cfg.embodiments)]
    scopes = tuple(sorted({e["scope"] for e in embs}))
    t0 = time.perf_counter()
    for s in specs:
        run_clip(ClipJob(loc.store_url, s.model_dump_json(), cfg.model_dump_json(), scopes, code_version()))
        for e in embs:
            run_embodiment(EmbodimentJob(loc.store_url, s.id, e, cfg.model_dump_json(), code_version()))
    return time.perf_counter() - t0


def stage_costs(out: Path) -> dict[str, dict]:
    """{stage: {seconds, frames}} from the chunks' provenance (frames: source frames for clip
    stages, frame x embodiment for the others; scope-level restoration summed over scopes)."""
    from handedit.storage import open_store
    from handedit.storage.ledger import iter_units
    from handedit.storage.provenance import read_records

    root = open_store(str(out))
    costs: dict[str, dict] = {}
    for unit in iter_units(root):
        recs = read_records(root, unit).values()
        if unit.stage == "ingest" and unit.clip.startswith("egodex-"):  # decoding, apart from synthetic rendering
            d = costs.setdefault("ingest (EgoDex)", {"seconds": 0.0, "frames": 0, "units": set(), "decoded": 0,
                                                     "delivered": 0, "decode_seconds": 0.0})
            d["seconds"] += sum(r.seconds for r in recs)
            d["frames"] += sum(r.stop - r.start for r in recs)
            for r in recs:
                for k in ("decoded", "delivered", "decode_seconds"):
                    d[k] += r.extra.get("decode", {}).get(k, 0)
            continue
        c = costs.setdefault(unit.stage, {"seconds": 0.0, "frames": 0, "units": set()})
        c["seconds"] += sum(r.seconds for r in recs)
        key = (unit.clip, unit.embodiment)
        if key not in c["units"]:  # the two restoration scopes of one clip count its frames once
            c["frames"] += sum(r.stop - r.start for r in recs)
            c["units"].add(key)
    return costs


def quality(specs, out: Path) -> dict[str, float]:
    """Mask IoU and hole PSNR of this run's stored outputs against the synthetic ground truth."""
    from handedit.storage import Unit, open_store, read_chunk
    from handedit.vision import quality as q

    root = open_store(str(out))
    hand, arm, psnr = [], [], []
    for s in specs:
        if hasattr(s, "root"):
            continue
        src = s.open()
        gt = src.read(0, s.n_frames).gt
        seg = read_chunk(root, Unit("segment", s.id), ["hand_mask", "handarm_mask"], 0, s.n_frames)
        bg = read_chunk(root, Unit("restore_background", s.id, scope="hand_arm"), ["background"], 0, s.n_frames) \
            if Unit("restore_background", s.id, scope="hand_arm").path in root else None
        for i in range(s.n_frames):
            hand.append(q.iou(seg["hand_mask"][i].any(0), gt["hand_mask"][i]))
            arm.append(q.iou(seg["handarm_mask"][i].any(0), gt["handarm_mask"][i]))
            if bg is not None:
                psnr.append(q.psnr_in(bg["background"][i], gt["background"][i], gt["handarm_mask"][i]))
    return {"hand_iou": float(np.mean(hand)) if hand else float("nan"),
            "handarm_iou": float(np.mean(arm)) if arm else float("nan"),
            "hole_psnr": float(np.mean(psnr)) if psnr else float("nan")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clips", type=int, default=2)
    ap.add_argument("--frames", type=int, default=32)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--embodiment", action="append", help="default: allegro and xarm_ability")
    ap.add_argument("--egodex", default="0:32", help="frames A:B of the shared EgoDex episodes, when present (default 0:32)")
    ap.add_argument("--no-egodex", action="store_true", help="synthetic clips only")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    from handedit.sources.synthetic import make_clip_specs

    w, h = (int(v) for v in args.size.split("x"))
    specs = list(make_clip_specs(args.clips, seed=args.seed, n_frames=args.frames, width=w, height=h))
    if args.no_egodex or not EGODEX.is_dir():
        args.egodex = None
    if args.egodex:
        from handedit.sources import EgoDexTree
        from handedit.sources.egodex import parse_frames

        specs += EgoDexTree(root=EGODEX, frames=parse_frames(args.egodex), resize=(960, 540)).clips()
    embodiments = args.embodiment or ["allegro", "xarm_ability"]
    out = Path(tempfile.mkdtemp(prefix="handedit-stages-")) / "handedit.zarr"
    try:
        wall = run(specs, embodiments, out)
        costs = stage_costs(out)
        qual = quality(specs, out)
    finally:
        shutil.rmtree(out.parent, ignore_errors=True)
    total = sum(c["seconds"] for c in costs.values())
    print(f"{args.clips} synthetic clip(s) x {args.frames} frames at {args.size}"
          f"{' + the EgoDex episodes, frames ' + args.egodex + ' at 960x540' if args.egodex else ''}"
          f", embodiments {embodiments}; one process, one thread; {wall:.1f} s wall")
    print(f"{'stage':22}{'ms/frame':>10}{'share':>8}   per")
    ms = {}
    for stage in ("ingest (EgoDex)", *PER_SOURCE, *PER_EMBODIMENT):
        c = costs.get(stage)
        if not c or not c["frames"]:
            continue
        ms[stage] = 1000 * c["seconds"] / c["frames"]
        per = "source frame" if stage in PER_SOURCE or stage.startswith("ingest") else "frame x embodiment"
        print(f"{stage:22}{ms[stage]:>10.1f}{100 * c['seconds'] / total:>7.1f}%   {per}")
    ego = costs.get("ingest (EgoDex)")
    if ego:
        print(f"EgoDex decode: {1000 * ego['decode_seconds'] / max(ego['delivered'], 1):.1f} ms per frame delivered; "
              f"{ego['decoded']} frames decoded for {ego['delivered']} delivered (equal: none decoded twice)")
    r = ms.get("render", float("nan"))
    after = sum(ms.get(s, 0.0) for s in ("composite", "harmonize", "qc"))
    print("\ngoals (issue 17)                                  measured   goal")
    print(f"composite + harmonize + qc / render              {after / r:>8.2f}   <= 0.50")
    print(f"render ms per frame                              {r:>8.1f}   <= 60")
    print(f"segment / render                                 {ms.get('segment', float('nan')) / r:>8.2f}   <= 2.00")
    print(f"restore_background / render                     {ms.get('restore_background', float('nan')) / r:>8.2f}   <= 2.00")
    print(f"\nquality of the same run (synthetic GT): hand IoU {qual['hand_iou']:.3f}, hand-arm IoU {qual['handarm_iou']:.3f}, "
          f"restored hole PSNR {qual['hole_psnr']:.2f} dB; load average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
