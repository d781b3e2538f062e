"""Position retargeting of MANO-order keypoints onto robot hands (casadi + IPOPT)."""

from handedit.retarget.api import RetargetResult, get_retargeter, retarget
from handedit.retarget.config import RetargetConfig

__all__ = ["RetargetConfig", "RetargetResult", "get_retargeter", "retarget"]
