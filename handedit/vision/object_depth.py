"""Depth of the manipulated object, rasterized from its mesh and pose, for occlusion.

Why: the composite must hide the robot exactly where the object is in front of it. The
object mask alone cannot say who is in front (a finger wraps *around* a cup), but with
the object's mesh and its per-frame pose (the synthetic source has both; an object
tracker such as FoundationPose provides them for real video) the object's depth per
pixel is exact, and ``composite`` then lets the nearer surface win per pixel.

A small z-buffer rasterizer in numpy (perspective-correct: 1/z is interpolated linearly
in screen space): object meshes have tens to a few thousand faces, so no GL context is
needed and it runs anywhere a task runs. Pixel (i, j) is sampled at (j + 0.5, i + 0.5),
the GL renderer's convention (pixel j covers [j, j + 1)): the silhouette then matches the
synthetic source's rendered object mask exactly (IoU 1.00 on visible pixels, vs 0.93 when
sampling at integer coordinates), and the robot render uses the same convention.
"""

from __future__ import annotations

import numpy as np

from handedit.camera import Intrinsics

Z_NEAR = 1e-3  # metres: faces with a vertex closer than this are skipped
_EPS = 1e-5  # pixels


def _runs(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(owner, k) for ``counts[i]`` items per owner i: owner index and 0-based rank within it."""
    owner = np.repeat(np.arange(len(counts)), counts)
    return owner, np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)


def rasterize_depth(vertices: np.ndarray, faces: np.ndarray, camera_from_object: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """(H,W) float32 camera-z depth in metres of the nearest object surface; 0 = no object.

    Vectorised over faces (a Python loop per face cost ~30 ms per frame, per embodiment):
    each face's rows are cut to the span its edges cross, every
    candidate pixel of every face is tested with the barycentric inside test at its centre,
    and ``np.minimum.at`` keeps the nearest surface."""
    H, W = intr.height, intr.width
    T = np.asarray(camera_from_object, np.float64)
    if not np.isfinite(T).all():
        return np.zeros((H, W), np.float32)
    v = np.asarray(vertices, np.float64) @ T[:3, :3].T + T[:3, 3]
    z = v[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([intr.fx * v[:, 0] / z + intr.cx, intr.fy * v[:, 1] / z + intr.cy], -1)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    f = f[(z[f] > Z_NEAR).all(1)]
    p = uv[f]  # (F,3,2) screen corners
    lo, hi = np.floor(p.min(1) - 0.5).astype(np.int64), np.ceil(p.max(1)).astype(np.int64)
    x0, y0 = np.maximum(lo[:, 0], 0), np.maximum(lo[:, 1], 0)
    x1, y1 = np.minimum(hi[:, 0], W - 1), np.minimum(hi[:, 1], H - 1)
    (ax, ay), (bx, by), (cx, cy) = p[:, 0].T, p[:, 1].T, p[:, 2].T
    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    keep = (x0 <= x1) & (y0 <= y1) & (np.abs(area) >= 1e-12)
    f, p, x0, y0, x1, y1, area = f[keep], p[keep], x0[keep], y0[keep], x1[keep], y1[keep], area[keep]
    # rows: the x range where the row's centre line crosses the face's edges (EPS px wider
    # than exact, far more than the inside test's 1e-9 barycentric tolerance can reach)
    face, k = _runs(y1 - y0 + 1)
    yr = y0[face] + k
    yc = yr + 0.5
    xl, xr = np.full(len(face), np.inf), np.full(len(face), -np.inf)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        (px, py), (qx, qy) = p[face, i].T, p[face, j].T
        on = (np.minimum(py, qy) - _EPS <= yc) & (yc <= np.maximum(py, qy) + _EPS)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.clip((yc - py) / (qy - py), 0.0, 1.0)
        x = np.where(qy != py, px + t * (qx - px), px)
        flat = qy == py  # a horizontal edge on the centre line: both its ends
        xl = np.where(on, np.minimum(xl, np.where(flat, np.minimum(px, qx), x)), xl)
        xr = np.where(on, np.maximum(xr, np.where(flat, np.maximum(px, qx), x)), xr)
    crossed = np.isfinite(xl)
    xl, xr = np.where(crossed, xl, 0.0), np.where(crossed, xr, -1.0)
    sl = np.maximum(np.ceil(xl - 0.5 - _EPS), x0[face]).astype(np.int64)  # pixel centres xi + 0.5 in [xl, xr]
    sr = np.minimum(np.floor(xr - 0.5 + _EPS), x1[face]).astype(np.int64)
    row, k = _runs(np.maximum(sr - sl + 1, 0))
    face, xi, yi = face[row], sl[row] + k, yr[row]
    xs, ys = xi + 0.5, yi + 0.5
    # the barycentric inside test and perspective-correct depth at each candidate's centre
    q = np.concatenate([p.reshape(-1, 6), area[:, None], 1.0 / z[f]], 1)[face]
    ax, ay, bx, by, cx, cy, A = q[:, 0], q[:, 1], q[:, 2], q[:, 3], q[:, 4], q[:, 5], q[:, 6]
    w0 = ((bx - xs) * (cy - ys) - (by - ys) * (cx - xs)) / A
    w1 = ((cx - xs) * (ay - ys) - (cy - ys) * (ax - xs)) / A
    w2 = 1.0 - w0 - w1
    inside = (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9)
    inv_z = w0 * q[:, 7] + w1 * q[:, 8] + w2 * q[:, 9]
    depth = np.full(H * W, np.inf, np.float64)
    np.minimum.at(depth, (yi * W + xi)[inside], 1.0 / np.maximum(inv_z[inside], 1e-12))
    depth[~np.isfinite(depth)] = 0.0
    return depth.reshape(H, W).astype(np.float32)


def object_depth(vertices: np.ndarray, faces: np.ndarray, camera_from_object: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """(n,H,W) float32 object depth for a chunk of poses (n,4,4); 0 where no object."""
    poses = np.asarray(camera_from_object, np.float64).reshape(-1, 4, 4)
    out = np.zeros((len(poses), intr.height, intr.width), np.float32)
    for i, T in enumerate(poses):
        out[i] = rasterize_depth(vertices, faces, T, intr)
    return out


def object_occluder(object_mask: np.ndarray | None, depth: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(occluder mask, occluder depth) for ``composite`` from the source's object mask and
    depth (ingest's ``object_depth``; None or all 0 where the source knows no geometry:
    then the mask alone, and no depth).

    With depth, the occluder is the object's whole silhouette (where the human hand hid
    it, the robot may now be behind it) united with the source's object mask.
    """
    if depth is None or not depth.any():
        return object_mask, None
    mask = depth > 0
    if object_mask is not None:
        mask |= np.asarray(object_mask, bool)
    return mask, depth
