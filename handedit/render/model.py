"""Visual model of a URDF for rendering: link-rigid triangle soups grouped by material.

The URDF is parsed once with yourdfpy (its ``actuated_joint_names`` define the project's qpos
order and it derives mimic joints). Every visual mesh is baked into the frame of the link that
carries it and merged per (link, material), so a frame costs one pose update per link and a
handful of draw calls instead of one per mesh file. With ``lod`` each part also carries coarser
levels of detail, each with the silhouette error it may cost, and the renderer draws the coarsest
level a link's distance allows (``renderer.lod_levels``).
"""

from __future__ import annotations

import hashlib
import io
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
import yourdfpy

from handedit.cache import cache_root
from handedit.embodiments.roster import CAPS
from handedit.files import atomic_write

Rgba = tuple[float, float, float, float]

NEUTRAL_GREY: Rgba = (0.6, 0.6, 0.6, 1.0)
"""Display (sRGB) colour for meshes that carry no colour at all (e.g. bare STL)."""


def srgb_to_linear(rgba: np.ndarray | tuple) -> Rgba:
    """Display colour -> linear PBR base colour. URDF <color>, MTL Kd, vertex colours and our
    overrides are authored as display colours; glTF baseColorFactor is already linear, and
    pyrender's shader gamma-encodes its output, so only the former need converting."""
    c = np.asarray(rgba, float)
    rgb = np.where(c[:3] <= 0.04045, c[:3] / 12.92, ((c[:3] + 0.055) / 1.055) ** 2.4)
    return tuple(float(x) for x in (*rgb, c[3]))


@dataclass(frozen=True)
class Material:
    """The uniform PBR parameters we keep per mesh (no asset in use has textures)."""

    rgba: Rgba
    metallic: float
    roughness: float
    double_sided: bool = False


@dataclass
class LinkPart:
    """Triangles of one link sharing one material, expressed in the link frame."""

    link: str
    material: Material
    vertices: np.ndarray  # (v,3) float32
    normals: np.ndarray  # (v,3) float32
    faces: np.ndarray  # (f,3) int32
    lods: tuple[LodLevel, ...] = ()  # coarser versions, finest first (``build_model(lod=True)``)


@dataclass
class LodLevel:
    """A simplified version of a part and how far its outline may stray from the part's."""

    vertices: np.ndarray  # (v,3) float32
    normals: np.ndarray  # (v,3) float32
    faces: np.ndarray  # (f,3) int32
    error: float  # metres: the widest strip where its silhouettes differ from the full meshes'


@dataclass
class RobotModel:
    urdf: yourdfpy.URDF
    parts: list[LinkPart] = field(default_factory=list)

    @property
    def links(self) -> list[str]:
        """Links with visual geometry, in a stable order."""
        return sorted({p.link for p in self.parts})

    @property
    def n_faces(self) -> int:
        return int(sum(len(p.faces) for p in self.parts))


def load_urdf(urdf_path: Path) -> yourdfpy.URDF:
    """Load with visual meshes; a mesh that does not resolve is an error, not a silent hole."""
    urdf_path = Path(urdf_path)
    if not urdf_path.is_file():
        raise FileNotFoundError(f"URDF not found: {urdf_path}")
    urdf = yourdfpy.URDF.load(str(urdf_path), build_scene_graph=True, load_meshes=True)
    missing = []
    for link in urdf.robot.links:
        for vis in link.visuals:
            mesh = vis.geometry.mesh if vis.geometry is not None else None
            if mesh is None:
                continue
            resolved = urdf._filename_handler(fname=mesh.filename)
            if not Path(resolved).is_file():
                missing.append(f"{resolved} (link '{link.name}', URDF filename '{mesh.filename}')")
    if missing:
        raise FileNotFoundError(f"{urdf_path}: visual mesh file(s) missing: " + "; ".join(missing))
    return urdf


