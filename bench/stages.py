"""Every stage's cost per frame in one process, its share, the speed goals, and the quality it keeps.

    .venv/bin/python bench/stages.py [--clips 2] [--frames 32] [--size 640x480]
                                     [--embodiment allegro --embodiment xarm_ability] [--egodex 0:32 | --no-egodex]
                                     [--repeats 3]

Runs the demo's synthetic clips (and, when ``../shared/data/egodex`` is there, frames A:B of
its EgoDex episodes at their 960x540 working resolution, with the decoder's cost per frame and
whether any frame was decoded twice) through the real task bodies (``handedit.tasks.clip``:
ingest -> registration -> segment -> restore_background -> retarget -> render -> composite ->
harmonize -> qc, chunk reads and writes included) in this one process, one thread, into a
temporary store. Per stage it prints ms per frame (per source frame up to restoration, per
frame and embodiment from retargeting on) from the chunks' own provenance timings and the
stage's share of the total; then each speed goal of issue 17 as a measured ratio, and the
quality of the same run on the synthetic clips (hand and hand-arm mask IoU against the exact
masks, restored-background PSNR inside the true hand-arm hole). ``--repeats N`` runs it N times,
each in a fresh process, and prints each figure's median with every run's value beside it: on
this shared machine single runs of the same code spread by 10-20 %.
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


GOALS = (("post_render", "composite + harmonize + qc / render", 0.5), ("render_ms", "render ms per frame", 60.0),
         ("segment", "segment / render", 2.0), ("restore", "restore_background / render", 2.0))


def measure(args) -> dict:
    """One run in this process: ms per frame per stage, the goals' ratios, EgoDex decoding, quality."""
    from handedit.sources.synthetic import make_clip_specs

    w, h = (int(v) for v in args.size.split("x"))
    specs = list(make_clip_specs(args.clips, seed=args.seed, n_frames=args.frames, width=w, height=h))
    if args.egodex:
        from handedit.sources import EgoDexTree
        from handedit.sources.egodex import parse_frames

        specs += EgoDexTree(root=EGODEX, frames=parse_frames(args.egodex), resize=(960, 540)).clips()
    out = Path(tempfile.mkdtemp(prefix="handedit-stages-")) / "handedit.zarr"
    try:
        wall = run(specs, args.embodiments, out)
        costs = stage_costs(out)
        qual = quality(specs, out)
    finally:
        shutil.rmtree(out.parent, ignore_errors=True)
    total = sum(c["seconds"] for c in costs.values())
    ms = {k: 1000 * c["seconds"] / c["frames"] for k, c in costs.items() if c["frames"]}
    share = {k: 100 * c["seconds"] / total for k, c in costs.items() if c["frames"]}
    r = ms.get("render", float("nan"))
    ratios = {"post_render": sum(ms.get(k, 0.0) for k in ("composite", "harmonize", "qc")) / r, "render_ms": r,
              "segment": ms.get("segment", float("nan")) / r, "restore": ms.get("restore_background", float("nan")) / r}
    ego = costs.get("ingest (EgoDex)")
    decode = None if not ego else {k: ego[k] for k in ("decoded", "delivered", "decode_seconds")}
    return {"wall": wall, "ms": ms, "share": share, "ratios": ratios, "decode": decode, "quality": qual,
            "load": os.getloadavg()[0]}


def repeated(args, n: int) -> list[dict]:
    """``n`` runs, each in a fresh process (none reuses another's homographies, solvers or
    decoded chunks), one after the other."""
    import json
    import subprocess

    argv = [sys.executable, str(Path(__file__).resolve()), "--clips", str(args.clips), "--frames", str(args.frames),
            "--size", args.size, "--seed", str(args.seed), *sum((["--embodiment", e] for e in args.embodiments), []),
            *(["--egodex", args.egodex] if args.egodex else ["--no-egodex"])]
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(n):
            path = Path(tmp) / f"run{i}.json"
            done = subprocess.run([*argv, "--json", str(path)], capture_output=True, text=True)
            if done.returncode != 0:
                raise SystemExit(f"run {i + 1} of {n} failed:\n{done.stderr[-2000:]}")
            runs.append(json.loads(path.read_text()))
    return runs


