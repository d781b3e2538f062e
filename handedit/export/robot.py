"""What a policy dataset must say about its robot: the URDF its joints belong to, which joints
are actuated and which follow them, how left hands are made, and each side's wrist pose.

Joint vectors are the store's ``qpos`` columns: the URDF's actuated joints in yourdfpy's order
(``Kinematics.joint_names``), mimic joints left out (they follow from the others). Left sides
drive the mirror image of the right-hand URDF (``handedit.embodiments.mirror``): the same joint
names and values, the mirrored pose.
"""

from __future__ import annotations

import numpy as np

from handedit.embodiments.mirror import ROOT_MIRROR

LEFT = ("mirrored: the left side drives the right-hand URDF mirrored across its root's x-z plane "
        "(diag(1,-1,1)); joint names, values and limits are the right hand's (handedit.embodiments.mirror)")
POSE_NAMES = ("x", "y", "z", "qx", "qy", "qz", "qw")


def robot_info(embodiment_id: str) -> dict:
    """Embodiment key, name and track, the URDF (path, sha256, where its parts came from),
    actuated and mimic joints, and how left sides are made."""
    from handedit.digests import file_sha256
    from handedit.embodiments import get_embodiment, resolve_asset, resolve_urdf
    from handedit.embodiments.kinematics import get_kinematics

    emb = get_embodiment(embodiment_id)
    urdf = resolve_urdf(emb)
    kin = get_kinematics(urdf)
    parts = {"hand": str(resolve_asset(emb).origin)}
    if emb.arm is not None:
        from handedit.embodiments.compose import compose_embodiment

        c = compose_embodiment(embodiment_id)
        parts["arm"] = str(c.arm_urdf)
    return {
        "embodiment": emb.id, "name": emb.name, "track": emb.track, "description": emb.description,
        "urdf": {"path": str(urdf), "sha256": file_sha256(urdf), "parts": parts},
        "actuated_joints": list(kin.joint_names),
        "mimic_joints": {n: {"follows": s, "multiplier": m, "offset": o} for n, (s, m, o) in sorted(kin.mimic_joints().items())},
        "joint_limits": {n: [_finite(lo), _finite(hi)] for n, lo, hi in zip(kin.joint_names, kin.lower, kin.upper)},
        "left": LEFT,
    }


def _finite(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def wrist_point(embodiment_id: str) -> tuple[str, np.ndarray]:
    """The link the human wrist is retargeted to and the wrist's offset on it (metres, link
    frame), in the embodiment's URDF (a hand-arm's: the composed one)."""
    from handedit.embodiments import get_embodiment, resolve_asset

    emb = get_embodiment(embodiment_id)
    if emb.arm is None:
        points = resolve_asset(emb).asset.keypoints
    else:
        from handedit.embodiments.compose import compose_embodiment

        points = compose_embodiment(embodiment_id).keypoints
    wrist = next(p for p in points if p.kind == "wrist")
    return wrist.link, np.asarray(wrist.offset, float)


def wrist_poses(embodiment_id: str, qpos: np.ndarray, root_pose: np.ndarray, sides: list[str]) -> np.ndarray:
    """(T, S, 4, 4) camera_from_wrist per side: the robot's wrist link (``wrist_point``) with
    its origin moved to the retargeted wrist point. ``root_pose`` is camera_from_URDF-root (a
    hand-arm's: its base), mirrored for left sides. NaN where the store has no pose."""
    from handedit.embodiments import get_embodiment, resolve_urdf
    from handedit.embodiments.kinematics import get_kinematics

    link, offset = wrist_point(embodiment_id)
    kin = get_kinematics(resolve_urdf(get_embodiment(embodiment_id)))
    out = np.full(root_pose.shape, np.nan)
    for t in range(out.shape[0]):
        for k, side in enumerate(sides):
            q = qpos[t, k]
            if not (np.all(np.isfinite(q)) and np.all(np.isfinite(root_pose[t, k]))):
                continue
            fk = kin.fk(q, link).copy()
            fk[:3, 3] += fk[:3, :3] @ offset
            out[t, k] = root_pose[t, k] @ (ROOT_MIRROR @ fk @ ROOT_MIRROR if side == "left" else fk)
    return out


def pose_vector(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) -> (..., 7) position and unit quaternion (x, y, z, qx, qy, qz, qw); NaN stays NaN."""
    from scipy.spatial.transform import Rotation

    flat = T.reshape(-1, 4, 4)
    out = np.full((len(flat), 7), np.nan)
    ok = np.all(np.isfinite(flat), axis=(1, 2))
    if ok.any():
        out[ok, :3] = flat[ok, :3, 3]
        out[ok, 3:] = Rotation.from_matrix(flat[ok, :3, :3]).as_quat()
    return out.reshape(*T.shape[:-2], 7)