def _source_material(mesh: trimesh.Trimesh) -> Material | None:
    """Uniform material of a loaded mesh, or None when the file carries no colour."""
    vis = mesh.visual
    if vis is None or not vis.defined:
        return None
    if vis.kind == "texture":
        mat = vis.material
        if isinstance(mat, trimesh.visual.material.PBRMaterial):
            base = mat.baseColorFactor
            rgba = (np.asarray(base, float) / 255.0) if base is not None else np.ones(4)
            if mat.baseColorTexture is not None and vis.uv is not None:
                # Textures are averaged: the robots we render are uniformly coloured parts.
                tex = np.asarray(mat.baseColorTexture.convert("RGBA"), float) / 255.0
                rgba = rgba * tex.reshape(-1, 4).mean(axis=0)
            metallic = 1.0 if mat.metallicFactor is None else float(mat.metallicFactor)
            roughness = 1.0 if mat.roughnessFactor is None else float(mat.roughnessFactor)
            return Material(tuple(float(c) for c in rgba), metallic, roughness, bool(mat.doubleSided))
        if isinstance(mat, trimesh.visual.material.SimpleMaterial):
            rgba = np.asarray(mat.diffuse, float) / 255.0
            if mat.image is not None:
                rgba = rgba * (np.asarray(mat.image.convert("RGBA"), float) / 255.0).reshape(-1, 4).mean(axis=0)
            return Material(srgb_to_linear(rgba), 0.1, 0.6)
        return None
    if vis.kind in ("vertex", "face"):
        cols = vis.vertex_colors if vis.kind == "vertex" else vis.face_colors
        rgba = np.asarray(cols, float).mean(axis=0) / 255.0
        return Material(srgb_to_linear(rgba), 0.1, 0.6)
    return None


def _final_material(link: str, src: Material | None, overrides: list[tuple[re.Pattern, Rgba]]) -> Material:
    default = Material(srgb_to_linear(NEUTRAL_GREY), 0.1, 0.6)
    for pattern, rgba in overrides:
        if pattern.fullmatch(link):
            base = src or default
            return Material(srgb_to_linear(rgba), base.metallic, base.roughness, base.double_sided)
    return src or default


# A ``materials`` key ``LINK_REGEX@caps`` (``CAPS``) colours the joint caps of those links:
# faces square to one of the link's joint axes (its own, and its child joints') within
# ``CAP_RADIUS_M`` of that axis, i.e. the round end faces of the joint housings (the Jaka's
# blue caps are faces of single-colour STL link meshes).
CAP_RADIUS_M = 0.05
CAP_COS = 0.95


