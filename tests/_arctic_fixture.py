"""A small ARCTIC tree in the official layout (``raw_seqs``, ``meta``, ``images``), made up.

One subject ``s01``, one sequence ``box_grab_01``: both hands reaching forward at a box (a
two-part object: its top part opens by the articulation angle), seen by a moving
egocentric camera with an 8-coefficient distortion; images painted from the distorted
projection (skin-coloured skeletons, grey box, a textured table), starting at
``IOI_OFFSET``, each carrying its own image index in a marker block.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from _mano_fixture import chain_fk, write_hand_model

SUBJECT, SEQ, OBJECT = "s01", "box_grab_01", "box"
T, W, H, IOI_OFFSET = 16, 384, 288, 3
K = np.array([[330.0, 0, 191.5], [0, 330.0, 143.5], [0, 0, 1]])
DIST8 = np.array([-0.12, 0.03, 0.0005, -0.0004, 0.0, 0.01, -0.004, 0.0])
MARK = (slice(0, 30), slice(164, 220))  # rows, cols of the frame-index marker (top centre)
MARK_CORE = (slice(12, 18), slice(186, 198))  # inside it wherever undistortion moves it
BONES = [(p, j) for j, p in enumerate((-1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19)) if p >= 0]


def box_mesh():
    """A 10 x 8 x 12 cm box (mm), vertices of its upper half flagged as the top part."""
    import trimesh

    m = trimesh.creation.box(extents=(100.0, 80.0, 120.0))
    m = m.subdivide().subdivide()
    return m, (m.vertices[:, 2] > 30.0)


def world_to_cam(t: int) -> np.ndarray:
    R = Rotation.from_rotvec([0.02 * np.sin(t / 3), 0.01 * t, 0.0]).as_matrix()
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, [0.004 * t, -0.002 * t, 0.0]
    return M


def hand_params(side: str) -> dict:
    """World-frame MANO parameters: fingers forward (+z), palm down, a slow finger curl."""
    base = Rotation.from_matrix(np.column_stack([[0, 0, 1], [-1, 0, 0], [0, -1, 0]]))  # hand x, y, z in the world
    tilt = Rotation.from_rotvec([np.deg2rad(-25), 0, 0])
    rot = np.tile((tilt * base).as_rotvec(), (T, 1))
    curl = np.linspace(0.0, 0.5, T)[:, None]
    pose = np.zeros((T, 45))
    pose[:, 2::3] = curl * (0.3 if side == "right" else 0.2)
    x = 0.09 if side == "right" else -0.09
    trans = np.stack([np.full(T, x), np.full(T, 0.06), np.linspace(0.30, 0.32, T)], 1)
    return {"rot": rot, "pose": pose, "trans": trans, "shape": np.array([0.8 if side == "right" else -0.6, *[0.0] * 9]),
            "fitting_err": np.zeros(T)}


def object_params() -> np.ndarray:
    """(T,7): articulation (rad), axis-angle, translation (mm)."""
    p = np.zeros((T, 7))
    p[:, 0] = np.linspace(0.0, 0.6, T)
    p[:, 1:4] = [0.1, 0.2, 0.0]
    p[:, 4:] = [0.0, 110.0, 580.0]
    return p


def expected_keypoints() -> np.ndarray:
    """(T,2,21,3) camera-frame joints (left, right), computed with a plain kinematic chain."""
    out = []
    for side in ("left", "right"):
        p = hand_params(side)
        world = chain_fk(side, np.tile(p["shape"], (T, 1)), p["rot"], p["pose"], p["trans"], add_mean=True)
        out.append(np.stack([world[t] @ world_to_cam(t)[:3, :3].T + world_to_cam(t)[:3, 3] for t in range(T)]))
    return np.stack(out, 1)


def _project(points_cam: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    uv, _ = cv2.projectPoints(points_cam.reshape(-1, 1, 3).astype(float), np.zeros(3), np.zeros(3), K,
                              np.zeros(5) if dist is None else dist)
    return uv.reshape(-1, 2)


def paint(kp: np.ndarray, objects: list, K: np.ndarray, dist: np.ndarray | None, size=(W, H), seed: int = 5) -> list:
    """BGR frames: a textured table, each frame's object (camera-frame vertices) as a grey
    silhouette, each hand (kp (T,S,21,3), camera frame) as a skin-coloured skeleton and palm;
    projected with ``dist`` (None: pinhole)."""
    w, h = size
    rng = np.random.default_rng(seed)
    table = cv2.GaussianBlur(rng.integers(0, 255, (h, w, 3)).astype(np.uint8), (0, 0), 3)
    table = (0.35 * table + [60, 90, 120]).clip(0, 255).astype(np.uint8)  # BGR brownish wood
    out = []
    for t in range(len(kp)):
        img = table.copy()
        if objects is not None and objects[t] is not None:
            hull = cv2.convexHull(_project(objects[t], K, dist).astype(np.float32)).astype(np.int32)
            cv2.fillConvexPoly(img, hull, (150, 150, 150), cv2.LINE_AA)
        for s in range(kp.shape[1]):
            if not np.isfinite(kp[t, s]).all() or not kp[t, s].any():
                continue
            uv = _project(kp[t, s], K, dist)
            palm = cv2.convexHull(uv[[0, 1, 2, 5, 9, 13, 17]].astype(np.float32)).astype(np.int32)
            cv2.fillConvexPoly(img, palm, (120, 160, 215), cv2.LINE_AA)
            for a, b in BONES:
                cv2.line(img, tuple(np.round(uv[a]).astype(int)), tuple(np.round(uv[b]).astype(int)), (120, 160, 215), 9,
                         cv2.LINE_AA)
        out.append(img)
    return out


def write_tree(root: Path, mano_dir: Path) -> Path:
    mano_dir.mkdir(parents=True, exist_ok=True)
    write_hand_model(mano_dir / "MANO_RIGHT.pkl", "right")
    write_hand_model(mano_dir / "MANO_LEFT.pkl", "left", seed=1)
    seqs = root / "raw_seqs" / SUBJECT
    seqs.mkdir(parents=True, exist_ok=True)
    mano = {s: hand_params(s) for s in ("right", "left")}
    np.save(seqs / f"{SEQ}.mano.npy", mano, allow_pickle=True)
    w2c = np.stack([world_to_cam(t) for t in range(T)])
    np.save(seqs / f"{SEQ}.egocam.dist.npy", {"R_k_cam_np": w2c[:, :3, :3], "T_k_cam_np": w2c[:, :3, 3:], "intrinsics": K,
                                              "dist8": DIST8, "R0": np.eye(3), "T0": np.zeros((3, 1))}, allow_pickle=True)
    obj = object_params()
    np.save(seqs / f"{SEQ}.object.npy", obj)
    meta = root / "meta"
    (meta / "object_vtemplates" / OBJECT).mkdir(parents=True, exist_ok=True)
    mesh, top = box_mesh()
    mesh.export(meta / "object_vtemplates" / OBJECT / "mesh.obj")
    (meta / "object_vtemplates" / OBJECT / "parts.json").write_text(json.dumps(top.astype(int).tolist()))
    (meta / "misc.json").write_text(json.dumps({SUBJECT: {"ioi_offset": IOI_OFFSET, "gender": "female",
                                                          "image_size": [[W, H]] * 9}}))
    images = root / "images" / SUBJECT / SEQ / "0"
    images.mkdir(parents=True, exist_ok=True)
    kp = expected_keypoints()
    objects = []
    for t in range(T):
        verts = mesh.vertices.copy()
        verts[top] = verts[top] @ Rotation.from_rotvec([0, 0, obj[t, 0]]).as_matrix().T
        wfo = np.eye(4)
        wfo[:3, :3], wfo[:3, 3] = Rotation.from_rotvec(obj[t, 1:4]).as_matrix(), obj[t, 4:] / 1000.0
        objects.append((verts / 1000.0) @ (w2c[t] @ wfo)[:3, :3].T + (w2c[t] @ wfo)[:3, 3])
    for t, img in enumerate(paint(kp, objects, K, DIST8)):
        img[MARK] = 8 * (t + IOI_OFFSET)
        cv2.imwrite(str(images / f"{t + IOI_OFFSET:05d}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    return root
