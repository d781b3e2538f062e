"""Target robot embodiments: roster, URDF loading and symbolic kinematics."""

from handedit.embodiments.errors import (
    AssetsMissing,
    BrokenUrdf,
    EmbodimentError,
    MissingMesh,
    UrdfNotFound,
)
from handedit.embodiments.roster import (
    ArmAsset,
    ArmSpec,
    Embodiment,
    HandSpec,
    KeypointLink,
    ResolvedArm,
    ResolvedAsset,
    UrdfAsset,
    asset_status,
    describe_embodiment,
    get_embodiment,
    list_embodiments,
    render_materials,
    resolve_arm,
    resolve_asset,
    resolve_urdf,
)
from handedit.embodiments.urdf import load_urdf

__all__ = [
    "ArmAsset", "ResolvedArm", "asset_status", "render_materials", "resolve_arm",
    "ArmSpec", "AssetsMissing", "BrokenUrdf", "Embodiment", "EmbodimentError", "HandSpec",
    "KeypointLink", "MissingMesh", "ResolvedAsset", "UrdfAsset", "UrdfNotFound",
    "describe_embodiment", "get_embodiment", "list_embodiments", "load_urdf", "resolve_asset", "resolve_urdf",
]
