"""Offscreen rendering of a URDF embodiment seen by an OpenCV pinhole camera.

One pyrender scene and one OffscreenRenderer per RobotRenderer: meshes are uploaded once and
every frame only moves link nodes. EGL contexts are bound to the thread that created them, so
a RobotRenderer refuses calls from other threads (use ``get_renderer`` per thread).
"""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")  # before pyrender/OpenGL import: headless

import threading  # noqa: E402
from collections.abc import Iterator  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pyrender  # noqa: E402

from handedit.camera import CV_TO_GL, Intrinsics  # noqa: E402
from handedit.embodiments.linkage import poly_mimics  # noqa: E402
from handedit.render.fk import LinkFK  # noqa: E402
from handedit.render.gl import Scene, make_offscreen  # noqa: E402
from handedit.render.model import Rgba, RobotModel, build_model, hull_points  # noqa: E402

Z_NEAR, Z_FAR = 0.01, 20.0  # metres; 24-bit depth keeps ~µm precision at 0.5 m with these
AMBIENT = 0.35
# (direction the light travels in the OpenCV camera frame, intensity): a key light from the
# upper left behind the camera and a weaker fill from the right, like a head-mounted view.
LIGHTS_CV: tuple[tuple[tuple[float, float, float], float], ...] = (
    ((0.45, 0.65, 1.0), 3.0),
    ((-0.8, -0.1, 0.6), 1.4),
)


@dataclass
class RenderResult:
    rgba: np.ndarray  # (n,H,W,4) uint8; alpha 255 on robot pixels, RGB black where alpha is 0
    depth: np.ndarray  # (n,H,W) float32 metres along the camera z axis; 0 where no robot
    boxes: np.ndarray | None = None  # (n,4) int (x, y, w, h): every robot pixel lies inside; None: anywhere
    arm: np.ndarray | None = None  # (n,H,W) bool: robot pixels of an arm link (a hand-arm's arm); None: no arm

    def box(self, i: int) -> tuple[slice, slice]:
        """Frame i's box as (rows, columns) slices."""
        if self.boxes is None:
            return slice(None), slice(None)
        return box_slices(self.boxes[i])

    @property
    def mask(self) -> np.ndarray:
        """(n,H,W) bool robot silhouette."""
        return self.rgba[..., 3] > 0


@dataclass
class Crop:
    """One frame's render inside its screen box (``box`` (x, y, w, h); w or h 0: off screen)."""

    box: tuple[int, int, int, int]
    rgba: np.ndarray  # (h,w,4) uint8
    depth: np.ndarray  # (h,w) float32
    arm: np.ndarray | None  # (h,w) bool or None (no arm)

    @property
    def slices(self) -> tuple[slice, slice]:
        return box_slices(self.box)


def box_slices(box) -> tuple[slice, slice]:
    """An (x, y, w, h) pixel box as (rows, columns) slices."""
    x, y, w, h = (int(v) for v in box)
    return slice(y, y + h), slice(x, x + w)


def _light_pose_gl(direction_cv: np.ndarray) -> np.ndarray:
    """Pose (in the GL camera frame) of a pyrender directional light shining along ``direction_cv``."""
    d = CV_TO_GL[:3, :3] @ (np.asarray(direction_cv, float) / np.linalg.norm(direction_cv))
    z = -d  # pyrender lights shine along their -z axis
    x = np.cross([0.0, 1.0, 0.0], z)
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2] = x, np.cross(z, x), z
    return T


ARM_ALPHA = 0.5  # material alpha of arm links: read back as 128, the part's tag (RobotRenderer)


def arm_links(urdf, hand_root: str) -> frozenset[str]:
    """The links outside ``hand_root``'s subtree (a hand-arm's arm, its base and flange)."""
    children: dict[str, list[str]] = {}
    for j in urdf.robot.joints:
        children.setdefault(j.parent, []).append(j.child)
    if hand_root not in {link.name for link in urdf.robot.links}:
        raise ValueError(f"hand root link '{hand_root}' is not a link of {urdf.robot.name}")
    hand, todo = set(), [hand_root]
    while todo:
        link = todo.pop()
        hand.add(link)
        todo.extend(children.get(link, ()))
    return frozenset(link.name for link in urdf.robot.links) - hand


