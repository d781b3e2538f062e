"""Image stages: segment the hand, restore the background, composite the robot, harmonize.

One module per stage; each has a pydantic config (with a ``VERSION`` for cache keys and
a ``method`` naming the implementation, "classical" here) and a result dataclass that
carries per-frame ``status`` codes (``handedit.reasons``) and the method string used.
"""

from handedit.vision.composite import CompositeConfig, CompositeResult, composite
from handedit.vision.harmonize import HarmonizeConfig, HarmonizeResult, harmonize
from handedit.vision.restore_background import RestoreConfig, RestoreResult, restore_background
from handedit.vision.segment import SegmentConfig, SegmentResult, segment

__all__ = [
    "CompositeConfig", "CompositeResult", "composite",
    "HarmonizeConfig", "HarmonizeResult", "harmonize",
    "RestoreConfig", "RestoreResult", "restore_background",
    "SegmentConfig", "SegmentResult", "segment",
]