def _cap_faces(urdf: yourdfpy.URDF, link: str, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(f,) bool: the faces of a link-frame mesh that are caps of the link's joint axes."""
    axes = []
    for j in urdf.robot.joints:
        if j.type == "fixed" or j.axis is None:
            continue
        if j.child == link:
            axes.append((np.zeros(3), np.asarray(j.axis, float)))
        elif j.parent == link:
            o = np.eye(4) if j.origin is None else np.asarray(j.origin, float)
            axes.append((o[:3, 3], o[:3, :3] @ np.asarray(j.axis, float)))
    tri = verts[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    c = tri.mean(1)
    out = np.zeros(len(faces), bool)
    for point, a in axes:
        a = a / np.linalg.norm(a)
        d = c - point
        radial = np.linalg.norm(d - (d @ a)[:, None] * a, axis=1)
        out |= (np.abs(n @ a) > CAP_COS) & (radial < CAP_RADIUS_M)
    return out


def _compile_overrides(materials: dict[str, Rgba] | None) -> list[tuple[re.Pattern, Rgba]]:
    out = []
    for pattern, rgba in (materials or {}).items():
        if pattern.endswith(CAPS):
            continue
        rgba = tuple(float(c) for c in rgba)
        if len(rgba) != 4 or not all(0.0 <= c <= 1.0 for c in rgba):
            raise ValueError(f"material for {pattern!r} must be RGBA in [0, 1], got {rgba}")
        out.append((re.compile(pattern), rgba))
    return out


DECIMATE_MIN_FACES = 2000
"""Meshes at or below this many faces are never simplified: they are cheap to draw, and the
thin parts they model (fingertips, screws, tendons) are what quadric decimation destroys first."""

DECIMATE_MIN_IOU = 0.99
"""Smallest silhouette IoU a simplified mesh may have against the original, in each of three
axis-aligned orthographic views rasterised at ``SILHOUETTE_PX`` across the mesh. A 5 cm link
0.4 m from a 640x480 head camera spans ~70 px, so this check is finer than any frame we render."""

SILHOUETTE_PX = 128

DECIMATE_CREASE_DEG = 30.0
"""A simplified mesh is welded, so its vertex normals average across every edge: a ring's
flat face and its cylinder would shade as one blurred surface (flat grey patches on the
DexHand021's shell, bright blots on the KUKA's rings at 960x540). Where the source mesh has
seams (CAD exports split their vertices at creases), the simplified mesh's faces meeting at more
than this angle get their own vertices (``trimesh.graph.smooth_shade``); a source without seams
is shaded smooth across every edge, and so is its simplification (LEAP's glossy palm)."""


def _require_fast_simplification():
    try:
        import fast_simplification
    except ImportError as exc:
        raise ImportError(
            "levels of detail (lod_px=) and decimate= need quadric mesh simplification from 'fast-simplification', "
            "which is not installed (pip install fast-simplification); use lod_px=None and decimate=None to render "
            "the full meshes"
        ) from exc
    return fast_simplification


def _welded(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Plain copy with coincident vertices merged. Exporters (GLB especially) split vertices at
    every normal/UV seam, so each triangle looks like an island to the simplifier, which then
    either cannot collapse anything or tears parts apart; welding makes the surface connected."""
    out = trimesh.Trimesh(np.asarray(mesh.vertices, float), np.asarray(mesh.faces), process=False)
    out.merge_vertices(merge_tex=True, merge_norm=True)
    out.update_faces(out.nondegenerate_faces())
    out.remove_unreferenced_vertices()
    return out


def _silhouettes(vertices: np.ndarray, faces: np.ndarray, lo: np.ndarray, scale: float,
                 px: int = SILHOUETTE_PX, margin: int = 0) -> list[np.ndarray]:
    """Filled orthographic silhouettes along the mesh's x, y and z axes (uint8 masks), ``margin``
    cells of room on every side for a mesh that reaches past the reference's box."""
    import cv2

    out = []
    for drop in range(3):
        keep = [i for i in range(3) if i != drop]
        uv = (((vertices[:, keep] - lo[keep]) * scale + margin) * 16).round().astype(np.int32)  # 4 subpixel bits
        img = np.zeros((px + 2 + 2 * margin, px + 2 + 2 * margin), np.uint8)
        for tri in uv[faces]:
            cv2.fillConvexPoly(img, tri, 1, shift=4)
        out.append(img)
    return out


class _Silhouettes:
    """The three axis-aligned silhouettes of a reference mesh, on a grid of ``px`` cells across its
    largest extent with ``margin`` cells of room, to compare other meshes with: the IoU check of
    ``decimate_mesh`` (``SILHOUETTE_PX``) and the error of a level of detail (``LOD_SILHOUETTE_PX``)."""

    def __init__(self, reference: trimesh.Trimesh, px: int = SILHOUETTE_PX, margin: int = 0) -> None:
        self.px, self.margin = px, margin
        self.lo = np.asarray(reference.bounds[0], float)
        self.scale = (px - 1) / max(float(np.max(reference.extents)), 1e-12)
        self.ref = self._of(reference)

    def _of(self, mesh: trimesh.Trimesh) -> list[np.ndarray]:
        return _silhouettes(np.asarray(mesh.vertices), np.asarray(mesh.faces), self.lo, self.scale, self.px, self.margin)

    def iou(self, other: trimesh.Trimesh) -> float:
        """Smallest of the three silhouette IoUs of ``other`` against the reference."""
        return min(float((x & y).sum() / max((x | y).sum(), 1)) for x, y in zip(self.ref, self._of(other)))

    def strip_width(self, other: trimesh.Trimesh) -> float:
        """In the mesh's units: the width of the widest strip where the two meshes' silhouettes
        differ, over the three views (twice the largest distance from a differing cell to an
        agreeing one). An outline moved by d differs in a strip d wide; a lost or added detail in
        a strip as wide as the detail, however far it sits from the rest (a Hausdorff distance
        would count that distance: the Inspire palm's engraved letters, 3 mm below it)."""
        import cv2

        out = 0.0
        for ref, s in zip(self.ref, self._of(other)):
            differ = (ref != s).astype(np.uint8)
            if differ.any():
                inside = cv2.distanceTransform(differ, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
                out = max(out, 2.0 * float(inside.max()))
        return out / self.scale


def silhouette_iou(a: trimesh.Trimesh, b: trimesh.Trimesh) -> float:
    """Smallest IoU of the three axis-aligned silhouettes of ``b`` against those of ``a``."""
    return _Silhouettes(a).iou(b)


LOD_FRACTIONS = (0.5, 0.25, 0.125, 0.0625)
"""Face fractions of the coarser levels of detail (``build_model(lod=True)``), each simplified
from the one before (``lod_meshes``). A hand 0.4 m from a 960x540 head camera is ~100 px across, drawn from
100k-500k faces: most of its triangles are smaller than a pixel, and drawing them is the render's cost."""

LOD_MIN_FACES = 500
"""Levels of detail stop at this many faces; meshes at or below ``DECIMATE_MIN_FACES`` get none."""

LOD_SILHOUETTE_PX = 512
"""Silhouette grid across a mesh's largest extent for ``silhouette_error``: a 124 mm palm's
cell is 0.24 mm, finer than a pixel at 0.4 m from a 1080p head camera (~0.5 mm)."""

LOD_SILHOUETTE_MARGIN = LOD_SILHOUETTE_PX // 8
"""Cells of room around the grid: a coarser level may reach past the full mesh's box, and a strip
cut off at the grid's edge would read as wide as the part left inside."""


def _lod_silhouettes(mesh: trimesh.Trimesh) -> _Silhouettes:
    return _Silhouettes(mesh, LOD_SILHOUETTE_PX, LOD_SILHOUETTE_MARGIN)


def silhouette_error(a: trimesh.Trimesh, b: trimesh.Trimesh) -> float:
    """How far (in the meshes' units) ``b``'s three axis-aligned silhouettes stray from ``a``'s:
    the widest strip where they differ (``_Silhouettes.strip_width``). Seen at depth z by a camera of
    focal length f, ``b`` drawn for ``a`` changes the outline in a strip about f * error / z pixels
    wide: the bound ``RobotRenderer`` picks a level of detail by."""
    return _lod_silhouettes(a).strip_width(b)


LOD_CACHE_VERSION = 2
"""Bumped whenever ``lod_meshes`` would compute other levels from the same mesh."""

_LODS: dict[str, list[tuple[trimesh.Trimesh, float]]] = {}


def lod_meshes(mesh: trimesh.Trimesh, fractions: tuple[float, ...] = LOD_FRACTIONS) -> list[tuple[trimesh.Trimesh, float]]:
    """One (mesh, silhouette error in the mesh's units) per fraction of the mesh's faces, coarser
    each: the previous level simplified further, or the previous level itself where that saves
    less than a quarter of its faces. Building them costs seconds for a dense hand (Jaka's
    DexHand021: ~7 s), so they are kept per process and in the user cache (``lod/``), named by
    a digest of the mesh and of everything that shapes them: a fresh worker reads them back.
    A mesh and its mirror image (a left robot's, ``embodiments.mirror``) share one set of levels,
    built for whichever of the two has the smaller digest and reflected for the other: the same
    levels whichever side is drawn first."""
    if len(mesh.faces) <= DECIMATE_MIN_FACES:
        return [(mesh, 0.0)] * len(fractions)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    key = _lod_key(v, f, fractions)
    if key not in _LODS:
        twin_key = _lod_key(v * _MIRROR_Y, f[:, ::-1], fractions)
        if twin_key < key:
            _LODS[key] = [(_mirrored(m), e) for m, e in _own_lods(_mirrored(mesh), twin_key, fractions)]
        else:
            _LODS[key] = _own_lods(mesh, key, fractions)
    return _LODS[key]


def _own_lods(mesh: trimesh.Trimesh, key: str, fractions: tuple[float, ...]) -> list[tuple[trimesh.Trimesh, float]]:
    """``mesh``'s levels from this process, the user cache, or built (and cached) now."""
    if key in _LODS:
        return _LODS[key]
    path = cache_root() / "lod" / f"{key}.npz"
    out = _read_lods(path)
    if out is None:
        built = _simplified_levels(mesh, fractions)
        arrays = {"error": np.array([e for _, e in built])}
        for i, (m, _) in enumerate(built):  # float32, as drawn: a level read back is the level built
            arrays.update({f"v{i}": np.asarray(m.vertices, np.float32), f"f{i}": np.asarray(m.faces, np.int32),
                           f"n{i}": np.asarray(m.vertex_normals, np.float32)})
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        atomic_write(path, buf.getvalue())  # concurrent workers write identical bytes
        out = _levels(arrays)
    _LODS[key] = out
    return out


_MIRROR_Y = np.array([1.0, -1.0, 1.0])


def _mirrored(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` reflected across its x-z plane with its faces kept outward, exactly as a mirrored
    URDF's ``scale="sx -sy sz"`` loads (negation and reversed winding are exact: twice is the mesh)."""
    return trimesh.Trimesh(np.asarray(mesh.vertices) * _MIRROR_Y, np.asarray(mesh.faces)[:, ::-1],
                           vertex_normals=np.asarray(mesh.vertex_normals) * _MIRROR_Y, process=False)


def _lod_key(vertices: np.ndarray, faces: np.ndarray, fractions: tuple[float, ...]) -> str:
    fast_simplification = _require_fast_simplification()
    h = hashlib.sha256()
    for a in (np.ascontiguousarray(vertices, np.float64), np.ascontiguousarray(faces, np.int64)):
        h.update(a.tobytes())
    h.update(repr((fractions, LOD_CACHE_VERSION, LOD_MIN_FACES, LOD_SILHOUETTE_PX, LOD_SILHOUETTE_MARGIN,
                   DECIMATE_MIN_FACES, DECIMATE_CREASE_DEG, fast_simplification.__version__,
                   trimesh.__version__)).encode())
    return h.hexdigest()[:32]


def _read_lods(path: Path) -> list[tuple[trimesh.Trimesh, float]] | None:
    """The cached levels, or None when absent or unreadable (they are built again and rewritten)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            return _levels(z)
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        return None


def _levels(arrays) -> list[tuple[trimesh.Trimesh, float]]:
    return [(trimesh.Trimesh(arrays[f"v{i}"], arrays[f"f{i}"], vertex_normals=arrays[f"n{i}"], process=False), float(e))
            for i, e in enumerate(arrays["error"])]


def _simplified_levels(mesh: trimesh.Trimesh, fractions: tuple[float, ...]) -> list[tuple[trimesh.Trimesh, float]]:
    out, prev, err = [], mesh, 0.0
    check = None
    for f in fractions:
        target = f * len(mesh.faces)
        if len(mesh.faces) > DECIMATE_MIN_FACES and LOD_MIN_FACES <= target < len(prev.faces):
            simple = decimate_mesh(prev, target / len(prev.faces), min_faces=LOD_MIN_FACES, min_iou=0.0)
            if len(simple.faces) <= 0.75 * len(prev.faces):
                check = check or _lod_silhouettes(mesh)
                prev, err = simple, max(err, check.strip_width(simple))
        out.append((prev, err))
    return out


def decimate_mesh(
    mesh: trimesh.Trimesh,
    fraction: float,
    min_faces: int = DECIMATE_MIN_FACES,
    min_iou: float = DECIMATE_MIN_IOU,
) -> trimesh.Trimesh:
    """Quadric decimation that keeps the silhouette and the shading (creases where the source
    has seams: ``DECIMATE_CREASE_DEG``), or the original mesh when it cannot.

    Policy: meshes with at most ``min_faces`` faces are returned as is; others are welded and
    simplified to ``max(min_faces, fraction * faces)`` faces (gently; more aggressively where the
    gentle pass stops well short of that). The result must keep the
    original's silhouettes (``silhouette_iou`` >= ``min_iou``); otherwise twice the faces are
    tried, and once that is no real saving (>= 75 % of the faces) the original is kept.
    """
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"decimate must be a fraction of faces in (0, 1], got {fraction}")
    fs = _require_fast_simplification()
    n = len(mesh.faces)
    if fraction >= 1.0 or n <= min_faces:
        return mesh
    welded = _welded(mesh)
    seams = len(np.unique(np.asarray(mesh.vertices), axis=0)) < len(mesh.vertices)
    target = max(min_faces, int(round(n * fraction)))
    check = None
    while target < 0.75 * n:
        verts, faces = fs.simplify(welded.vertices, welded.faces, target_count=target, agg=3.0)
        if len(faces) > 1.25 * target:  # the gentle pass stalls on some CAD exports (UR5e: ~95 % of the faces left)
            verts, faces = fs.simplify(welded.vertices, welded.faces, target_count=target, agg=7.0)
        simple = trimesh.Trimesh(verts, faces, process=False)
        if min_iou > 0.0:
            check = check or _Silhouettes(mesh)
        if len(simple.faces) and (check is None or check.iou(simple) >= min_iou):
            simple.update_faces(simple.nondegenerate_faces())  # zero-area faces: no pixel, no normal
            simple.remove_unreferenced_vertices()
            return trimesh.graph.smooth_shade(simple, angle=np.radians(DECIMATE_CREASE_DEG)) if seams else simple
        target *= 2
    return mesh


def build_model(
    urdf_path: Path,
    materials: dict[str, Rgba] | None = None,
    decimate: float | None = None,
    lod: bool = False,
) -> RobotModel:
    """Load the URDF and bake its visual meshes into per-(link, material) parts; ``lod``: each
    part also gets its ``LOD_FRACTIONS`` levels of detail (``LinkPart.lods``)."""
    urdf = load_urdf(urdf_path)
    overrides = _compile_overrides(materials)
    caps = [(re.compile(k[: -len(CAPS)]), _final_material("", None, [(re.compile(""), v)]))
            for k, v in (materials or {}).items() if k.endswith(CAPS)]
    scene = urdf.scene
    graph = scene.graph
    groups: dict[tuple[str, Material], list[list[tuple[np.ndarray, np.ndarray, np.ndarray, float]]]] = {}
    simplified: dict[tuple, trimesh.Trimesh] = {}
    for node in graph.nodes_geometry:
        _, geom_name = graph[node]
        mesh = scene.geometry[geom_name]
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            continue
        link = graph.transforms.parents[node]
        link_from_mesh, _ = graph.get(frame_to=node, frame_from=link)
        material = _final_material(link, _source_material(mesh), overrides)
        if decimate is not None:
            # the same mesh file is often instanced on several links (fingers): simplify it once
            key = (hash(np.asarray(mesh.vertices).tobytes()), hash(np.asarray(mesh.faces).tobytes()))
            if key not in simplified:
                simplified[key] = decimate_mesh(mesh, decimate)
            mesh = simplified[key]
        R, t = link_from_mesh[:3, :3], link_from_mesh[:3, 3]
        cap = next((m for pattern, m in caps if pattern.fullmatch(link)), None)
        stretch = float(np.linalg.norm(R, 2))  # the mesh file's units -> metres (its largest scale)
        versions = [(mesh, 0.0)] + [(m, stretch * err) for m, err in (lod_meshes(mesh) if lod else [])]
        for level, (m, err) in enumerate(versions):
            verts, normals, faces = _baked(m, R, t)
            if cap is not None:
                on = _cap_faces(urdf, link, verts, faces)
                if on.any():
                    _group_level(groups, (link, cap), level, len(versions), (verts, normals, faces[on], err))
                    faces = faces[~on]
            _group_level(groups, (link, material), level, len(versions), (verts, normals, faces, err))
    parts = []
    for (link, material), levels in groups.items():
        (v, n, f, _), *coarser = (_concatenated(items) for items in levels)
        parts.append(LinkPart(link=link, material=material, vertices=v, normals=n, faces=f,
                              lods=tuple(LodLevel(*c) for c in coarser)))
    if not parts:
        raise ValueError(f"{urdf_path}: no visual mesh geometry to render")
    return RobotModel(urdf=urdf, parts=parts)


def _baked(mesh: trimesh.Trimesh, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A mesh's vertices, unit normals and faces in its link's frame (``R``, ``t``: link_from_mesh)."""
    verts = mesh.vertices @ R.T + t
    normals = mesh.vertex_normals @ np.linalg.inv(R)  # inverse-transpose: right under scaling
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    # A mirroring transform flips triangle winding; keep faces outward for back-face culling.
    faces = mesh.faces if np.linalg.det(R) > 0 else mesh.faces[:, ::-1]
    return verts, normals, faces


def _group_level(groups: dict, key: tuple, level: int, n_levels: int, item: tuple) -> None:
    levels = groups.setdefault(key, [[] for _ in range(n_levels)])
    levels[level].append(item)


def _concatenated(items: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]]) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """One part's meshes as one vertex/normal/face array each, and the largest of their errors
    (none: a level where the part has no faces, e.g. a joint cap the simplifier moved)."""
    if not items:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), 0.0
    offsets = np.cumsum([0] + [len(v) for v, _, _, _ in items[:-1]])
    return (np.concatenate([v for v, _, _, _ in items]).astype(np.float32),
            np.concatenate([n for _, n, _, _ in items]).astype(np.float32),
            np.concatenate([f + o for (_, _, f, _), o in zip(items, offsets)]).astype(np.int32),
            max(e for _, _, _, e in items))


def joint_limits(urdf: yourdfpy.URDF) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) per actuated joint; continuous or unlimited joints get [-pi, pi]."""
    lo, hi = [], []
    for name in urdf.actuated_joint_names:
        j = urdf.joint_map[name]
        lim = j.limit
        if j.type == "continuous" or lim is None or lim.lower is None or lim.upper is None:
            lo.append(-np.pi)
            hi.append(np.pi)
        else:
            lo.append(float(lim.lower))
            hi.append(float(lim.upper))
    return np.array(lo), np.array(hi)


def hull_points(model: RobotModel, links: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(link index (m,), link-frame points (m,3)): each part's convex-hull vertices (of all its
    levels of detail), whose projection bounds the part's (a segment in front of the camera
    projects to a segment)."""
    from scipy.spatial import ConvexHull, QhullError

    index, points = [], []
    for p in model.parts:
        v = np.concatenate([np.asarray(x.vertices, np.float64) for x in (p, *p.lods)])
        try:
            v = v[ConvexHull(v).vertices] if len(v) > 64 else v
        except QhullError:  # flat or degenerate: every vertex
            pass
        index.append(np.full(len(v), links.index(p.link)))
        points.append(v)
    return np.concatenate(index), np.concatenate(points)
