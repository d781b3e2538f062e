"""Render robot embodiments (URDF) at joint configurations seen by a camera: RGB, mask, depth."""

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")  # must precede any pyrender/OpenGL import

from handedit.render.cache import clear_renderers, embodiment_renderer, get_renderer, render_embodiment  # noqa: E402
from handedit.render.framing import frame_points, rotation_from_euler  # noqa: E402
from handedit.render.model import joint_limits  # noqa: E402
from handedit.render.renderer import RenderResult, RobotRenderer  # noqa: E402

__all__ = [
    "RenderResult",
    "RobotRenderer",
    "clear_renderers",
    "embodiment_renderer",
    "frame_points",
    "get_renderer",
    "joint_limits",
    "render_embodiment",
    "rotation_from_euler",
]
