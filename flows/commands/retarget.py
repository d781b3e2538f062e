"""``handedit retarget``: retarget a standalone keypoint trajectory onto one robot hand.

    handedit retarget --embodiment allegro --keypoints kp.npy --out traj.npz [--frame camera|wrist]

kp.npy: (T,21,3) float, MANO joint order (``handedit.keypoints``), metres; NaN marks a
missing joint. The output .npz holds ``joint_names`` (dof,), ``qpos`` (T,dof),
``root_pose`` (T,4,4) frame_from_root, ``wrist_pose`` (T,4,4) frame_from_wrist-link,
``fingertip_error_mm`` / ``wrist_error_mm`` (T,), ``status`` (T,) reason codes, and
``frame`` (which frame the keypoints and poses are in).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


class KeypointFileError(ValueError):
    pass


def load_keypoints(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(T,21,3) float64 keypoints and (T,21) validity from a .npy file, or a clear error."""
    p = Path(path)
    fix = "Save a float array of shape (T,21,3) in MANO joint order, in metres, with numpy.save."
    if not p.is_file():
        raise KeypointFileError(f"keypoints file {p} does not exist. {fix}")
    try:
        arr = np.load(p, allow_pickle=False)
    except Exception as e:  # not a .npy, pickled objects, truncated file
        raise KeypointFileError(f"keypoints file {p} is not a readable .npy array ({e}). {fix}") from None
    if not isinstance(arr, np.ndarray) or arr.ndim != 3 or arr.shape[1:] != (21, 3) or arr.shape[0] < 1:
        raise KeypointFileError(f"keypoints file {p} has shape {getattr(arr, 'shape', '?')}, expected (T,21,3). {fix}")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise KeypointFileError(f"keypoints file {p} has dtype {arr.dtype}, expected float. {fix}")
    kp = arr.astype(np.float64)
    valid = np.all(np.isfinite(kp), axis=-1)
    if not valid.any():
        raise KeypointFileError(f"keypoints file {p} has no finite keypoint. {fix}")
    if np.abs(kp[valid]).max() > 10.0:
        raise KeypointFileError(f"keypoints file {p} has coordinates up to {np.abs(kp[valid]).max():.1f}: "
                                f"expected metres (convert millimetres by dividing by 1000). {fix}")
    return np.where(valid[..., None], kp, 0.0), valid


def cmd_retarget(args: argparse.Namespace) -> int:
    from handedit.embodiments import EmbodimentError
    from handedit.retarget import RetargetConfig, get_retargeter, retarget

    try:
        kp, valid = load_keypoints(args.keypoints)
    except KeypointFileError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    cfg = RetargetConfig()
    try:
        res = retarget(kp, valid, args.embodiment, cfg)
        rt = get_retargeter(args.embodiment, cfg)
    except EmbodimentError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    wrist_link = next(k for k in rt.asset.keypoints if k.mano == 0)
    wrist_fn = rt.kin.fk_function(wrist_link.link)
    wrist = np.stack([res.root_pose[i] @ np.asarray(wrist_fn(res.qpos[i].astype(float)), float) for i in range(len(kp))])
    wrist[:, :3, 3] += np.einsum("tij,j->ti", wrist[:, :3, :3], np.asarray(wrist_link.offset, float))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp.npz")  # no half-written output
    np.savez(tmp, joint_names=np.array(res.joint_names), qpos=res.qpos, root_pose=res.root_pose, wrist_pose=wrist,
             fingertip_error_mm=res.fingertip_error_mm, wrist_error_mm=res.wrist_error_mm, status=res.status,
             frame=np.array(args.frame), embodiment=np.array(args.embodiment))
    tmp.replace(out)
    ok = int((res.status == 1).sum())
    tip = res.fingertip_error_mm[np.isfinite(res.fingertip_error_mm)]
    print(f"{args.embodiment}: {len(kp)} frames, {ok} ok; fingertip error mean {tip.mean() if tip.size else float('nan'):.1f} mm "
          f"-> {out}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("retarget", help="retarget a (T,21,3) keypoint .npy onto a robot hand")
    p.add_argument("--embodiment", required=True, help="embodiment id (handedit embodiments list)")
    p.add_argument("--keypoints", required=True, help=".npy of shape (T,21,3), MANO order, metres")
    p.add_argument("--out", required=True, help="output .npz")
    p.add_argument("--frame", choices=("camera", "wrist"), default="camera",
                   help="frame of the keypoints (and of the output poses): camera, or the hand's own wrist-centred frame")
    p.set_defaults(func=cmd_retarget)
