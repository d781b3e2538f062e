"""Measured quality of the vision stages on synthetic clips with exact ground truth.

Prints, per clip and overall: hand and hand-arm mask IoU (classical segmenter, keypoint
seeded; on sleeved clips against the arm with its sleeve, with and without the tracked
elbow), the occluder found from the image with the object mesh withheld (its pixels on the
object; the object's pixels in front of the fingers it finds), restored-background PSNR / SSIM *inside the hole* (the true hand-arm region;
with the predicted masks, and with the true masks to isolate restoration), the
composite-boundary error (a robot silhouette composited over the restored vs the true
background, mean |RGB diff| in a 3 px band), and harmonization's Lab gap between the
robot and its surroundings before/after. Then segments + restores frames of the real
video and writes the contact sheet ``runs/stage_quality/real_video_contact_sheet.png``
(source | hand-arm (blue) / hand (red) overlay | restored background).

    .venv/bin/python bench/stage_quality.py [--clips 2] [--frames 16] [--size 192x144] [--still 1] [--sleeves 2] [--no-real]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from handedit.camera import project  # noqa: E402
from handedit.sources.synthetic import make_clip_specs  # noqa: E402
from handedit.vision import quality as q  # noqa: E402
from handedit.vision.arm import limbs  # noqa: E402
from handedit.vision.occluder import finger_footprint, hidden_fingers  # noqa: E402
from handedit.vision.composite import composite  # noqa: E402
from handedit.vision.harmonize import harmonize  # noqa: E402
from handedit.vision.restore_background import restore_background, visible_residue  # noqa: E402
from handedit.vision.segment import segment  # noqa: E402

REAL_VIDEO = Path(os.environ.get("HANDEDIT_REAL_VIDEO", ROOT.parent / "shared/data/real-hand-video/human_hand_video.mp4"))


def robot_layer(mask: np.ndarray, rgb=(150, 160, 175)) -> tuple[np.ndarray, np.ndarray]:
    """A flat metallic-grey stand-in for a rendered robot on ``mask`` (rgba, depth)."""
    rgba = np.zeros((*mask.shape, 4), np.uint8)
    rgba[mask, :3] = rgb
    rgba[mask, 3] = 255
    return rgba, np.where(mask, 0.5, 0.0).astype(np.float32)


def measure_clip(spec, track_arm: bool = True) -> dict:
    src = spec.open()
    info, c = src.info(), src.read(0, spec.n_frames)
    # a sleeved clip tracks its elbow, as EgoDex does (track_arm=False: as a video would not)
    arm = limbs(c.keypoints, *c.arms()) if info.has_arm and track_arm else None
    seg = segment(c.frames, project(c.keypoints, info.intrinsics), c.keypoints_valid, limbs=arm, intr=info.intrinsics)
    seg_hand, seg_arm = seg.union  # one hand: the union is that hand
    gh, ga, gbg = c.gt["hand_mask"], c.gt["handarm_mask"], c.gt["background"]
    n = len(c.frames)
    out = {
        "hand_iou": [q.iou(a, b) for a, b in zip(seg_hand, gh)],
        "handarm_iou": [q.iou(a, b) for a, b in zip(seg_arm, ga)],
        "seg_ok": float((seg.status == 1).mean()),
    }
    targets = np.arange(n)
    for tag, masks in (("pred", seg_arm), ("gt", ga)):
        res = restore_background(c.frames, masks, targets)
        out[f"psnr_{tag}"] = [q.psnr_in(res.background[i], gbg[i], ga[i]) for i in range(n)]
        out[f"ssim_{tag}"] = [q.ssim_in(res.background[i], gbg[i], ga[i]) for i in range(n)]
        if tag == "pred":
            restored = res.background
            out["restore_ok"] = float((res.status == 1).mean())
            # residue judged on the whole restored hole (before compositing) and on what a robot
            # the size of the true hand leaves visible (composite's check)
            none = np.zeros_like(res.hole)
            out["residue_whole"] = float(visible_residue(restored, res.hole, none, 0.25).mean())
            out["residue_visible"] = float(visible_residue(restored, res.hole, gh, 0.25).mean())
    # composite-boundary error and harmonization, with the true hand as the robot's silhouette
    rgba, depth = zip(*(robot_layer(m) for m in gh))
    rgba, depth = np.stack(rgba), np.stack(depth)
    on_restored = composite(restored, rgba, depth).image
    on_true = composite(gbg, rgba, depth)
    out["boundary_err"] = [q.boundary_error(a, b, m) for a, b, m in zip(on_restored, on_true.image, gh)]
    harm = harmonize(on_true.image, on_true.union)
    before = [q.lab_gap(im, m) for im, m in zip(on_true.image, on_true.union)]
    after = [q.lab_gap(im, m) for im, m in zip(harm.image, on_true.union)]
    out["lab_before"], out["lab_after"] = before, after
    # the occluder a source without an object mesh gets (composite.image_occluder), the mesh withheld:
    # from the keypoints and the predicted hand masks, against the object's true mask
    occ = hidden_fingers(c.keypoints, c.keypoints_valid, seg.hand_mask, info.intrinsics, frames=c.frames)
    truth = c.object_mask & finger_footprint(c.keypoints, c.keypoints_valid, info.intrinsics, gh.shape[1:]) & ~gh
    out["occluder_px"] = [int(occ.sum())]
    out["occluder_on_object"] = [int((occ & c.object_mask).sum())]
    out["occluder_found"], out["occluder_truth"] = [int((occ & truth).sum())], [int(truth.sum())]
    return out


def contact_sheet(path: Path, out: Path, times=(0.1, 0.35, 0.6, 0.85), width=640, window=6) -> None:
    from handedit.sources.video import VideoSpec

    src = VideoSpec(path=path).open()
    n = src.info().n_frames
    rows = []
    for u in times:
        t = int(u * (n - 1))
        lo, hi = max(0, t - window), min(n, t + window + 1)
        raw = src.read(lo, hi).frames
        h = int(round(raw.shape[1] * width / raw.shape[2]))
        frames = np.stack([cv2.resize(f, (width, h), interpolation=cv2.INTER_AREA) for f in raw])
        seg = segment(frames, None, None)
        hand, arm = seg.union
        k = t - lo
        res = restore_background(frames, arm, np.array([k]))
        f = frames[k]
        ov = f.astype(np.float32)
        a, hm = arm[k], hand[k]
        ov[a] = 0.5 * ov[a] + 0.5 * np.array([40, 80, 255])
        ov[hm] = 0.5 * f[hm] + 0.5 * np.array([255, 40, 40])
        row = np.hstack([f, ov.astype(np.uint8), res.background[0]])
        cv2.putText(row, f"frame {t}  conf {' '.join(f'{c:.2f}' for c in seg.confidence[k])}  {res.method.split(':')[1]}", (8, 22),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
        rows.append(row)
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet = np.vstack(rows)
    cv2.imwrite(str(out), cv2.cvtColor(cv2.resize(sheet, None, fx=0.6, fy=0.6, interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2BGR))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", type=int, default=2)
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--size", default="192x144")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--no-real", action="store_true")
    ap.add_argument("--still", type=int, default=1, help="and this many clips whose hand holds still (restoration "
                    "never sees behind it): their residue, before and after compositing, and hole PSNR")
    ap.add_argument("--sleeves", type=int, default=2, help="and this many clips whose forearm wears a sleeve (cloth, some "
                    "close to skin; the elbow tracked): hand IoU, and hand-arm IoU against the arm-with-sleeve truth")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    t0 = time.perf_counter()
    allm: dict[str, list] = {}
    sleeved: dict[str, list] = {}
    for spec in make_clip_specs(args.sleeves, seed=args.seed + 2, n_frames=args.frames, width=w, height=h, sleeve=True):
        m, untracked = measure_clip(spec), measure_clip(spec, track_arm=False)
        for k in ("hand_iou", "handarm_iou", "psnr_pred"):
            sleeved.setdefault(k, []).extend(m[k])
        sleeved.setdefault("untracked", []).extend(untracked["handarm_iou"])
        print(f"{spec.clip_id} (sleeve): hand IoU {np.mean(m['hand_iou']):.3f}, hand-arm IoU against the arm with its sleeve "
              f"{np.mean(m['handarm_iou']):.3f} (min {np.min(m['handarm_iou']):.3f}; without the tracked elbow "
              f"{np.mean(untracked['handarm_iou']):.3f}), hole PSNR {np.mean(m['psnr_pred']):.2f} dB")
    if sleeved:
        print(f"SLEEVES ({args.sleeves} clips): hand IoU {np.mean(sleeved['hand_iou']):.3f}, hand-arm IoU "
              f"{np.mean(sleeved['handarm_iou']):.3f} (without the tracked elbow, as from a video: "
              f"{np.mean(sleeved['untracked']):.3f}), hole PSNR {np.mean(sleeved['psnr_pred']):.2f} dB")
    for spec in make_clip_specs(args.still, seed=args.seed + 1, n_frames=args.frames, width=w, height=h, still=True):
        m = measure_clip(spec)
        print(f"{spec.clip_id} (still hand): hole PSNR {np.mean(m['psnr_pred']):.2f} dB (true masks {np.mean(m['psnr_gt']):.2f}), "
              f"frames with RESIDUE judged on the whole hole {m['residue_whole']:.2f}, on what a hand-sized robot leaves "
              f"visible {m['residue_visible']:.2f}, restore OK {m['restore_ok']:.2f}")
    for spec in make_clip_specs(args.clips, seed=args.seed, n_frames=args.frames, width=w, height=h):
        m = measure_clip(spec)
        print(f"{spec.clip_id}: hand IoU {np.mean(m['hand_iou']):.3f} (min {np.min(m['hand_iou']):.3f})  "
              f"hand-arm IoU {np.mean(m['handarm_iou']):.3f} (min {np.min(m['handarm_iou']):.3f})  "
              f"PSNR {np.mean(m['psnr_pred']):.2f} dB / SSIM {np.mean(m['ssim_pred']):.3f} (pred masks), "
              f"{np.mean(m['psnr_gt']):.2f} / {np.mean(m['ssim_gt']):.3f} (true masks)  "
              f"boundary {np.mean(m['boundary_err']):.2f}  Lab gap {np.mean(m['lab_before']):.2f} -> {np.mean(m['lab_after']):.2f}  "
              f"seg OK {m['seg_ok']:.2f} restore OK {m['restore_ok']:.2f}")
        for k, v in m.items():
            allm.setdefault(k, []).extend(v if isinstance(v, list) else [v])
    mean = {k: float(np.mean(v)) for k, v in allm.items()}
    if mean:
        print(f"ALL ({args.clips} clips x {args.frames} frames, {w}x{h}): hand IoU {mean['hand_iou']:.3f}, "
              f"hand-arm IoU {mean['handarm_iou']:.3f}, hole PSNR {mean['psnr_pred']:.2f} dB SSIM {mean['ssim_pred']:.3f} "
              f"(true masks {mean['psnr_gt']:.2f} / {mean['ssim_gt']:.3f}), boundary error {mean['boundary_err']:.2f} grey levels, "
              f"harmonize Lab gap {mean['lab_before']:.2f} -> {mean['lab_after']:.2f} "
              f"({100 * (1 - mean['lab_after'] / max(mean['lab_before'], 1e-9)):.0f}% closer)  [{time.perf_counter() - t0:.1f} s]")
        print(f"occluder from the image (object mesh withheld, predicted masks): {sum(allm['occluder_on_object'])} of its "
              f"{sum(allm['occluder_px'])} px on the object, {sum(allm['occluder_found'])} of the "
              f"{sum(allm['occluder_truth'])} object px in front of the fingers found")
    if not args.no_real:
        if REAL_VIDEO.is_file():
            out = ROOT / "runs" / "stage_quality" / "real_video_contact_sheet.png"
            out.parent.mkdir(parents=True, exist_ok=True)
            contact_sheet(REAL_VIDEO, out)
            print(f"contact sheet: {out}")
        else:
            print(f"real video not found at {REAL_VIDEO} (set HANDEDIT_REAL_VIDEO); no contact sheet")


if __name__ == "__main__":
    main()
