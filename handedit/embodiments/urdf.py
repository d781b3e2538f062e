"""Load URDFs with yourdfpy, failing loudly and early.

yourdfpy silently "recovers" broken XML and only logs a warning for a missing mesh, which
would later surface as an invisible robot in a render. Here both are hard errors whose
message names the offending file and the fix. Models are cached per process: FK builders
and the renderer load the same file many times.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import yourdfpy
from lxml import etree

from handedit.embodiments.errors import BrokenUrdf, MissingMesh, UrdfNotFound
from handedit.setup_meter import metered


def resolve_mesh_filename(fname: str, urdf_path: str | os.PathLike) -> Path:
    """Map a URDF mesh reference (relative, absolute, file:// or package://) to a path.

    ``package://NAME/rest`` is resolved against the URDF's ancestors: an ancestor called
    NAME (ROS / example-robot-data share layout), or NAME / share/NAME below an ancestor.
    Returns the best candidate even when it does not exist (the caller reports it).
    """
    urdf_dir = Path(urdf_path).resolve().parent
    if fname.startswith("file://"):
        fname = fname[len("file://"):]
    if fname.startswith("package://"):
        pkg, _, rest = fname[len("package://"):].partition("/")
        candidates: list[Path] = []
        for anc in (urdf_dir, *urdf_dir.parents):
            if anc.name == pkg:
                candidates.append(anc / rest)
            candidates += [anc / pkg / rest, anc / "share" / pkg / rest]
        candidates.append(urdf_dir / rest)
        for c in candidates:
            if c.is_file():
                return c
        return candidates[0]
    p = Path(fname)
    return p if p.is_absolute() else urdf_dir / p


def _check_xml(path: Path) -> None:
    try:
        etree.parse(str(path), etree.XMLParser(remove_blank_text=True))
    except etree.XMLSyntaxError as e:
        raise BrokenUrdf(
            f"URDF {path} is not valid XML ({e}). Restore the file from its source "
            f"(e.g. re-copy the dex-urdf robot folder) or fix the XML by hand."
        ) from e


def _check_meshes(urdf: yourdfpy.URDF, path: Path) -> None:
    for link in urdf.robot.links:
        for vis in link.visuals:
            mesh = vis.geometry.mesh if vis.geometry is not None else None
            if mesh is None:
                continue
            resolved = resolve_mesh_filename(mesh.filename, path)
            if not resolved.is_file():
                raise MissingMesh(
                    f"URDF {path}: visual mesh '{mesh.filename}' of link '{link.name}' not found "
                    f"(looked for {resolved}). Copy the robot's complete meshes/ folder next to "
                    f"the URDF (dex-urdf layout) or fix the filename in the URDF."
                )


@functools.lru_cache(maxsize=64)
@metered
def _load_cached(path: str, mtime_ns: int, load_meshes: bool) -> yourdfpy.URDF:
    p = Path(path)
    _check_xml(p)
    handler = functools.partial(_handler, urdf_path=path)
    try:
        parsed = yourdfpy.URDF.load(path, build_scene_graph=False, load_meshes=False, filename_handler=handler)
        if not parsed.robot.links:
            raise ValueError("no <link> elements")
        _check_meshes(parsed, p)
        urdf = yourdfpy.URDF(
            robot=parsed.robot, build_scene_graph=True, load_meshes=load_meshes, filename_handler=handler
        )
    except MissingMesh:
        raise
    except Exception as e:  # yourdfpy raises assorted errors on malformed robots
        raise BrokenUrdf(f"URDF {p} is not a valid robot description ({e!r}). Fix or replace the file.") from e
    if urdf.base_link is None:
        raise BrokenUrdf(f"URDF {p} has no single root link. Fix or replace the file.")
    return urdf


def _handler(fname: str, urdf_path: str) -> str:
    return str(resolve_mesh_filename(fname, urdf_path))


def load_urdf(path: str | os.PathLike, *, load_meshes: bool = True) -> yourdfpy.URDF:
    """Load (and cache per process) a URDF; raise a clear ``EmbodimentError`` on bad input.

    The cached model is shared: callers must not rely on its current configuration
    (call ``update_cfg`` before reading transforms). ``load_meshes=False`` is enough for
    kinematics; mesh files are still checked for existence either way.
    """
    p = Path(path).expanduser().resolve()
    if not p.is_file():
        raise UrdfNotFound(
            f"URDF file {p} does not exist. Provide it (dex-urdf layout under a directory in "
            f"HANDEDIT_ASSET_DIRS) or fix the path."
        )
    return _load_cached(str(p), p.stat().st_mtime_ns, load_meshes)


def parse_urdf_xml(path: Path) -> etree._ElementTree:
    """A URDF as an XML tree (for writing derived URDFs), or ``BrokenUrdf`` naming the file."""
    try:
        return etree.parse(str(path), etree.XMLParser(remove_blank_text=True, remove_comments=True))
    except etree.XMLSyntaxError as e:
        raise BrokenUrdf(f"URDF {path} is not valid XML ({e}). Restore the file from its source.") from e


def absolutize_meshes(root: etree._Element, urdf_path: Path) -> None:
    """Mesh references made absolute, so a derived URDF written elsewhere finds them."""
    for mesh in root.iter("mesh"):
        fn = mesh.get("filename")
        if fn:
            mesh.set("filename", str(resolve_mesh_filename(fn, urdf_path)))


def matrix_to_xyz_rpy(T) -> tuple:
    """URDF origin (xyz, rpy; R = Rz(y) Ry(p) Rx(r)) of a rigid 4x4."""
    import numpy as np

    R = np.asarray(T, float)[:3, :3]
    pitch = np.arctan2(-R[2, 0], np.hypot(R[0, 0], R[1, 0]))
    if np.hypot(R[0, 0], R[1, 0]) < 1e-12:  # gimbal lock: put everything into roll
        roll, yaw = np.arctan2(-R[1, 2], R[1, 1]), 0.0
    else:
        roll, yaw = np.arctan2(R[2, 1], R[2, 2]), np.arctan2(R[1, 0], R[0, 0])
    return np.asarray(T, float)[:3, 3], np.array([roll, pitch, yaw])
