"""Retargeting speed and accuracy for every available hand, side by side in one run.

    .venv/bin/python bench/retarget.py [--clips 3] [--frames 48] [--trajectory kp.npy ...] [--hand-arm]
    .venv/bin/python bench/retarget.py --against-dex-retargeting /tmp/dexenv/bin/python [--trajectory kp.npy] [--repeats 3]
        [--real [../shared]]        # real hands too: the shared EgoDex episodes' and real video's, reported apart

Synthetic clips (``handedit.sources.synthetic``, keypoints exact: the known ground truth
of the human hand) are retargeted with the per-process solver built once (build time is
reported separately); per hand: ms per frame (warm-started, one core), fingertip
residual mean / p95 in mm, wrist residual mean, joint-limit violations (must be 0) and
frames rejected by the 50 mm QC threshold. ``--trajectory`` adds any (T,21,3) .npy.
``--hand-arm`` also times the 27-candidate virtual-base search per assembly.
``--against-dex-retargeting PYTHON`` runs only the side-by-side with dex-retargeting's
position mode (its own venv: ``bench/_dex_retargeting_side.py``) on the same keypoints.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("HANDEDIT_ASSET_DIRS", "/work/shared/assets/robots")

from handedit.embodiments import EmbodimentError, list_embodiments  # noqa: E402
from handedit.retarget import RetargetConfig, get_retargeter, retarget  # noqa: E402
from handedit.retarget.quality import residual_stats, synthetic_keypoints  # noqa: E402


BUILD_S: dict[str, float] = {}


def hand_ids() -> list[str]:
    """Hands whose assets resolve; builds (and times) each solver once."""
    ids = []
    for e in list_embodiments():
        if e.track != "hand":
            continue
        try:
            t0 = time.perf_counter()
            get_retargeter(e.id, RetargetConfig())
            BUILD_S[e.id] = time.perf_counter() - t0
            ids.append(e.id)
        except EmbodimentError as exc:
            print(f"  skip {e.id}: {str(exc)[:100]}")
    return ids


def bench_hand(emb: str, clips, cfg: RetargetConfig) -> dict:
    t0 = time.perf_counter()
    rt = get_retargeter(emb, cfg)
    build = BUILD_S.get(emb, 0.0) if cfg == RetargetConfig() else time.perf_counter() - t0
    results, secs = [], 0.0
    for _, kp, valid, _ in clips:
        t0 = time.perf_counter()
        results.append(retarget(kp, valid, emb, cfg))
        secs += time.perf_counter() - t0
    stats = residual_stats(results, rt.lower, rt.upper)
    return {"build_s": build, "ms": 1000 * secs / max(stats["frames"], 1), **stats}


def real_trajectories(shared: Path, n_frames: int = 96) -> list[tuple[str, np.ndarray, np.ndarray, None]]:
    """Real hands as first-class inputs: both hands of the shared EgoDex episodes (their own
    tracked joints) and the shared real video's hand (``estimate_hands``, the pipeline's
    hand pose from any video), each the frames where all 21 joints are valid, camera frame,
    left hands mirrored into right ones (as the pipeline solves them)."""
    from handedit.embodiments.mirror import mirror_keypoints
    from handedit.keypoints import SIDES
    from handedit.reasons import Reason
    from handedit.sources.egodex import EgoDexSource, EgoDexSpec
    from handedit.sources.video import VideoSource, VideoSpec
    from handedit.vision.estimate_hands import estimate_hands

    out = []
    root = shared / "data" / "egodex"
    for h5 in sorted(root.glob("*/*.hdf5")) if root.is_dir() else []:
        src = EgoDexSource(EgoDexSpec(root=root, task=h5.parent.name, episode=h5.stem))
        n = min(n_frames, src.info().n_frames)
        c = src.read(0, n)
        for k, side in enumerate(SIDES):
            ok = c.keypoints_valid[:, k].all(1)
            kp = c.keypoints[ok, k]
            kp = mirror_keypoints(kp) if side == "left" else kp
            if len(kp) >= 8:
                out.append((f"egodex {h5.parent.name}/{h5.stem} {side}", kp, np.ones(kp.shape[:2], bool), None))
    video = shared / "data" / "real-hand-video" / "human_hand_video.mp4"
    if video.is_file():  # the project's own reader: its probe, frame count and intrinsics
        vsrc = VideoSource(VideoSpec(path=video, max_frames=n_frames))
        vinfo = vsrc.info()
        c = vsrc.read(0, vinfo.n_frames)
        est = estimate_hands(iter(c.frames), len(c.frames), vinfo.intrinsics, vinfo.fps)
        for k, side in enumerate(SIDES):
            ok = (est.hand_status[:, k] == Reason.OK) & est.keypoints_valid[:, k].all(1)
            if ok.sum() >= 8:
                kp = est.keypoints[ok, k]
                kp = mirror_keypoints(kp) if side == "left" else kp
                out.append((f"real video {side} (estimate_hands)", kp, np.ones(kp.shape[:2], bool), None))
    return out


def print_table(title: str, rows: dict[str, dict]) -> None:
    print(f"\n{title}")
    print(f"{'hand':<12}{'build s':>8}{'ms/frame':>10}{'tip mean':>10}{'tip p95':>9}{'wrist':>8}{'lim viol':>9}{'QC rej':>8}{'frames':>8}")
    for k, r in rows.items():
        print(f"{k:<12}{r['build_s']:>8.2f}{r['ms']:>10.2f}{r['tip_mean']:>10.2f}{r['tip_p95']:>9.2f}{r['wrist_mean']:>8.2f}"
              f"{r['violations']:>9d}{r['rejected']:>8d}{r['frames']:>8d}")


def bench_hand_arm(clips) -> None:
    from handedit.retarget.arm import arm_model
    from handedit.retarget.virtual_base import VirtualBaseConfig, search_virtual_base, support_plane_from_world

    print(f"\nvirtual base (27 candidates, per clip of {len(clips[0][1])} frames)")
    print(f"{'embodiment':<16}{'L_r m':>7}{'search s':>9}{'valid':>6}{'chosen':>7}{'ee mm':>7}")
    for emb in [e.id for e in list_embodiments() if e.track == "hand_arm"]:
        try:
            arm = arm_model(emb)
        except EmbodimentError as exc:
            print(f"  skip {emb}: {str(exc)[:60]}")
            continue
        for name, kp, valid, wfc in clips[:1]:
            r = retarget(kp, valid, arm.hand_id, RetargetConfig())
            targets = arm.wrist_targets(r.root_pose, r.qpos.astype(float))
            up, plane = support_plane_from_world(wfc[0])
            t0 = time.perf_counter()
            res = search_virtual_base(targets, r.status == 1, emb, VirtualBaseConfig(), up=up, support_plane=plane)
            dt = time.perf_counter() - t0
            ee = res.candidates[res.chosen].ee_error_mm if res.chosen is not None else float("nan")
            print(f"{emb:<16}{arm.reach:>7.3f}{dt:>9.2f}{len(res.ranking):>6d}{str(res.chosen):>7}{ee:>7.2f}")


def against_dex_retargeting(clips, dex_python: str, robots_dir: Path, repeats: int = 3, label: str = "") -> None:
    """The side-by-side of issue 17: the same keypoints and start through this solver and
    dex-retargeting's position mode (Allegro, its offline config), one process each, one core.
    The two sides alternate ``repeats`` times and each side's median is compared: a 2-core
    machine's load drifts by +-30 % between consecutive runs of either side alone."""
    import json
    import subprocess
    import tempfile

    from handedit.embodiments.roster import get_embodiment, resolve_asset
    from handedit.retarget.palm import keypoint_palm_frame

    wrist_from_root = resolve_asset(get_embodiment("allegro")).asset.wrist_from_root_matrix
    root0 = np.stack([keypoint_palm_frame(kp[0]) @ wrist_from_root for _, kp, _, _ in clips])
    cfg = RetargetConfig()
    get_retargeter("allegro", cfg)  # build excluded, as on the other side
    n = sum(len(kp) for _, kp, _, _ in clips)
    ours_ms, dex_ms = [], []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "kp.npz"
        np.savez(path, root0=root0, **{f"keypoints_{i}": kp for i, (_, kp, _, _) in enumerate(clips)})
        env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        for _ in range(repeats):
            ours_s, ours_tip = 0.0, []
            for _, kp, valid, _ in clips:
                t0 = time.perf_counter()
                r = retarget(kp, valid, "allegro", cfg)
                ours_s += time.perf_counter() - t0
                ours_tip.append(r.fingertip_error_mm)  # per frame: the mean over the tips
            ours_ms.append(1000 * ours_s / n)
            out = subprocess.run([dex_python, str(Path(__file__).with_name("_dex_retargeting_side.py")), str(path), str(robots_dir)],
                                 capture_output=True, text=True, env=env, check=False)
            if out.returncode != 0:
                raise SystemExit(f"dex-retargeting side failed ({dex_python}):\n{out.stderr[-2000:]}")
            dex = json.loads(out.stdout.strip().splitlines()[-1])
            dex_ms.append(dex["ms_per_frame"])
    ours_mm, dex_mm = float(np.mean(np.concatenate(ours_tip))), float(np.mean(dex["tip_mm"]))
    ours, theirs = float(np.median(ours_ms)), float(np.median(dex_ms))
    print(f"\n{label}: against dex-retargeting 0.5.0 (position mode, Allegro, {n} frames, same keypoints and first-frame root; "
          f"median of {repeats} alternating runs)")
    print(f"handedit's Newton evaluates its casadi functions {get_retargeter('allegro', cfg).newton.evaluation.split(' /')[0]}")
    print(f"{'':24}{'ms/frame':>10}{'tip mm':>9}   runs (ms/frame)")
    print(f"{'handedit':24}{ours:>10.2f}{ours_mm:>9.2f}   {' '.join(f'{v:.2f}' for v in ours_ms)}")
    print(f"{'dex-retargeting':24}{theirs:>10.2f}{dex_mm:>9.2f}   {' '.join(f'{v:.2f}' for v in dex_ms)}")
    print(f"ratio time {ours / theirs:.2f} (goal <= 0.50), residual {ours_mm / dex_mm:.2f} (goal <= 0.80)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clips", type=int, default=3)
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--trajectory", nargs="*", default=[], help="(T,21,3) .npy files, MANO order, metres")
    ap.add_argument("--hand-arm", action="store_true")
    ap.add_argument("--real", nargs="?", const="../shared", metavar="SHARED",
                    help="also real hands: both hands of the shared EgoDex episodes and the shared real video's "
                         "hand (estimate_hands), up to --real-frames each, reported apart from the synthetic clips")
    ap.add_argument("--real-frames", type=int, default=96)
    ap.add_argument("--repeats", type=int, default=3, help="alternating runs of each side in the side-by-side (median)")
    ap.add_argument("--against-dex-retargeting", metavar="PYTHON", nargs="?", const=os.environ.get("DEX_RETARGETING_PYTHON", ""),
                    help="only the side-by-side with dex-retargeting, run by this interpreter (a venv with "
                         "`pip install dex-retargeting==0.5.0` and torch CPU; default $DEX_RETARGETING_PYTHON)")
    args = ap.parse_args()
    from handedit.flows.commands.retarget import load_keypoints

    trajectories = [(f, *load_keypoints(f), None) for f in args.trajectory]
    real = real_trajectories(Path(args.real).resolve(), args.real_frames) if args.real else []
    if args.real and not real:
        raise SystemExit(f"--real: no EgoDex episode or real video under {args.real} (the folder beside the project: "
                         "data/egodex/<task>/<k>.hdf5, data/real-hand-video/human_hand_video.mp4)")
    if args.against_dex_retargeting is not None:
        if not args.against_dex_retargeting:
            raise SystemExit("--against-dex-retargeting needs the python of a venv with dex-retargeting 0.5.0: "
                             "python3 -m venv /tmp/dexenv && /tmp/dexenv/bin/pip install torch --index-url "
                             "https://download.pytorch.org/whl/cpu && /tmp/dexenv/bin/pip install dex-retargeting==0.5.0 six")
        robots = Path(os.environ["HANDEDIT_ASSET_DIRS"].split(os.pathsep)[0])
        synthetic = synthetic_keypoints(args.clips, args.frames)
        against_dex_retargeting(synthetic + trajectories, args.against_dex_retargeting, robots, args.repeats,
                                f"synthetic ({args.clips} clips x {args.frames} frames)"
                                + (f" + {len(trajectories)} trajectory file(s)" if trajectories else ""))
        if real:
            for name, kp, _, _ in real:
                print(f"  real: {name}, {len(kp)} frames")
            against_dex_retargeting(real, args.against_dex_retargeting, robots, args.repeats, "real hands")
            for origin in ("egodex", "real video"):  # each kind of real hand apart: one must not hide the other
                part = [t for t in real if t[0].startswith(origin)]
                if part and len(part) < len(real):
                    against_dex_retargeting(part, args.against_dex_retargeting, robots, args.repeats, f"real hands: {origin}")
        return 0
    cfg = RetargetConfig()
    ids = hand_ids()
    clips = synthetic_keypoints(args.clips, args.frames)
    print_table(f"synthetic: {args.clips} clips x {args.frames} frames (exact keypoints), warm-started", {e: bench_hand(e, clips, cfg) for e in ids})
    cold = cfg.model_copy(update={"warm_start": False})
    print_table("same, cold (hybrid vector+position init every frame)", {e: bench_hand(e, clips, cold) for e in ids})
    for name, kp, valid, _ in trajectories:
        print_table(f"trajectory {name}", {e: bench_hand(e, [(name, kp, valid, None)], cfg) for e in ids})
    if real:
        print_table("real hands: " + ", ".join(f"{name} ({len(kp)})" for name, kp, _, _ in real),
                    {e: bench_hand(e, real, cfg) for e in ids})
    if args.hand_arm:
        bench_hand_arm(clips)
    return 0


if __name__ == "__main__":
    sys.exit(main())
