"""The MANO 21-joint order, documented once for the whole project.

Every keypoint array in handedit is (..., 21, 3) in this order, in metres, in the
OpenCV camera frame (x right, y down, z forward) unless a name says otherwise.

    0  wrist
    1  thumb_cmc    2  thumb_mcp    3  thumb_ip     4  thumb_tip
    5  index_mcp    6  index_pip    7  index_dip    8  index_tip
    9  middle_mcp  10  middle_pip  11  middle_dip  12  middle_tip
   13  ring_mcp    14  ring_pip    15  ring_dip    16  ring_tip
   17  pinky_mcp   18  pinky_pip   19  pinky_dip   20  pinky_tip

This is the OpenPose/MediaPipe ordering that MANO-based datasets (ARCTIC, OakInk2,
HOI4D, HO-Cap) export after appending fingertip vertices to MANO's 16 joints; EgoDex's
joint names map onto it in the dataset adapter.
"""

from __future__ import annotations

MANO_JOINTS: tuple[str, ...] = (
    "wrist",
    "thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip",
    "index_mcp", "index_pip", "index_dip", "index_tip",
    "middle_mcp", "middle_pip", "middle_dip", "middle_tip",
    "ring_mcp", "ring_pip", "ring_dip", "ring_tip",
    "pinky_mcp", "pinky_pip", "pinky_dip", "pinky_tip",
)
N_JOINTS = len(MANO_JOINTS)
JOINT_INDEX = {name: i for i, name in enumerate(MANO_JOINTS)}

WRIST = 0
FINGERTIPS: tuple[int, ...] = (4, 8, 12, 16, 20)  # thumb, index, middle, ring, pinky
MCPS: tuple[int, ...] = (1, 5, 9, 13, 17)
FINGERS: dict[str, tuple[int, ...]] = {
    "thumb": (1, 2, 3, 4),
    "index": (5, 6, 7, 8),
    "middle": (9, 10, 11, 12),
    "ring": (13, 14, 15, 16),
    "pinky": (17, 18, 19, 20),
}
# Parent of each joint in the kinematic tree (wrist is the root).
PARENT: tuple[int, ...] = (-1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19)
