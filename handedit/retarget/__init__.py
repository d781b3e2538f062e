"""Retargeting of MANO-order keypoints onto robot hands and hand-arm robots (casadi: IPOPT,
and a projected Newton method on warm frames).

api: hand retargeting (hybrid vector -> position); qc: its automatic QC; arm / virtual_base /
hand_arm: the hand-arm track (virtual base search, arm IK); preview: review renders.
"""

from handedit.retarget.api import RetargetResult, get_retargeter, retarget
from handedit.retarget.config import RetargetConfig
from handedit.retarget.qc import RetargetQC, RetargetQCConfig, retarget_qc
from handedit.retarget.virtual_base import VirtualBaseConfig, VirtualBaseResult, search_virtual_base

__all__ = ["RetargetConfig", "RetargetQC", "RetargetQCConfig", "RetargetResult", "VirtualBaseConfig",
           "VirtualBaseResult", "get_retargeter", "retarget", "retarget_qc", "search_virtual_base"]