def screen_box(points: np.ndarray, camera_from_link: np.ndarray, link: np.ndarray, intr: Intrinsics,
               corners: np.ndarray, margin: int = 2) -> tuple[int, int, int, int]:
    """(x, y, w, h) pixel box holding every pixel the links' hulls can cover, clipped to the
    image (w or h 0: off screen). ``points``: each link's hull points, ``link`` the link of each
    (``hull_points``); ``corners``: (links, 8, 3) each link's box in its own frame (``link_corners``).
    A link that crosses the near plane is drawn clipped there: its visible part lies in the hull
    of its box's corners in front and of where its edges cross the plane (``_near_clipped``; the
    box, 8 corners, not the hull's hundreds of points, which cost more than the pixels saved).
    A hand-arm's base is behind the head camera and its upper arm passes beside it: without the
    clip every hand-arm frame was drawn full-frame."""
    T = camera_from_link[link]
    p = np.einsum("mij,mj->mi", T[:, :3, :3], points) + T[:, :3, 3]
    behind = p[:, 2] <= NEAR_CLIP
    if behind.any():
        cut = np.unique(link[behind])
        keep = ~np.isin(link, cut)
        C = camera_from_link[cut]
        c = (np.einsum("kij,kpj->kpi", C[:, :3, :3], corners[cut]) + C[:, None, :3, 3]).reshape(-1, 3)
        cl = np.repeat(cut, corners.shape[1])
        p = np.concatenate([p[keep], _near_clipped(c, cl)])
        if not len(p):
            return 0, 0, 0, 0
    u, v = intr.fx * p[:, 0] / p[:, 2] + intr.cx, intr.fy * p[:, 1] / p[:, 2] + intr.cy
    x0, x1 = max(int(np.floor(u.min())) - margin, 0), min(int(np.ceil(u.max())) + margin, intr.width)
    y0, y1 = max(int(np.floor(v.min())) - margin, 0), min(int(np.ceil(v.max())) + margin, intr.height)
    return x0, y0, max(x1 - x0, 0), max(y1 - y0, 0)


def link_corners(points: np.ndarray, link: np.ndarray, n_links: int) -> np.ndarray:
    """(n_links, 8, 3) the corners of each link's axis-aligned box in its own frame (it holds the hull)."""
    out = np.zeros((n_links, 8, 3))
    for k in range(n_links):
        q = points[link == k]
        if len(q):
            lo, hi = q.min(0), q.max(0)
            out[k] = [[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[m][2]] for i in (0, 1) for j in (0, 1) for m in (0, 1)]
    return out


