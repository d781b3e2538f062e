"""The MANO 21-joint order and the hand sides, documented once for the whole project.

Every keypoint array in handedit is (..., 21, 3) in this order, in metres, in the
OpenCV camera frame (x right, y down, z forward) unless a name says otherwise. A clip
tracks one or more hands: its arrays carry a ``hand`` axis before the joint axis, in
the order of ``ClipInfo.hands`` (``SIDES`` order: left before right), e.g. keypoints
(T, S, 21, 3) with S = 2 for EgoDex and S = 1 for a one-hand source.

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
SIDES: tuple[str, ...] = ("left", "right")

# Arm joints beyond the hand, per side, where a source tracks them (EgoDex does):
#   elbow     EgoDex "Forearm" (0.27 m from the wrist)
#   shoulder  EgoDex "Arm", the shoulder joint (0.31 m further; left and right 0.36 m apart)
#   clavicle  EgoDex "Shoulder", the clavicle's inner end (0.16 m further, near the neck)
# segment reads the elbow (forearm direction), the virtual-base search the shoulders.
ARM_JOINTS: tuple[str, ...] = ("elbow", "shoulder", "clavicle")
ELBOW, SHOULDER = 0, 1

# Parent of each joint in the kinematic tree (wrist is the root).
PARENT: tuple[int, ...] = (-1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19)