def report(args, runs: list[dict]) -> None:
    """The table of one run, or the medians of several (each ratio the median of the runs' own)."""
    def med(vals) -> float:
        return float(np.median(vals))

    n = len(runs)
    stages = [s for s in ("ingest (EgoDex)", *PER_SOURCE, *PER_EMBODIMENT) if all(s in r["ms"] for r in runs)]
    print(f"{args.clips} synthetic clip(s) x {args.frames} frames at {args.size}"
          f"{' + the EgoDex episodes, frames ' + args.egodex + ' at 960x540' if args.egodex else ''}"
          f", embodiments {args.embodiments}; one process, one thread per run; "
          + (f"{runs[0]['wall']:.1f} s wall" if n == 1 else f"median of {n} runs, each in a fresh process"))
    print(f"{'stage':22}{'ms/frame':>10}{'share':>8}   per" + ("" if n == 1 else "                  runs"))
    for stage in stages:
        per = "source frame" if stage in PER_SOURCE or stage.startswith("ingest") else "frame x embodiment"
        vals = [r["ms"][stage] for r in runs]
        tail = "" if n == 1 else f"{'':{20 - len(per)}}" + " ".join(f"{v:.1f}" for v in vals)
        print(f"{stage:22}{med(vals):>10.1f}{med([r['share'][stage] for r in runs]):>7.1f}%   {per}{tail}")
    decode = [r["decode"] for r in runs if r["decode"]]
    if decode:
        d = decode[-1]
        print(f"EgoDex decode: {med([1000 * x['decode_seconds'] / max(x['delivered'], 1) for x in decode]):.1f} ms per frame "
              f"delivered; {d['decoded']} frames decoded for {d['delivered']} delivered (equal: none decoded twice)")
    print("\ngoals (issue 17)                                  measured   goal" + ("" if n == 1 else "      runs"))
    for key, label, goal in GOALS:
        vals = [r["ratios"][key] for r in runs]
        fmt = ".1f" if key == "render_ms" else ".2f"
        tail = "" if n == 1 else "   " + " ".join(f"{v:{fmt}}" for v in vals)
        goal_s = f"{goal:{'.0f' if key == 'render_ms' else '.2f'}}"
        print(f"{label:48}{med(vals):>9{fmt}}   <= {goal_s:<4}{tail}")
    q = runs[-1]["quality"]
    print(f"\nquality of the {'same' if n == 1 else 'last'} run (synthetic GT): hand IoU {q['hand_iou']:.3f}, hand-arm IoU "
          f"{q['handarm_iou']:.3f}, restored hole PSNR {q['hole_psnr']:.2f} dB; load average {runs[-1]['load']:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clips", type=int, default=2)
    ap.add_argument("--frames", type=int, default=32)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--embodiment", action="append", help="default: allegro and xarm_ability")
    ap.add_argument("--egodex", default="0:32", help="frames A:B of the shared EgoDex episodes, when present (default 0:32)")
    ap.add_argument("--no-egodex", action="store_true", help="synthetic clips only")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=1, help="runs, each in a fresh process; the medians are printed")
    ap.add_argument("--json", type=Path, default=None, help=argparse.SUPPRESS)  # one run's figures, for --repeats
    args = ap.parse_args()
    if args.no_egodex or not EGODEX.is_dir():
        args.egodex = None
    args.embodiments = args.embodiment or ["allegro", "xarm_ability"]
    if args.repeats > 1:
        report(args, repeated(args, args.repeats))
        return
    result = measure(args)
    if args.json is not None:
        import json

        args.json.write_text(json.dumps(result))
        return
    report(args, [result])


if __name__ == "__main__":
    main()
