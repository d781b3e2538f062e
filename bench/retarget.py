"""Retargeting speed and accuracy for every available hand, side by side in one run.

    .venv/bin/python bench/retarget.py [--clips 3] [--frames 48] [--trajectory kp.npy ...] [--hand-arm]

Synthetic clips (``handedit.sources.synthetic``, keypoints exact: the known ground truth
of the human hand) are retargeted with the per-process solver built once (build time is
reported separately); per hand: ms per frame (warm-started, one core), fingertip
residual mean / p95 in mm, wrist residual mean, joint-limit violations (must be 0) and
frames rejected by the 50 mm QC threshold. ``--trajectory`` adds any (T,21,3) .npy.
``--hand-arm`` also times the 27-candidate virtual-base search per assembly.
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


def synthetic_keypoints(n_clips: int, n_frames: int) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """(name, keypoints (T,21,3) camera frame, valid, world_from_camera) without rendering pixels."""
    from handedit.sources.synthetic import frame_keypoints, frame_state, make_clip_specs, make_plan

    out = []
    for spec in make_clip_specs(n_clips, n_frames=n_frames):
        plan = make_plan(spec)
        kps, wfc = [], []
        for t in range(n_frames):
            st = frame_state(plan, t, n_frames)
            cw = np.linalg.inv(st.world_from_camera)
            kps.append(frame_keypoints(plan, st) @ cw[:3, :3].T + cw[:3, 3])
            wfc.append(st.world_from_camera)
        out.append((spec.clip_id, np.array(kps), np.ones((n_frames, 21), bool), np.array(wfc)))
    return out


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
    tips, wrists, secs, n, viol, rej = [], [], 0.0, 0, 0, 0
    for _, kp, valid, _ in clips:
        t0 = time.perf_counter()
        r = retarget(kp, valid, emb, cfg)
        secs += time.perf_counter() - t0
        n += len(kp)
        tips.append(r.fingertip_error_mm[np.isfinite(r.fingertip_error_mm)])
        wrists.append(r.wrist_error_mm[np.isfinite(r.wrist_error_mm)])
        viol += int(np.sum((r.qpos < rt.lower) | (r.qpos > rt.upper)))
        rej += int(np.sum(r.status >= 100))
    tip, wr = np.concatenate(tips), np.concatenate(wrists)
    return {"build_s": build, "ms": 1000 * secs / max(n, 1), "tip_mean": tip.mean(), "tip_p95": np.percentile(tip, 95),
            "wrist_mean": wr.mean(), "violations": viol, "rejected": rej, "frames": n}


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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clips", type=int, default=3)
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--trajectory", nargs="*", default=[], help="(T,21,3) .npy files, MANO order, metres")
    ap.add_argument("--hand-arm", action="store_true")
    args = ap.parse_args()
    cfg = RetargetConfig()
    ids = hand_ids()
    clips = synthetic_keypoints(args.clips, args.frames)
    print_table(f"synthetic: {args.clips} clips x {args.frames} frames (exact keypoints), warm-started", {e: bench_hand(e, clips, cfg) for e in ids})
    cold = cfg.model_copy(update={"warm_start": False})
    print_table("same, cold (hybrid vector+position init every frame)", {e: bench_hand(e, clips, cold) for e in ids})
    for f in args.trajectory:
        from handedit.flows.commands.retarget import load_keypoints

        kp, valid = load_keypoints(f)
        print_table(f"trajectory {f}", {e: bench_hand(e, [(f, kp, valid, None)], cfg) for e in ids})
    if args.hand_arm:
        bench_hand_arm(clips)
    return 0


if __name__ == "__main__":
    sys.exit(main())
