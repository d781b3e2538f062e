"""Content hashes of files: one implementation for sources, models, assets and releases."""

from __future__ import annotations

import hashlib
from functools import lru_cache
from pathlib import Path

_BLOCK = 1 << 20


def file_sha256(path: str | Path) -> str:
    """sha256 of a file's bytes, cached per process by (path, inode, size, mtime, ctime): a
    file rewritten or replaced in place is hashed again, an unchanged one once."""
    st = Path(path).stat()
    return _sha256(str(path), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


@lru_cache(maxsize=1024)
def _sha256(path: str, ino: int, size: int, mtime_ns: int, ctime_ns: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(_BLOCK):
            h.update(block)
    return h.hexdigest()


def file_digest(path: str | Path) -> str:
    """``file_sha256``, or "missing" for a file that is not there (a plan still keys on it;
    the stage that needs the file reports it)."""
    try:
        return file_sha256(path)
    except OSError:
        return "missing"


def model_digests(stage_config) -> dict[str, str]:
    """Content of every model file a stage's config runs, by input name: ``model`` for its
    ``model_path`` (the ONNX plug-ins), plus what the config's own ``model_digests()`` names
    (files it finds itself, e.g. estimate_hands' hand models). New weights at the same path
    change these, so the stage, and only what reads it, runs again."""
    out = {}
    path = getattr(stage_config, "model_path", None)
    if path:
        out["model"] = file_digest(path)
    own = getattr(stage_config, "model_digests", None)
    if callable(own):
        out.update(own())
    return out


def robot_digest(urdf_path: str | Path) -> str:
    """The content of a robot: its URDF and every mesh file it names (visual and collision),
    resolved the way the URDF loader resolves them. A mesh edited in place changes it, so
    the stages that load the robot run again."""
    import xml.etree.ElementTree as ET

    import yourdfpy

    urdf_path = Path(urdf_path)
    h = hashlib.sha256(file_digest(urdf_path).encode())
    try:
        names = sorted({m.get("filename") for m in ET.parse(urdf_path).iter("mesh") if m.get("filename")})
    except (OSError, ET.ParseError):
        return h.hexdigest()  # the loader reports an unreadable URDF
    for name in names:
        resolved = yourdfpy.filename_handler_magic(name, dir=str(urdf_path.parent))
        h.update(f"\n{name}={file_digest(resolved)}".encode())
    return h.hexdigest()


def embodiment_digest(urdf_path: str | Path, robot_files: tuple[str, ...] = ()) -> str:
    """``robot_digest`` and the content of the robot files the embodiment is made of (its
    keypoints, wrist calibration, colours): editing a robot file runs its stages again."""
    h = hashlib.sha256(robot_digest(urdf_path).encode())
    for f in robot_files:
        h.update(f"\n{Path(f).name}={file_digest(f)}".encode())
    return h.hexdigest()
