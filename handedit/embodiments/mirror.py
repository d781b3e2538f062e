"""Left hands (and left hand-arms) by mirroring a right-hand URDF.

Every roster robot is described as a right hand; a left human hand drives its mirror
image. The mirror reflects the robot across the x-z plane of its root frame
(``ROOT_MIRROR`` = diag(1, -1, 1)):

* every joint origin T becomes M T M (a proper rigid transform again: M R M has det +1);
* a revolute/continuous axis a becomes -M a, a prismatic axis M a, so the same joint
  value gives the mirrored motion: the left hand's qpos *equals* the right hand's for a
  mirrored pose, joint names, limits and mimic couplings are unchanged;
* every visual/collision origin becomes M T M, and each mesh is reflected in its own frame
  by negating its y scale (``scale="sx -sy sz"``): the files stay untouched, and loaders
  that apply the scale (trimesh, and ``handedit.render.model``) reverse the triangle
  winding with it, so faces stay outward.

Retargeting a left hand therefore needs no second solver: reflect the left keypoints
across the camera's y-z plane (``CAMERA_MIRROR`` = diag(-1, 1, 1)), retarget them onto the
right robot (q, camera_from_root T), and the mirrored robot at ``left_pose(T)`` =
CAMERA_MIRROR T ROOT_MIRROR with the same q reproduces the left hand exactly
(``camera_from_link' = CAMERA_MIRROR (T root_from_link) ROOT_MIRROR``).

Checked against dex-urdf's real left Allegro (tests/test_mirror.py): its fingers are the
right hand's modules with the thumb moved across, so the mirrored right hand's links sit
on the left URDF's (index <-> ring finger names swapped, spread joints negated) to 1e-9,
and the two render the same silhouette.

The mirrored URDF is written once per source file to ``$HANDEDIT_CACHE_DIR/mirrored``
(named by a digest of its content, atomically), like composed hand-arm URDFs.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
from lxml import etree

from handedit.cache import cache_root
from handedit.embodiments.urdf import absolutize_meshes, matrix_to_xyz_rpy, parse_urdf_xml
from handedit.files import atomic_write

ROOT_MIRROR = np.diag([1.0, -1.0, 1.0, 1.0])
CAMERA_MIRROR = np.diag([-1.0, 1.0, 1.0, 1.0])


def _floats(text: str | None, n: int, default: float) -> np.ndarray:
    vals = [float(v) for v in (text or "").replace(",", " ").split()]
    return np.array(vals if len(vals) == n else [default] * n, float)


def _rpy_matrix(rpy: np.ndarray) -> np.ndarray:
    r, p, y = rpy
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    Rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _mirror_origin(parent: etree._Element) -> None:
    o = parent.find("origin")
    if o is None:
        return  # identity: its mirror is the identity
    T = np.eye(4)
    T[:3, :3] = _rpy_matrix(_floats(o.get("rpy"), 3, 0.0))
    T[:3, 3] = _floats(o.get("xyz"), 3, 0.0)
    xyz, rpy = matrix_to_xyz_rpy(ROOT_MIRROR @ T @ ROOT_MIRROR)
    o.set("xyz", " ".join(repr(float(v)) for v in xyz))
    o.set("rpy", " ".join(repr(float(v)) for v in rpy))


def mirror_tree(root: etree._Element) -> None:
    """Mirror a parsed URDF in place (see module doc)."""
    M = ROOT_MIRROR[:3, :3]
    for joint in root.findall("joint"):
        _mirror_origin(joint)
        axis = joint.find("axis")
        kind = joint.get("type")
        if kind in ("revolute", "continuous", "prismatic"):
            a = _floats(None if axis is None else axis.get("xyz"), 3, 0.0) if axis is not None else np.array([1.0, 0, 0])
            b = M @ a if kind == "prismatic" else -(M @ a)
            if axis is None:
                axis = etree.SubElement(joint, "axis")
            axis.set("xyz", " ".join(repr(float(v) + 0.0) for v in b))
    for link in root.findall("link"):
        for el in (*link.findall("visual"), *link.findall("collision"), *link.findall("inertial")):
            _mirror_origin(el)
        for mesh in link.iter("mesh"):
            s = _floats(mesh.get("scale"), 3, 1.0)
            mesh.set("scale", " ".join(repr(float(v)) for v in (s[0], -s[1], s[2])))


def mirror_urdf(urdf_path: str | os.PathLike) -> Path:
    """The mirrored (left) twin of a URDF file, written once to the cache (see module doc)."""
    path = Path(urdf_path).resolve()
    root = parse_urdf_xml(path).getroot()
    absolutize_meshes(root, path)
    mirror_tree(root)
    root.set("name", f"{root.get('name', 'robot')}__mirrored")
    text = etree.tostring(root, pretty_print=True, xml_declaration=True, encoding="utf-8")
    out = cache_root() / "mirrored" / f"{path.stem}-{hashlib.sha256(text).hexdigest()[:16]}.urdf"
    if not out.is_file():
        atomic_write(out, text)  # concurrent workers write identical bytes
    return out


def mirror_keypoints(points: np.ndarray) -> np.ndarray:
    """Camera-frame points (..., 3) reflected across the camera's y-z plane (x -> -x)."""
    out = np.array(points, dtype=np.float64, copy=True)
    out[..., 0] *= -1.0
    return out


def left_pose(camera_from_root: np.ndarray) -> np.ndarray:
    """camera_from_root of the mirrored robot, from the right robot's pose in the mirrored
    view: CAMERA_MIRROR @ T @ ROOT_MIRROR (works on (..., 4, 4))."""
    return CAMERA_MIRROR @ np.asarray(camera_from_root, float) @ ROOT_MIRROR


def mirror_world(world_from_camera: np.ndarray) -> np.ndarray:
    """The world seen in the mirrored view: x of the world reflected too, so world up and a
    horizontal support plane are unchanged (world' = M_w world M_c, M_w = diag(-1,1,1))."""
    return CAMERA_MIRROR @ np.asarray(world_from_camera, float) @ CAMERA_MIRROR
