"""Target robot embodiments: roster, URDF loading and symbolic kinematics."""

from handedit.embodiments.errors import (
    AssetsMissing,
    BrokenUrdf,
    EmbodimentError,
    MissingMesh,
    UrdfNotFound,
)
from handedit.embodiments.roster import (
    ArmSpec,
    Embodiment,
    HandSpec,
    KeypointLink,
    ResolvedAsset,
    UrdfAsset,
    describe_embodiment,
    get_embodiment,
    list_embodiments,
    resolve_asset,
    resolve_urdf,
)
from handedit.embodiments.urdf import load_urdf

__all__ = [
    "ArmSpec", "AssetsMissing", "BrokenUrdf", "Embodiment", "EmbodimentError", "HandSpec",
    "KeypointLink", "MissingMesh", "ResolvedAsset", "UrdfAsset", "UrdfNotFound",
    "describe_embodiment", "get_embodiment", "list_embodiments", "load_urdf", "resolve_asset", "resolve_urdf",
]
