"""Replay previews of the top virtual-base candidates, for the operator's sequence choice.

Egocentric: the robot rendered in the source camera (what the pseudo-GT will show).
Third-person: a fixed virtual camera beside the arm, looking at the midpoint between the
base and the hand's mean position from ``side_m`` metres to the side and above, so base
plausibility, overextension and collisions are visible (the paper's replay videos).
"""

from __future__ import annotations

import numpy as np

from handedit.camera import Intrinsics, look_at
from handedit.retarget.hand_arm import HandArmResult


def third_person_camera(camera_from_base: np.ndarray, hand_points: np.ndarray, up: np.ndarray, side_m: float = 1.2) -> np.ndarray:
    """ref_from_camera of the third-person view (all in the reference frame of the base)."""
    base = camera_from_base[:3, 3]
    mid = (base + hand_points.mean(axis=0)) / 2
    lateral = camera_from_base[:3, 1]
    eye = mid + side_m * lateral + 0.5 * side_m * up / np.linalg.norm(up)
    return look_at(eye, mid, up)


def render_previews(res: HandArmResult, intr: Intrinsics, candidates: list[int] | None = None,
                    frames: list[int] | None = None, world_from_camera: np.ndarray | None = None,
                    up: np.ndarray | None = None) -> dict[int, dict[str, np.ndarray]]:
    """candidate -> {"ego": (n,H,W,4) uint8, "third": (n,H,W,4) uint8} for the top-3 by default.
    ``world_from_camera`` + ``up``: the base is fixed in that world (else in the camera frame)."""
    from handedit.render import render_embodiment
    from handedit.retarget.arm import arm_model

    vb = res.virtual_base
    arm = arm_model(vb.embodiment_id)
    cands = vb.ranking[:3] if candidates is None else candidates
    n = len(res.qpos)
    frames = list(range(n)) if frames is None else frames
    world = world_from_camera is not None and up is not None
    up = np.asarray(up, float) if world else np.array([0.0, -1.0, 0.0])
    names = arm.kin.joint_names
    out: dict[int, dict[str, np.ndarray]] = {}
    for c in cands:
        ref_from_base = vb.candidates[c].camera_from_base
        q = np.tile(res.qpos[frames].astype(float), (1, 1))
        q[:, arm.arm_idx] = vb.arm_tracks[c][frames]
        cam_from_ref = np.linalg.inv(world_from_camera[frames]) if world else np.tile(np.eye(4), (len(frames), 1, 1))
        ego = render_embodiment(vb.embodiment_id, q, cam_from_ref @ ref_from_base, intr)
        hand = np.array([(ref_from_base @ arm.wrist_pose(vb.arm_tracks[c][i]))[:3, 3] for i in frames])
        ref_from_tp = third_person_camera(ref_from_base, hand, up)
        tp_from_base = np.linalg.inv(ref_from_tp) @ ref_from_base
        third = render_embodiment(vb.embodiment_id, q, np.tile(tp_from_base, (len(frames), 1, 1)), intr)
        out[c] = {"ego": ego.rgba, "third": third.rgba, "joint_names": np.array(names)}
    return out


def preview_frames(n: int, count: int = 3) -> list[int]:
    """``count`` frames evenly spaced over a sequence of ``n``, first and last included (3: the
    first, middle and last; more: a replay)."""
    if n <= 1 or count <= 1:
        return [0]
    return sorted({int(np.floor(i * (n - 1) / (count - 1) + 0.5)) for i in range(count)})


def top_previews(res: HandArmResult, intr: Intrinsics, world_from_camera: np.ndarray | None = None,
                 top: int = 3, up: np.ndarray | None = None, frames: int = 3) -> tuple[list[int], list[int], np.ndarray, np.ndarray]:
    """What an operator reviews: the top candidates at ``frames`` frames of the sequence (the
    first, middle and last; under ``review: manual`` a replay).

    Returns (candidates, frames, ego (K,P,H,W,4), third (K,P,H,W,4)); K = 0 when no
    candidate survived the search.
    """
    frames = preview_frames(len(res.qpos), frames)
    cands = res.virtual_base.ranking[:top]
    shape = (0, len(frames), intr.height, intr.width, 4)
    if not cands:
        return [], frames, np.zeros(shape, np.uint8), np.zeros(shape, np.uint8)
    views = render_previews(res, intr, candidates=cands, frames=frames, world_from_camera=world_from_camera, up=up)
    return cands, frames, np.stack([views[c]["ego"] for c in cands]), np.stack([views[c]["third"] for c in cands])


def replay(source: np.ndarray, ego: np.ndarray, third: np.ndarray, grey: int = 96) -> np.ndarray:
    """One candidate's review frames, (P,H,2W,3) uint8: its egocentric render over the source
    frame (what the pseudo-GT will show) beside its third-person render on grey (where the base
    stands), for the paper's replay videos."""
    a = ego[..., 3:].astype(np.float32) / 255
    left = source.astype(np.float32) * (1 - a) + ego[..., :3].astype(np.float32) * a
    b = third[..., 3:].astype(np.float32) / 255
    right = grey * (1 - b) + third[..., :3].astype(np.float32) * b
    return np.concatenate([left, right], axis=2).round().astype(np.uint8)


def write_video(path, frames: np.ndarray, fps: float) -> None:
    """(P,H,W,3) RGB uint8 frames as an MP4 (OpenCV's own MPEG-4 encoder: no system FFmpeg)."""
    import cv2

    h, w = frames.shape[1:3]
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
    if not out.isOpened():
        raise OSError(f"cannot write the video {path}: OpenCV has no MPEG-4 writer here")
    try:
        for f in frames:
            out.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    finally:
        out.release()
