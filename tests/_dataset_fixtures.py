"""Small OakInk2, HOI4D and HO-Cap trees in their official layouts, made up (see
_arctic_fixture.py for the shared scene: two hands reaching at a box, a moving camera)."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from _arctic_fixture import H, K, T, W, box_mesh, hand_params, paint, world_to_cam
from _mano_fixture import chain_fk, write_hand_model

SIDES = ("left", "right")
BOX_POSE = np.array([[1.0, 0, 0, 0.0], [0, 1, 0, 0.11], [0, 0, 1, 0.58], [0, 0, 0, 1]])  # world_from_object


def write_mano(d: Path, components: np.ndarray | None = None) -> Path:
    d.mkdir(parents=True, exist_ok=True)
    write_hand_model(d / "MANO_RIGHT.pkl", "right", components=components)
    write_hand_model(d / "MANO_LEFT.pkl", "left", seed=1, components=components)
    return d


def world_joints(side: str, centre: bool = False) -> np.ndarray:
    p = hand_params(side)
    betas = np.tile(p["shape"], (T, 1))
    if not centre:
        return chain_fk(side, betas, p["rot"], p["pose"], p["trans"], add_mean=False)
    j = chain_fk(side, betas, p["rot"], p["pose"], np.zeros_like(p["trans"]), add_mean=False)
    return j - j[:, :1] + p["trans"][:, None]  # manotorch center_idx=0, then + tsl


def to_cam(world: np.ndarray) -> np.ndarray:
    return np.stack([world[t] @ world_to_cam(t)[:3, :3].T + world_to_cam(t)[:3, 3] for t in range(T)])


def _box_cam(t: int, w2c: np.ndarray | None = None) -> np.ndarray:
    mesh, _ = box_mesh()
    M = (world_to_cam(t) if w2c is None else w2c) @ BOX_POSE
    return (mesh.vertices / 1000.0) @ M[:3, :3].T + M[:3, 3]


def _write_box(path: Path) -> None:
    mesh, _ = box_mesh()
    mesh.apply_scale(0.001)
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(path)


# ----------------------------------------------------------------------------- OakInk2

OAK_TOKEN, OAK_EGO, OAK_FIDS = "scene_01__A001++seq__0001__2024-01-01-00-00-00", "cam_ego_01", [4 * t + 10 for t in range(T)]


def write_oakink2(root: Path) -> Path:
    import torch

    cam = {f: world_to_cam(t) for t, f in enumerate(OAK_FIDS)}
    raw = {}
    for t, f in enumerate(OAK_FIDS):
        entry = {}
        for side, pre in (("left", "lh__"), ("right", "rh__")):
            p = hand_params(side)
            aa = np.concatenate([p["rot"][t], p["pose"][t]]).reshape(16, 3)
            xyzw = Rotation.from_rotvec(aa).as_quat()
            wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], 1)
            entry[pre + "pose_coeffs"] = torch.tensor(wxyz[None], dtype=torch.float64)
            entry[pre + "betas"] = torch.tensor(p["shape"][None])
            entry[pre + "tsl"] = torch.tensor(p["trans"][t][None])
        raw[f] = entry
    far = BOX_POSE.copy()
    far[:3, 3] = [0.6, -0.3, 1.5]
    anno = {"cam_def": {OAK_EGO: "egocentric", "cam_top_01": "allocentric_top"}, "cam_selection": ["egocentric"],
            "frame_id_list": OAK_FIDS, "cam_intr": {"egocentric": {f: K for f in OAK_FIDS}},
            "cam_extr": {"egocentric": cam}, "obj_list": ["O_far", "O_box"],
            "obj_transf": {"O_far": {f: far for f in OAK_FIDS}, "O_box": {f: BOX_POSE for f in OAK_FIDS}}, "raw_mano": raw}
    (root / "anno_preview").mkdir(parents=True, exist_ok=True)
    with open(root / "anno_preview" / f"{OAK_TOKEN}.pkl", "wb") as fh:
        pickle.dump(anno, fh)
    for o in ("O_far", "O_box"):
        _write_box(root / "object_raw" / "align_ds" / o / "model.obj")
    kp = np.stack([to_cam(world_joints(s, centre=True)) for s in SIDES], 1)
    d = root / "data" / OAK_TOKEN / OAK_EGO
    d.mkdir(parents=True, exist_ok=True)
    for t, img in enumerate(paint(kp, [_box_cam(t) for t in range(T)], K, None)):
        cv2.imwrite(str(d / f"{OAK_FIDS[t]:06d}.png"), img)
    return root


# ----------------------------------------------------------------------------- HOI4D

HOI_SEQ = "ZY20210800004/H4/C5/N14/S71/s03/T2"  # C5: Bottle


def write_hoi4d(base: Path) -> Path:
    """base/HOI4D_release (root), base/handpose, base/camera_params, base/HOI4D_CAD_Model_for_release."""
    root = base / "HOI4D_release"
    seq = root / HOI_SEQ
    (seq / "align_rgb").mkdir(parents=True, exist_ok=True)
    (seq / "2Dseg" / "mask").mkdir(parents=True, exist_ok=True)
    (seq / "objpose").mkdir(parents=True, exist_ok=True)
    cam_dir = base / "camera_params" / HOI_SEQ.split("/")[0]
    cam_dir.mkdir(parents=True, exist_ok=True)
    np.save(cam_dir / "intrin.npy", K)
    _write_box(base / "HOI4D_CAD_Model_for_release" / "rigid" / "Bottle" / "014.obj")
    hp = base / "handpose" / "refinehandpose_right" / HOI_SEQ
    hp.mkdir(parents=True, exist_ok=True)
    p = hand_params("right")  # HOI4D: the right hand only, parameters in the camera frame
    for t in range(T):
        with open(hp / f"{t}.pickle", "wb") as fh:
            pickle.dump({"poseCoeff": np.concatenate([p["rot"][t], p["pose"][t]]), "beta": p["shape"], "trans": p["trans"][t],
                         "kps2D": np.zeros((21, 2))}, fh)
        r = Rotation.from_matrix(BOX_POSE[:3, :3]).as_euler("XYZ")
        json.dump({"dataList": [{"center": dict(zip("xyz", BOX_POSE[:3, 3].tolist())), "rotation": dict(zip("xyz", r.tolist())),
                                 "dimensions": {"length": 0.1, "width": 0.08, "height": 0.12}}]},
                  open(seq / "objpose" / f"{t}.json", "w"))
    kp = world_joints("right")[:, None]  # the camera frame is HOI4D's only frame
    box = [_box_cam(t, np.eye(4)) for t in range(T)]
    from handedit.sources.hoi4d import voc_palette

    pal = voc_palette()
    for t, img in enumerate(paint(kp, box, K, None)):
        cv2.imwrite(str(seq / "align_rgb" / f"{t:05d}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        labels = np.zeros((H, W), np.uint8)
        obj = paint(np.zeros((1, 1, 21, 3)), [box[t]], K, None)[0]
        labels[(obj == (150, 150, 150)).all(-1)] = 1
        hand = paint(kp[t:t + 1], None, K, None)[0]
        labels[(np.abs(hand.astype(int) - (120, 160, 215)).max(-1) < 3)] = 2
        cv2.imwrite(str(seq / "2Dseg" / "mask" / f"{t:05d}.png"), cv2.cvtColor(pal[labels], cv2.COLOR_RGB2BGR))
    return root


# ----------------------------------------------------------------------------- HO-Cap

HOCAP_SUBJECT, HOCAP_SEQ, HOCAP_SERIAL = "subject_1", "20231025_165502", "hl_0001"
LEFT_MISSING = (3, 4)  # frames whose left-hand pose is all zeros (not annotated)


def pca_basis() -> np.ndarray:
    return np.linalg.qr(np.random.default_rng(11).normal(size=(45, 45)))[0].T


def hocap_params(side: str) -> np.ndarray:
    """(T,51): global axis-angle, 45 PCA coefficients (whose pose is hand_params' pose), translation."""
    p = hand_params(side)
    coeffs = p["pose"] @ np.linalg.inv(pca_basis())
    out = np.concatenate([p["rot"], coeffs, p["trans"]], 1)
    if side == "left":
        out[list(LEFT_MISSING)] = 0.0
    return out


def write_hocap(root: Path) -> Path:
    seq = root / HOCAP_SUBJECT / HOCAP_SEQ
    (seq / HOCAP_SERIAL).mkdir(parents=True, exist_ok=True)
    meta = {"num_frames": T, "object_ids": ["G01_1"], "mano_sides": ["right", "left"], "task_id": 1,
            "realsense": {"serials": [], "width": 640, "height": 480},
            "hololens": {"serials": [HOCAP_SERIAL], "depth_mode": "AHAT", "pv_width": W, "pv_height": H,
                         "depth_width": 512, "depth_height": 512},
            "calibration": {"mano": "subject_1_mano", "extrinsics": "extrinsics_20231014"}}
    (seq / "meta.json").write_text(json.dumps(meta))
    np.save(seq / "poses_m.npy", np.stack([hocap_params("right"), hocap_params("left")]))
    pv = []
    for t in range(T):
        wfc = np.linalg.inv(world_to_cam(t))
        pv.append(np.concatenate([Rotation.from_matrix(wfc[:3, :3]).as_quat(), wfc[:3, 3]]))
    np.save(seq / "poses_pv.npy", np.array(pv))
    obj = np.concatenate([Rotation.from_matrix(BOX_POSE[:3, :3]).as_quat(), BOX_POSE[:3, 3]])
    np.save(seq / "poses_o.npy", np.tile(obj, (1, T, 1)))
    _write_box(root / "models" / "G01_1" / "cleaned_mesh_10000.obj")
    (root / "calibration" / "mano" / "subject_1_mano").mkdir(parents=True, exist_ok=True)
    (root / "calibration" / "mano" / "subject_1_mano" / "mano.json").write_text(json.dumps({"betas": [0.8] + [0.0] * 9}))
    kd = root / "calibration" / "hololens" / HOCAP_SERIAL / "personal_video" / f"1000_{W}_{H}"
    kd.mkdir(parents=True, exist_ok=True)
    B = K.T.copy()
    B[0, 0] = -B[0, 0]  # the toolkit negates fx and transposes when it reads the file
    M = np.eye(4, dtype=np.float32)
    M[:3, :3] = B
    M.astype(np.float32).tofile(kd / "intrinsics.bin")
    kp = np.stack([to_cam(hocap_world_joints(s)) for s in SIDES], 1)
    kp[list(LEFT_MISSING), 0] = 0.0
    for t, img in enumerate(paint(kp, [_box_cam(t) for t in range(T)], K, None)):
        cv2.imwrite(str(seq / HOCAP_SERIAL / f"color_{t:06d}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    return root


def hocap_world_joints(side: str) -> np.ndarray:
    p = hand_params(side)
    betas = np.tile([0.8] + [0.0] * 9, (T, 1))  # the subject's calibrated betas
    return chain_fk(side, betas, p["rot"], p["pose"], p["trans"], add_mean=False)
