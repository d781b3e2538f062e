"""Retargeting accuracy on the synthetic hand: what ``bench/retarget.py`` reports per robot and
``handedit embodiments check`` prints for a new one (the same clips, the same numbers).

The synthetic clips' keypoints are exact (the human hand's ground truth), so the fingertip
residual is the robot's own: how closely its fingers can follow a human hand.
"""

from __future__ import annotations

import numpy as np


def _synthetic_clips(n_clips: int, n_frames: int):
    """Per clip: (source, keypoints (T,21,3) camera frame, world_from_camera, camera_from_object), no pixels."""
    from handedit.sources.synthetic import SyntheticSource, frame_keypoints, frame_state, make_clip_specs

    for spec in make_clip_specs(n_clips, n_frames=n_frames):
        src = SyntheticSource(spec)
        kps, wfc, cfo = [], [], []
        for t in range(n_frames):
            st = frame_state(src.plan, t, n_frames)
            cw = np.linalg.inv(st.world_from_camera)
            kps.append(frame_keypoints(src.plan, st) @ cw[:3, :3].T + cw[:3, 3])
            wfc.append(st.world_from_camera)
            cfo.append(cw @ st.world_from_object)
        yield src, np.array(kps), np.array(wfc), np.array(cfo)


def synthetic_keypoints(n_clips: int = 3, n_frames: int = 48) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """(name, keypoints (T,21,3) camera frame, valid, world_from_camera) without rendering pixels."""
    return [(src.spec.clip_id, kp, np.ones((n_frames, 21), bool), wfc) for src, kp, wfc, _ in _synthetic_clips(n_clips, n_frames)]


def synthetic_grasps(n_clips: int = 8, n_frames: int = 48) -> list[tuple[str, np.ndarray, np.ndarray, tuple, np.ndarray]]:
    """(name, keypoints, valid (in front of the camera, as the source marks them), object mesh,
    camera_from_object (T,4,4)): the grasp clips with what the contact terms and QC need."""
    return [(src.spec.clip_id, kp, kp[..., 2] > 0.01, src.object_mesh(), cfo)
            for src, kp, _, cfo in _synthetic_clips(n_clips, n_frames)]


def residual_stats(results: list, lower: np.ndarray, upper: np.ndarray) -> dict:
    """Fingertip residual mean / p95 and wrist mean (mm), joint-limit violations (must be 0)
    and frames the 50 mm QC threshold rejects, over ``results`` (``RetargetResult``s)."""
    tip = np.concatenate([r.fingertip_error_mm[np.isfinite(r.fingertip_error_mm)] for r in results])
    wrist = np.concatenate([r.wrist_error_mm[np.isfinite(r.wrist_error_mm)] for r in results])
    return {"tip_mean": float(tip.mean()), "tip_p95": float(np.percentile(tip, 95)), "wrist_mean": float(wrist.mean()),
            "violations": int(sum(np.sum((r.qpos < lower) | (r.qpos > upper)) for r in results)),
            "rejected": int(sum(np.sum(r.status >= 100) for r in results)), "frames": int(sum(len(r.qpos) for r in results))}


def synthetic_residual(embodiment_id: str, n_clips: int = 3, n_frames: int = 48) -> dict:
    """``residual_stats`` of a hand on the synthetic clips (bench/retarget.py's defaults)."""
    from handedit.retarget import RetargetConfig, get_retargeter, retarget

    cfg = RetargetConfig()
    rt = get_retargeter(embodiment_id, cfg)
    results = [retarget(kp, valid, embodiment_id, cfg) for _, kp, valid, _ in synthetic_keypoints(n_clips, n_frames)]
    return residual_stats(results, rt.lower, rt.upper)