def out_of_view(camera_from_link: np.ndarray, corners: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """(links,) bool: the link's box lies wholly outside one plane of the view frustum (behind the
    near plane, or beyond an image edge), so it covers no pixel and need not be drawn. The planes
    pass through the camera centre, so the test holds for corners behind the camera too. A
    hand-arm's base and upper arm are mostly behind or beside the head camera: drawing them cost
    their whole vertex work for no pixel."""
    c = np.einsum("kij,kpj->kpi", camera_from_link[:, :3, :3], corners) + camera_from_link[:, None, :3, 3]
    x, y, z = c[..., 0], c[..., 1], c[..., 2]
    outside = (
        (z <= Z_NEAR),
        (intr.fx * x + intr.cx * z < 0),  # u < 0
        (intr.fx * x + (intr.cx - intr.width) * z > 0),  # u > width
        (intr.fy * y + intr.cy * z < 0),  # v < 0
        (intr.fy * y + (intr.cy - intr.height) * z > 0),  # v > height
    )
    return np.any([o.all(axis=1) for o in outside], axis=0)


def lod_levels(camera_from_link: np.ndarray, corners: np.ndarray, intr: Intrinsics, error: np.ndarray,
               px: float) -> np.ndarray:
    """(links,) each link's level of detail: the coarsest whose silhouette error (``error``
    (links, levels) metres, non-decreasing along a row, 0 first) moves the outline by at most
    ``px`` pixels where the link comes nearest the camera (f * error / z at its box's nearest
    corner). A link reaching the near plane gets its full mesh."""
    c = np.einsum("kij,kpj->kpi", camera_from_link[:, :3, :3], corners) + camera_from_link[:, None, :3, 3]
    z = c[..., 2].min(axis=1)
    near = z <= Z_NEAR
    pixels = error * (max(intr.fx, intr.fy) / np.where(near, 1.0, z))[:, None]
    fine = (pixels <= px) & ~near[:, None]
    fine[:, 0] = True
    return fine.shape[1] - 1 - np.argmax(fine[:, ::-1], axis=1)


NEAR_CLIP = Z_NEAR * 1.001  # crossing points sit just in front of the near plane, where the projection is finite


def _near_clipped(p: np.ndarray, link: np.ndarray) -> np.ndarray:
    """The points of each link in front of the near plane plus, for a link with points on both
    sides, the crossings of every segment between a point in front and one behind (a convex
    hull clipped by a plane is the hull of those); links wholly behind drop out."""
    front = p[:, 2] > NEAR_CLIP
    out = [p[front]]
    for k in np.unique(link[~front]):
        mine = link == k
        a, b = p[mine & front], p[mine & ~front]
        if not len(a):
            continue
        t = (NEAR_CLIP - b[:, None, 2]) / (a[None, :, 2] - b[:, None, 2])  # along b -> a
        out.append((b[:, None] + t[..., None] * (a[None] - b[:, None])).reshape(-1, 3))
    return np.concatenate(out)


class RobotRenderer:
    """Renders one URDF at joint configurations; heavy state (meshes, GL context) built once.

    ``materials``: link-name regex (``re.fullmatch``, first match wins) -> display (sRGB) RGBA in
    [0, 1], overriding the mesh colours of matching links (the embodiment roster's convention).
    Links with no match keep their URDF/mesh colours; meshes with none render neutral grey.
    ``decimate``: keep about this fraction of the faces of each dense mesh (quadric decimation;
    small meshes, and meshes whose silhouette would change, stay in full: ``model.decimate_mesh``).
    ``lod_px``: draw each link at the coarsest level of detail (``model.LOD_FRACTIONS``) whose
    silhouette error, seen from the link's nearest point, is at most this many pixels
    (``lod_levels``); None: the full meshes always.
    ``hand_root``: a hand-arm's hand root link; the links outside its subtree are the arm, and
    ``render`` says which pixels show them (``RenderResult.arm``) at no extra pass: their
    material's alpha is ``ARM_ALPHA``, which the shader writes out (meshes are drawn opaque).
    """

    def __init__(
        self,
        urdf_path: Path,
        width: int,
        height: int,
        materials: dict[str, Rgba] | None = None,
        decimate: float | None = None,
        hand_root: str | None = None,
        lod_px: float | None = None,
    ) -> None:
        self.urdf_path = Path(urdf_path)
        self.width, self.height = int(width), int(height)
        self.decimate = decimate
        self.lod_px = lod_px
        self.model: RobotModel = build_model(self.urdf_path, materials=materials, decimate=decimate, lod=lod_px is not None)
        self.urdf = self.model.urdf
        self.joint_names: list[str] = list(self.urdf.actuated_joint_names)
        self._fk = LinkFK(self.urdf, poly_mimics(self.urdf_path))
        self._thread = threading.get_ident()
        self.arm_links = arm_links(self.urdf, hand_root) if hand_root is not None else frozenset()

        # The camera sits at the scene origin; the scene frame *is* the GL camera frame, so lights
        # placed in it stay fixed relative to the camera and robot poses are CV_TO_GL @ root_pose.
        self.scene = Scene(bg_color=(0.0, 0.0, 0.0, 0.0), ambient_light=(AMBIENT,) * 3)
        self._link_nodes: dict[str, pyrender.Node] = {}  # each link's full mesh
        self._lod_nodes: dict[str, list[pyrender.Node]] = {}  # each link's levels of detail, full first
        errors = []
        for link in self.model.links:
            parts = [p for p in self.model.parts if p.link == link]
            nodes, error, n_drawn = [], [], 0
            for level in range(1 + max(len(p.lods) for p in parts)):
                arrays = [p if level == 0 else p.lods[level - 1] for p in parts]
                faces = sum(len(a.faces) for a in arrays)
                if level and faces > 0.75 * n_drawn:  # saves too little to be worth a level
                    continue
                prims = [self._primitive(link, p.material, a) for p, a in zip(parts, arrays) if len(a.faces)]
                nodes.append(self.scene.add(pyrender.Mesh(prims), name=link if level == 0 else f"{link}@lod{level}"))
                error.append(0.0 if level == 0 else max(a.error for a in arrays))
                n_drawn = faces
            self._link_nodes[link], self._lod_nodes[link] = nodes[0], nodes
            errors.append(error)
        width = max(len(e) for e in errors)
        self._lod_error = np.array([e + [np.inf] * (width - len(e)) for e in errors])  # (links, levels) metres
        for direction, intensity in LIGHTS_CV:
            light = pyrender.DirectionalLight(color=np.ones(3), intensity=intensity)
            self.scene.add(light, pose=_light_pose_gl(np.array(direction)))
        self._camera = pyrender.IntrinsicsCamera(
            fx=1.0, fy=1.0, cx=self.width / 2, cy=self.height / 2, znear=Z_NEAR, zfar=Z_FAR
        )
        self.scene.add(self._camera, pose=np.eye(4))
        self._gl = make_offscreen(self.width, self.height)
        self._hull_link, self._hull_points = hull_points(self.model, list(self._link_nodes))
        self._hull_corners = link_corners(self._hull_points, self._hull_link, len(self._link_nodes))

    def _primitive(self, link: str, material, arrays) -> pyrender.Primitive:
        return pyrender.Primitive(
            positions=arrays.vertices,
            normals=arrays.normals,
            indices=arrays.faces,
            material=pyrender.MetallicRoughnessMaterial(
                baseColorFactor=(*material.rgba[:3], ARM_ALPHA if link in self.arm_links else 1.0),
                metallicFactor=material.metallic,
                roughnessFactor=material.roughness,
                doubleSided=material.double_sided,
                alphaMode="OPAQUE",
            ),
        )

    @property
    def n_faces(self) -> int:
        return self.model.n_faces

    def link_transforms(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """root_link_from_link (4x4) for every link with visual geometry at configuration ``q``."""
        T = self._fk(q)
        return {link: T[link] for link in self._link_nodes}

    def points(self, q: np.ndarray, per_part: int = 400) -> np.ndarray:
        """A subsample of visual vertices in the root-link frame at ``q`` (for framing and checks)."""
        Ts = self.link_transforms(q)
        out = []
        for p in self.model.parts:
            v = p.vertices[:: max(1, len(p.vertices) // per_part)].astype(float)
            T = Ts[p.link]
            out.append(v @ T[:3, :3].T + T[:3, 3])
        return np.concatenate(out)

    def render(self, qpos: np.ndarray, root_pose: np.ndarray, intrinsics: Intrinsics) -> RenderResult:
        """qpos (n,dof) in ``joint_names`` order; root_pose (n,4,4) camera_from_root_link (OpenCV)."""
        n = len(np.atleast_2d(qpos))
        rgba = np.zeros((n, self.height, self.width, 4), np.uint8)
        depth = np.zeros((n, self.height, self.width), np.float32)
        boxes = np.zeros((n, 4), np.int64)
        arm = np.zeros((n, self.height, self.width), bool) if self.arm_links else None
        for i, crop in enumerate(self.crops(qpos, root_pose, intrinsics)):
            boxes[i] = crop.box
            rows, cols = crop.slices
            rgba[i, rows, cols], depth[i, rows, cols] = crop.rgba, crop.depth
            if arm is not None:
                arm[i, rows, cols] = crop.arm
        return RenderResult(rgba=rgba, depth=depth, boxes=boxes, arm=arm)

    def crops(self, qpos: np.ndarray, root_pose: np.ndarray, intrinsics: Intrinsics) -> Iterator[Crop]:
        """``render`` one frame at a time, each as its screen box's pixels only: the render stage
        merges these straight into its frames (full-frame copies per side cost a third of the stage)."""
        if threading.get_ident() != self._thread:
            raise RuntimeError(
                "RobotRenderer used from a thread other than the one that created it; EGL contexts "
                "are thread-bound: get a renderer per thread with handedit.render.get_renderer"
            )
        qpos = np.atleast_2d(np.asarray(qpos, dtype=float))
        root_pose = np.asarray(root_pose, dtype=float).reshape(-1, 4, 4)
        n = len(qpos)
        if qpos.shape[1] != len(self.joint_names):
            raise ValueError(f"qpos has {qpos.shape[1]} columns, {self.urdf_path.name} has {len(self.joint_names)} dof")
        if len(root_pose) != n:
            raise ValueError(f"root_pose has {len(root_pose)} frames, qpos has {n}")
        if not (np.isfinite(qpos).all() and np.isfinite(root_pose).all()):
            raise ValueError("qpos and root_pose must be finite")
        R = root_pose[:, :3, :3]
        if not np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-3) or (np.linalg.det(R) <= 0).any():
            # the shader transforms normals with the pose's rotation, which needs a rigid pose
            raise ValueError("root_pose rotations must be proper rotations (rigid camera_from_root)")
        if self._gl is None:
            raise RuntimeError("renderer was closed")
        if (intrinsics.width, intrinsics.height) != (self.width, self.height):
            raise ValueError(
                f"intrinsics are for {intrinsics.width}x{intrinsics.height}, renderer is {self.width}x{self.height}"
            )
        return self._crops(qpos, root_pose, intrinsics)

    def _crops(self, qpos: np.ndarray, root_pose: np.ndarray, intrinsics: Intrinsics) -> Iterator[Crop]:
        cam = self._camera
        cam.fx, cam.fy, cam.cx, cam.cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
        for i in range(len(qpos)):
            Ts = self.link_transforms(qpos[i])
            camera_from_link = np.stack([root_pose[i] @ Ts[link] for link in self._link_nodes])
            box = screen_box(self._hull_points, camera_from_link, self._hull_link, intrinsics, self._hull_corners)
            if box[2] == 0 or box[3] == 0:  # entirely off screen
                yield Crop(box, np.zeros((box[3], box[2], 4), np.uint8), np.zeros((box[3], box[2]), np.float32),
                           np.zeros((box[3], box[2]), bool) if self.arm_links else None)
                continue
            gl_from_root = CV_TO_GL @ root_pose[i]
            hidden = out_of_view(camera_from_link, self._hull_corners, intrinsics)
            levels = (np.zeros(len(hidden), np.int64) if self.lod_px is None
                      else lod_levels(camera_from_link, self._hull_corners, intrinsics, self._lod_error, self.lod_px))
            for (link, nodes), off, level in zip(self._lod_nodes.items(), hidden, levels):
                for j, node in enumerate(nodes):
                    node.mesh.is_visible = not off and j == level
                if not off:
                    self.scene.set_pose(nodes[level], gl_from_root @ Ts[link])
            # Single-sample rendering onto a (0,0,0,0) background with opaque shading: the RGBA
            # read-back already is black/transparent off the robot and alpha 255 on it.
            self._gl.region = box
            c, d = self._gl.render(self.scene, flags=pyrender.RenderFlags.RGBA)
            arm = None
            if self.arm_links:  # the part is in the alpha: arm links below 255, then every robot pixel opaque
                a = c[..., 3]
                arm = (a > 0) & (a < 255)
                np.copyto(a, 255, where=arm)
            yield Crop(box, c, d, arm)

    def close(self) -> None:
        """Free the GL context (from the creating thread)."""
        if self._gl is not None:
            self._gl.delete()
            self._gl = None
