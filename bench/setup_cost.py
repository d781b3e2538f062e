"""Per-worker setup over the whole roster: two passes of retarget + render in one process.

    .venv/bin/python bench/setup_cost.py --store runs/roster [--embodiment kuka_sharpa ...]

``bench/egodex.py --roster`` projects the cost per pair without each task's setup (the
renderers, IK solvers and retargeters a worker builds once and keeps, ``handedit.setup_meter``),
on the claim that a worker curating a dataset builds them once per embodiment. This checks the
claim on a curated store (`bench/egodex.py --roster --out DIR` makes one): in one process it
retargets and renders every embodiment of the store on every clip, twice, as the tasks call
them, and prints each pass's wall time, its setup (per embodiment in the first), and the
process's resident memory. A second pass that builds nothing means the per-process caches hold
the whole roster; its memory is what a worker needs for that.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _runs import open_run  # noqa: E402


def main() -> None:
    from handedit import setup_meter
    from handedit.camera import Intrinsics
    from handedit.embodiments import get_embodiment
    from handedit.reasons import Reason, gate
    from handedit.render.stage import RenderConfig, render_stage
    from handedit.retarget import RetargetConfig
    from handedit.retarget.sides import retarget_hand_arm_sides, retarget_sides

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--store", required=True, help="an output folder of bench/egodex.py (--roster for the whole roster)")
    ap.add_argument("--embodiment", action="append", help="default: every embodiment in the store")
    args = ap.parse_args()
    root = open_run(args.store, "bench/setup_cost.py", f"bench/egodex.py --roster --out {args.store}")
    clips = sorted(root["clips"].group_keys())
    embs = args.embodiment or sorted(root[f"clips/{clips[0]}/embodiments"].group_keys())
    inputs = {}
    for clip in clips:  # what the retarget task reads, read once
        c = root["clips"][clip]
        plan = dict(c["source"].attrs["plan"])
        src = {k: c["source"][k][:] for k in ("status", "world_from_camera", "arm_valid") if k in c["source"]}
        reg = {k: c["registration"][k][:] for k in ("keypoints", "keypoints_valid", "hand_status", "status", "arm_keypoints")
               if k in c["registration"]}
        ready = gate(src["status"], reg["status"])[:, None] & (reg["hand_status"] == Reason.OK) \
            & (c["segment"]["hand_status"][:] == Reason.OK)
        inputs[clip] = plan, src, reg, ready
    cfg = RetargetConfig()
    for rnd in (1, 2):
        setup_meter.take()
        t0, built = time.perf_counter(), {}
        for emb in embs:
            for clip in clips:
                plan, src, reg, ready = inputs[clip]
                hands, intr = tuple(plan["hands"]), Intrinsics(**plan["intrinsics"])
                if get_embodiment(emb).track == "hand_arm":
                    world = plan.get("world")
                    res = retarget_hand_arm_sides(reg["keypoints"], reg["keypoints_valid"], ready, hands, emb, cfg,
                                                  src["world_from_camera"] if world else None, world,
                                                  reg.get("arm_keypoints"), src.get("arm_valid"), {}, intr=intr)
                else:
                    res = retarget_sides(reg["keypoints"], reg["keypoints_valid"], ready, hands, emb, cfg)
                render_stage(emb, res.qpos, res.root_pose, res.hand_status == Reason.OK, hands, intr, RenderConfig())
            built[emb] = setup_meter.take()
        rss_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
        print(f"pass {rnd}: {time.perf_counter() - t0:.0f} s, setup {sum(built.values()):.1f} s, "
              f"peak resident memory {rss_gb:.1f} GB", flush=True)
        if rnd == 1:
            print("  setup per embodiment, s: " + ", ".join(f"{e} {s:.2f}" for e, s in built.items()))


if __name__ == "__main__":
    main()
