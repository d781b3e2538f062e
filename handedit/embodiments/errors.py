"""Embodiment errors: every message names the file or id at fault and how to fix it."""

from __future__ import annotations

from handedit.reasons import Reason


class EmbodimentError(ValueError):
    """Bad embodiment id, missing assets or a broken robot description.

    ``reason`` is the per-frame status a pipeline records for frames it cannot process.
    """

    reason: Reason = Reason.ASSETS_MISSING


class AssetsMissing(EmbodimentError):
    """No candidate URDF of an embodiment could be found (maps to Reason.ASSETS_MISSING)."""


class UrdfNotFound(EmbodimentError):
    """A URDF path does not exist."""


class BrokenUrdf(EmbodimentError):
    """A URDF is not valid XML or not a valid robot."""


class MissingMesh(EmbodimentError):
    """A visual mesh referenced by a URDF does not exist."""
