"""Per-process, per-thread renderer cache and the embodiment-level convenience entry point.

Building a renderer (mesh loading, GL upload) costs seconds, so a Dask worker builds each
one once; the thread id is part of the key because an EGL context is bound to its thread,
and the robot's content (URDF and meshes, ``handedit.digests.robot_digest``) because a
worker outlives an edit of the files: a mesh changed in place is loaded again.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np

from handedit.camera import Intrinsics
from handedit.render.renderer import RenderResult, RobotRenderer
from handedit.setup_meter import building

_CACHE: dict[tuple, RobotRenderer] = {}
_LOCK = threading.Lock()


def get_renderer(
    urdf_path: Path,
    width: int,
    height: int,
    materials_key: tuple | None = None,
    decimate: float | None = None,
    hand_root: str | None = None,
    lod_px: float | None = None,
) -> RobotRenderer:
    """Cached RobotRenderer. ``materials_key`` is a hashable materials mapping: a tuple of
    (link-name regex, (r, g, b, a)) pairs, as ``RobotRenderer(materials=dict(materials_key))``;
    ``hand_root``: a hand-arm's hand root link (its arm's pixels are tagged, ``RenderResult.arm``);
    ``lod_px``: levels of detail within that many pixels (``RobotRenderer``)."""
    from handedit.digests import robot_digest

    urdf_path = Path(urdf_path).resolve()
    materials_key = tuple((str(k), tuple(float(c) for c in v)) for k, v in materials_key) if materials_key else None
    key = (os.getpid(), threading.get_ident(), str(urdf_path), robot_digest(urdf_path), int(width), int(height),
           materials_key, decimate, hand_root, lod_px)
    with _LOCK:
        renderer = _CACHE.get(key)
    if renderer is None:
        # Built outside the lock: other threads keep rendering while this one loads meshes.
        with building():
            renderer = RobotRenderer(urdf_path, width, height, dict(materials_key) if materials_key else None, decimate,
                                     hand_root, lod_px)
        with _LOCK:
            renderer = _CACHE.setdefault(key, renderer)
    return renderer


def clear_renderers() -> None:
    """Free this thread's cached renderers (GL contexts must be deleted on their own thread)."""
    me = (os.getpid(), threading.get_ident())
    with _LOCK:
        keys = [k for k in _CACHE if k[:2] == me]
        renderers = [_CACHE.pop(k) for k in keys]
    for r in renderers:
        r.close()


def embodiment_renderer(
    embodiment_id: str,
    width: int,
    height: int,
    decimate: float | None = None,
    materials: dict | None = None,
    side: str = "right",
    lod_px: float | None = None,
) -> RobotRenderer:
    """This thread's cached renderer of a registered embodiment (hand-arm: the composed URDF;
    ``side="left"``: its mirror image, ``handedit.embodiments.mirror``).

    Colours: the roster's (``embodiments.render_materials``) unless ``materials`` (link regex ->
    RGBA) overrides them; overrides are tried first, the roster's apply to the other links.
    A hand-arm's renderer tags its arm's pixels (``RenderResult.arm``)."""
    from handedit import embodiments
    from handedit.embodiments.compose import compose_embodiment
    from handedit.embodiments.mirror import mirror_urdf

    emb = embodiments.get_embodiment(embodiment_id)
    urdf_path = embodiments.resolve_urdf(emb)
    hand_root = compose_embodiment(embodiment_id).hand_root if emb.track == "hand_arm" else None
    if side == "left":
        urdf_path = mirror_urdf(urdf_path)
    merged = {**(materials or {}), **embodiments.render_materials(emb)}
    key = tuple((k, tuple(v)) for k, v in merged.items()) if merged else None
    return get_renderer(Path(urdf_path), width, height, key, decimate, hand_root, lod_px)


def render_embodiment(
    embodiment_id: str,
    qpos: np.ndarray,
    root_pose: np.ndarray,
    intrinsics: Intrinsics,
    decimate: float | None = None,
    materials: dict | None = None,
    side: str = "right",
    lod_px: float | None = None,
) -> RenderResult:
    """Render a registered embodiment: URDF and materials come from ``handedit.embodiments``;
    ``root_pose`` is camera_from_root of the URDF root (hand-arm: the arm base)."""
    renderer = embodiment_renderer(embodiment_id, intrinsics.width, intrinsics.height, decimate, materials, side, lod_px)
    return renderer.render(qpos, root_pose, intrinsics)
