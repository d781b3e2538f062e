"""Contacts kept by hand retargeting: the QC's contact and penetration rejections on the synthetic
grasp clips, with the solve's contact terms off and on, side by side in one run.

    .venv/bin/python bench/contacts.py [--clips 8] [--frames 48] [--embodiment allegro ...]

Per hand (default: every available hand), over the same clips and keypoints: frames where the
human touches the object, ``CONTACT_LOSS``, ``PENETRATION``, ``CONTACT_DISTANCE`` and the other
QC rejections, the fingertip residual and ms per frame (solve and QC). The QC's thresholds are the
paper's and stay unchanged (``RetargetQCConfig``: 10 mm touch, 20 mm contact distance, 10 mm
severe penetration); only ``RetargetConfig.contact`` differs between the two sides. The demo
(``curate --demo``) is 2 of these clips with Allegro.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("HANDEDIT_ASSET_DIRS", str(Path(__file__).resolve().parents[2] / "shared" / "assets" / "robots"))

from handedit.embodiments import EmbodimentError, list_embodiments  # noqa: E402
from handedit.reasons import Reason  # noqa: E402
from handedit.retarget import RetargetConfig, RetargetQCConfig, get_retargeter, retarget, retarget_qc  # noqa: E402
from handedit.retarget.quality import synthetic_grasps  # noqa: E402


def run(emb: str, clips, cfg: RetargetConfig) -> dict:
    qcfg = RetargetQCConfig.from_retarget(cfg)
    get_retargeter(emb, cfg)  # built outside the timing
    counts, tips, secs, frames, touch = Counter(), [], 0.0, 0, 0
    for _, kp, valid, mesh, pose in clips:
        t0 = time.perf_counter()
        res = retarget(kp, valid, emb, cfg, object_mesh=mesh, object_pose=pose)
        qc = retarget_qc(res, kp, valid, emb, qcfg, cfg, object_mesh=mesh, object_pose=pose)
        secs += time.perf_counter() - t0
        frames += len(kp)
        touch += int(qc.human_contact.sum())
        counts.update(Reason(int(s)).name for s in qc.status if s != Reason.OK)
        tips.append(res.fingertip_error_mm[np.isfinite(res.fingertip_error_mm)])
    return {"counts": counts, "tip": float(np.concatenate(tips).mean()), "ms": 1000 * secs / max(frames, 1),
            "frames": frames, "touch": touch}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clips", type=int, default=8)
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--embodiment", action="append")
    args = ap.parse_args()
    ids = args.embodiment or [e.id for e in list_embodiments() if e.track == "hand"]
    clips = synthetic_grasps(args.clips, args.frames)
    off, on = RetargetConfig(contact=False), RetargetConfig()
    print(f"{args.clips} synthetic grasp clips x {args.frames} frames; contact terms off | on")
    print(f"{'hand':<18}{'touch':>6}  {'CONTACT_LOSS':>13}{'PENETRATION':>13}{'CONTACT_DIST':>13}{'other':>9}"
          f"{'tip mm':>14}{'ms/frame':>14}")
    total = {False: Counter(), True: Counter()}
    for emb in ids:
        try:
            a, b = run(emb, clips, off), run(emb, clips, on)
        except EmbodimentError as exc:
            print(f"  skip {emb}: {str(exc)[:100]}")
            continue
        row = []
        for key in ("CONTACT_LOSS", "PENETRATION", "CONTACT_DISTANCE"):
            row.append(f"{a['counts'][key]:>6} |{b['counts'][key]:>4}")
        other = [sum(v for k, v in r["counts"].items() if not k.startswith(("CONTACT", "PENETRATION"))) for r in (a, b)]
        print(f"{emb:<18}{a['touch']:>6}  " + "".join(f"{c:>13}" for c in row) + f"{other[0]:>5} |{other[1]:>2}"
              f"{a['tip']:>8.1f} |{b['tip']:>5.1f}{a['ms']:>8.1f} |{b['ms']:>5.1f}")
        total[False].update(a["counts"])
        total[True].update(b["counts"])
    lost = [total[k]["CONTACT_LOSS"] + total[k]["PENETRATION"] for k in (False, True)]
    print(f"CONTACT_LOSS + PENETRATION over the hands: {lost[0]} -> {lost[1]} "
          f"({lost[1] / max(lost[0], 1):.2f}x)")


if __name__ == "__main__":
    main()
