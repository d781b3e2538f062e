"""The README's real-video figure, from a curate run on a video without keypoints.

Rows are frames; columns: source | estimated keypoints (estimate_hands, skeleton drawn per
side: left blue, right red) | restored background | robot pseudo-GT (harmonize).

    .venv/bin/handedit curate --video ../shared/data/real-hand-video/human_hand_video.mp4 --embodiment allegro --out runs/real
    .venv/bin/python bench/real_video_figure.py --run runs/real [--embodiment allegro] [--frames 3] [--out docs/real_video_pseudo_gt.jpg]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from handedit.camera import Intrinsics, project  # noqa: E402
from handedit.keypoints import PARENT  # noqa: E402
from handedit.reasons import Reason  # noqa: E402
from handedit.storage import Unit, open_store  # noqa: E402

COLOURS = {0: (60, 120, 255), 1: (255, 60, 60)}  # RGB per side index (left, right)


def draw_skeleton(rgb: np.ndarray, uv: np.ndarray, colour) -> np.ndarray:
    out = rgb.copy()
    r = max(2, rgb.shape[1] // 320)
    for j, p in enumerate(PARENT):
        if p >= 0:
            cv2.line(out, tuple(np.round(uv[p]).astype(int)), tuple(np.round(uv[j]).astype(int)), colour, r, cv2.LINE_AA)
    for x, y in uv:
        cv2.circle(out, (int(round(x)), int(round(y))), r + 1, (255, 255, 255), -1, cv2.LINE_AA)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", default="runs/real")
    ap.add_argument("--clip", help="default: the run's only (first) clip")
    ap.add_argument("--embodiment", default="allegro")
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--width", type=int, default=480, help="width of each panel")
    ap.add_argument("--out", default=str(ROOT / "docs" / "real_video_pseudo_gt.jpg"))
    args = ap.parse_args()
    root = open_store(args.run)
    clip = args.clip or sorted(root["clips"].group_keys())[0]
    ingest, est = root[Unit("ingest", clip).path], root[Unit("estimate_hands", clip).path]
    restore = root[Unit("restore_background", clip, scope="hand").path]
    harm = root[Unit("harmonize", clip, embodiment=args.embodiment).path]
    kept = np.flatnonzero(root[Unit("qc", clip, embodiment=args.embodiment).path]["status"][:] == Reason.OK)
    if not len(kept):
        raise SystemExit(f"{args.run}: no frame of {clip} was kept for {args.embodiment}; nothing to show")
    picks = kept[np.linspace(0, len(kept) - 1, args.frames).round().astype(int)]
    intr = Intrinsics(**{k: v for k, v in ingest.attrs["info"]["intrinsics"].items()})
    rows = []
    for i in picks:
        src = ingest["frames"][i]
        skel = src
        for k in range(est["keypoints"].shape[1]):
            if est["hand_status"][i, k] == Reason.OK:
                skel = draw_skeleton(skel, project(est["keypoints"][i, k], intr), COLOURS[k])
        panels = [src, skel, restore["background"][i], harm["image"][i]]
        h = int(round(src.shape[0] * args.width / src.shape[1]))
        rows.append(np.concatenate([cv2.resize(p, (args.width, h), interpolation=cv2.INTER_AREA) for p in panels], 1))
    sheet = np.concatenate(rows, 0)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(args.out, cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    print(f"{args.out}: frames {list(map(int, picks))} of {clip} ({len(kept)} kept for {args.embodiment})")


if __name__ == "__main__":
    main()
