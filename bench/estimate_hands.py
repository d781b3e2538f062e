"""estimate_hands measured: ms/frame, and errors where ground truth exists.

Ground truth: the synthetic clips (exact keypoints of the rendered skin-coloured hand) and,
when present, the shared EgoDex episodes (the Vision Pro's tracked joints, both hands; not
exact, but metric and in the camera frame). Per source it prints:
- detection rate (frames whose true hand is in view and that the stage keeps, per side);
- handedness accuracy (EgoDex: the side the stage assigns vs the annotated side);
- 2-D error (px, mean over joints) of the estimated joints' projection vs the true one's;
- 3-D error after per-frame rigid alignment (rotation + translation, mm, mean over joints);
- wrist depth error (mm and % of the true depth), and the hand-size error behind it;
- ms/frame (detection, landmarks, PnP, smoothing; decoding excluded).

    .venv/bin/python bench/estimate_hands.py [--clips 4] [--frames 48] [--egodex-frames 120] [--no-egodex]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from handedit.camera import project  # noqa: E402
from handedit.keypoints import SIDES  # noqa: E402
from handedit.sources.synthetic import make_clip_specs  # noqa: E402
from handedit.vision.estimate_hands import EstimateHandsConfig, aligned_error_mm, estimate_hands  # noqa: E402

EGODEX = Path(os.environ.get("HANDEDIT_EGODEX_ROOT", ROOT.parent / "shared/data/egodex"))
REAL_VIDEO = Path(os.environ.get("HANDEDIT_REAL_VIDEO", ROOT.parent / "shared/data/real-hand-video/human_hand_video.mp4"))


def hand_size(kp: np.ndarray) -> float:
    return float(np.linalg.norm(kp[9] - kp[0]))


def compare(est, gt_kp: np.ndarray, gt_valid: np.ndarray, gt_sides: tuple[str, ...], intr) -> dict:
    """Per side of the ground truth: the frames where its wrist projects into the image."""
    rows = {"seen": 0, "kept": 0, "px": [], "mm": [], "depth_mm": [], "depth_pct": [], "size_pct": []}
    for g, side in enumerate(gt_sides):
        k = SIDES.index(side)
        for i in range(len(gt_kp)):
            if not gt_valid[i, g].all():
                continue
            uv = project(gt_kp[i, g], intr)
            if not ((uv[:, 0] >= 0) & (uv[:, 0] < intr.width) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.height)).mean() > 0.8:
                continue
            rows["seen"] += 1
            if not est.keypoints_valid[i, k].all():
                continue
            e = est.keypoints_raw[i, k].astype(np.float64)
            px = float(np.linalg.norm(project(e, intr) - uv, axis=1).mean())
            if px > np.linalg.norm(uv[9] - uv[0]):  # the estimate is another hand
                continue
            rows["kept"] += 1
            rows["px"].append(px)
            rows["mm"].append(aligned_error_mm(e, gt_kp[i, g]))
            dz = e[0, 2] - gt_kp[i, g, 0, 2]
            rows["depth_mm"].append(abs(dz) * 1000)
            rows["depth_pct"].append(100 * abs(dz) / gt_kp[i, g, 0, 2])
            rows["size_pct"].append(100 * (hand_size(e) / hand_size(gt_kp[i, g]) - 1))
    return rows


def side_accuracy(est, gt_kp, gt_valid, gt_sides, intr) -> tuple[int, int]:
    """(frames where a found hand lies on a true hand, of those the side is right)."""
    n = ok = 0
    for i in range(len(gt_kp)):
        for k in range(len(SIDES)):
            if not est.keypoints_valid[i, k].all():
                continue
            uv = project(est.keypoints_raw[i, k], intr)
            best, side = None, None
            for g, s in enumerate(gt_sides):
                if gt_valid[i, g].all():
                    d = np.linalg.norm(project(gt_kp[i, g], intr) - uv, axis=1).mean()
                    if best is None or d < best:
                        best, side = d, s
            if best is not None and best < 60:
                n += 1
                ok += side == SIDES[k]
    return n, ok


def summarise(name: str, rows: dict, ms: float, sides: tuple[int, int] | None = None) -> None:
    f = lambda v: f"{np.mean(v):6.1f} (p90 {np.percentile(v, 90):6.1f})" if v else "   n/a"  # noqa: E731
    print(f"{name:28s} kept {rows['kept']:4d}/{rows['seen']:4d} hand-frames | 2-D {f(rows['px'])} px | "
          f"3-D aligned {f(rows['mm'])} mm | wrist depth {f(rows['depth_mm'])} mm = {f(rows['depth_pct'])} % | "
          f"hand size {np.mean(rows['size_pct']) if rows['size_pct'] else float('nan'):+.1f} % | {ms:5.1f} ms/frame"
          + (f" | side right {sides[1]}/{sides[0]}" if sides else ""))


def merge(into: dict, rows: dict) -> None:
    for key, v in rows.items():
        into[key] = into.get(key, 0 if isinstance(v, int) else []) + v


def run_clip(src, n: int, cfg) -> tuple:
    info = src.info()
    chunk = src.read(0, n)
    t0 = time.perf_counter()
    est = estimate_hands(iter(chunk.frames), n, info.intrinsics, info.fps, cfg)
    ms = (time.perf_counter() - t0) / n * 1000
    return info, chunk, est, ms


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clips", type=int, default=4)
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--egodex-frames", type=int, default=120)
    ap.add_argument("--no-egodex", action="store_true")
    ap.add_argument("--real-frames", type=int, default=120, help="frames of the real video (no ground truth: rates only)")
    args = ap.parse_args()
    for depth in ("bones", "pnp"):
        print(f"-- depth: {depth}")
        measure(args, EstimateHandsConfig(depth=depth))


def measure(args, cfg: EstimateHandsConfig) -> None:
    total, times = {}, []
    for spec in make_clip_specs(args.clips, n_frames=args.frames):
        info, chunk, est, ms = run_clip(spec.open(), args.frames, cfg)
        rows = compare(est, chunk.keypoints, chunk.keypoints_valid, info.hands, info.intrinsics)
        summarise(spec.clip_id, rows, ms)
        merge(total, rows)
        times.append(ms)
    summarise("synthetic (all)", total, float(np.mean(times)))
    if not args.no_egodex and EGODEX.is_dir():
        from handedit.sources import EgoDexTree

        etotal, etimes, sides = {}, [], [0, 0]
        for spec in EgoDexTree(root=EGODEX, resize=(960, 540)).clips():
            src = spec.open()
            n = min(args.egodex_frames, src.info().n_frames)
            info, chunk, est, ms = run_clip(src, n, cfg)
            rows = compare(est, chunk.keypoints, chunk.keypoints_valid, info.hands, info.intrinsics)
            s = side_accuracy(est, chunk.keypoints, chunk.keypoints_valid, info.hands, info.intrinsics)
            summarise(spec.id, rows, ms, s)
            merge(etotal, rows)
            etimes.append(ms)
            sides = [sides[0] + s[0], sides[1] + s[1]]
        summarise("egodex (all)", etotal, float(np.mean(etimes)), tuple(sides))
    if REAL_VIDEO.is_file() and args.real_frames:
        from handedit.reasons import Reason
        from handedit.sources import VideoSpec

        src = VideoSpec(path=REAL_VIDEO, max_frames=args.real_frames, resize=(640, 360)).open()
        info, chunk, est, ms = run_clip(src, src.info().n_frames, cfg)
        found = (est.hand_status == Reason.OK).any(1).mean()
        right = (est.hand_status[:, 1] == Reason.OK).mean()
        print(f"{'real video (640x360)':28s} a hand kept in {100 * found:.0f} % of {len(chunk.frames)} frames, called right in "
              f"{100 * right:.0f} % | wrist depth median {np.median(est.keypoints[:, 1, 0, 2][est.keypoints_valid[:, 1, 0]]):.2f} m "
              f"(70 deg hfov guess) | {ms:5.1f} ms/frame")


if __name__ == "__main__":
    main()
