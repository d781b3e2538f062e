"""The MANO wrist (palm) frame and small SE(3) helpers.

Convention (also used for every robot, from its own correspondences): origin at the
wrist point, z towards the middle MCP, y across the palm towards the index side
(orthogonalised against z), x = y x z (palm normal, out of the palm for a right hand).
The ulnar reference is the pinky MCP, or the ring MCP for robots without a pinky.
"""

from __future__ import annotations

import numpy as np

from handedit.keypoints import JOINT_INDEX

PALM_POINTS = (JOINT_INDEX["wrist"], JOINT_INDEX["index_mcp"], JOINT_INDEX["middle_mcp"], JOINT_INDEX["pinky_mcp"])


def palm_frame(wrist, index_mcp, middle_mcp, ulnar_mcp) -> np.ndarray:
    """frame_from_wrist (4x4) from four points given in some frame."""
    wrist, index_mcp, middle_mcp, ulnar_mcp = (np.asarray(p, float) for p in (wrist, index_mcp, middle_mcp, ulnar_mcp))
    z = middle_mcp - wrist
    z /= np.linalg.norm(z)
    v = index_mcp - ulnar_mcp
    y = v - (v @ z) * z
    y /= np.linalg.norm(y)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = np.cross(y, z), y, z, wrist
    return T


def keypoint_palm_frame(kp: np.ndarray) -> np.ndarray:
    """camera_from_wrist from one (21,3) MANO keypoint array."""
    return palm_frame(*(kp[i] for i in PALM_POINTS))


def cayley(c: np.ndarray) -> np.ndarray:
    """Rotation from the Cayley parameter c (R = I + 2(K + K^2)/(1 + |c|^2), K = [c]x)."""
    c = np.asarray(c, float)
    K = np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]])
    return np.eye(3) + 2.0 * (K + K @ K) / (1.0 + c @ c)


def calibrate_wrist_from_root(emb_id: str) -> np.ndarray:
    """wrist_from_root of an embodiment's resolved URDF from its own correspondences at
    the neutral pose (how the roster constants were produced)."""
    from handedit.embodiments.kinematics import get_kinematics
    from handedit.embodiments.roster import get_embodiment, resolve_asset

    ra = resolve_asset(get_embodiment(emb_id))
    kin = get_kinematics(ra.path)
    q = kin.neutral()
    for name, v in ra.asset.locked_joints:
        q[kin.joint_names.index(name)] = v
    pts = {}
    for kp in ra.asset.keypoints:
        T = kin.fk(q, kp.link)
        pts[kp.mano] = T[:3, :3] @ np.asarray(kp.offset) + T[:3, 3]
    ulnar = pts.get(JOINT_INDEX["pinky_mcp"], pts.get(JOINT_INDEX["ring_mcp"]))
    root_from_wrist = palm_frame(pts[0], pts[JOINT_INDEX["index_mcp"]], pts[JOINT_INDEX["middle_mcp"]], ulnar)
    return np.linalg.inv(root_from_wrist)
