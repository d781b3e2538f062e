"""HO-Cap (Wang et al., 2024): hands and objects from multi-view capture, its HoloLens view.

Layout of the current toolkit (IRVLUTD/HO-Cap, ``hocap/loaders/sequence_loader.py``):

* ``<root>/subject_<i>/<date>/meta.json``: ``num_frames``, ``object_ids``, ``mano_sides``,
  ``hololens`` (``serials``, ``pv_width``, ``pv_height``), ``calibration.mano`` (the subject id);
* ``.../poses_m.npy`` (2, T, 51): per side (0 right, 1 left) 48 MANO values (3 global
  axis-angle + **45 PCA** coefficients) + 3 translation, world frame, metres;
* ``<root>/calibration/mano/<subject id>/mano.json``: the subject's ``betas``;
* MANO as the toolkit builds it: manopth, ``use_pca=True``, 45 components,
  ``flat_hand_mean=True``, ``center_idx=0`` (which manopth applies only without a
  translation, so never to these poses); joints = MANO joints + translation;
* ``.../poses_pv.npy`` (T, 7): the HoloLens PV camera's pose in the world (quaternion x, y,
  z, w, then translation; OpenCV axes): the egocentric view;
* ``<root>/calibration/hololens/<serial>/personal_video/1000_<W>_<H>/intrinsics.bin``:
  float32 4x4, transposed, with fx negated (as the toolkit reads it);
* ``.../poses_o.npy`` (n_objects, T, 7): objects in the world (same pose format);
  ``<root>/models/<object id>/cleaned_mesh_10000.obj`` (metres);
* the HoloLens frames: ``.../<hololens serial>/color_<k:06d>.jpg``, named like the
  RealSense cameras' (``image_pattern`` if a copy differs).

A side absent from ``mano_sides``, or a frame whose pose is all zeros or all -1, is invalid.
The older toolkit (per-frame ``pose_m`` files, DexYCB style) is not read; its sequences are
rejected naming ``meta.json`` and ``poses_m.npy``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import numpy as np

from handedit.hands.mano import TIPS_MANOPTH, ManoConvention
from handedit.keypoints import SIDES
from handedit.sources.base import SourceError
from handedit.sources.mano_model import mano_digest, mano_model
from handedit.sources.sequence import ManoSpecBase, ManoTreeBase, Sequence, SequenceSource, load_mesh
from handedit.vision.object_depth import rasterize_depth

CONVENTION = ManoConvention(pca=True, flat_hand_mean=True, tips=TIPS_MANOPTH)  # manopth, 45 PCA components
_SIDE_INDEX = {"right": 0, "left": 1}  # poses_m.npy's first axis


class HocapSpec(ManoSpecBase):
    kind: Literal["hocap"] = "hocap"
    root: Path  # holding calibration/, models/, subject_*/
    subject: str  # subject_1
    sequence: str  # 20231025_165502
    image_pattern: str = "{serial}/color_{frame:06d}.jpg"

    @property
    def id(self) -> str:
        return self.clip_id or f"hocap-{self.subject}-{self.sequence}"

    def open(self) -> SequenceSource:
        return SequenceSource(load_sequence(self), self.frames, self.resize, "HO-Cap")


class HocapTree(ManoTreeBase):
    """Every ``subject_*/<date>/meta.json`` (sorted), one group per subject (``tasks``: subjects)."""

    kind: Literal["hocap"] = "hocap"

    def _spec(self, **kw) -> HocapSpec:
        return HocapSpec(root=self.root, **kw)

    def _groups(self):
        root = Path(self.root)
        if not (root / "calibration").is_dir():
            raise SourceError(f"HO-Cap root {root} has no calibration/ folder; pass --root the toolkit's data folder "
                              f"(calibration/, models/, subject_*/).")
        for sub in self.tasks or sorted(p.name for p in root.glob("subject_*") if p.is_dir()):
            yield sub, [{"subject": sub, "sequence": p.parent.name} for p in sorted((root / sub).glob("*/meta.json"))]


def quat_pose(q: np.ndarray) -> np.ndarray:
    """(...,7) quaternion x, y, z, w + translation -> (...,4,4) (the toolkit's quat_to_mat)."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(q, np.float64)
    out = np.tile(np.eye(4), (*q.shape[:-1], 1, 1))
    out[..., :3, :3] = Rotation.from_quat(q[..., :4].reshape(-1, 4)).as_matrix().reshape(*q.shape[:-1], 3, 3)
    out[..., :3, 3] = q[..., 4:]
    return out


def load_sequence(spec: HocapSpec) -> Sequence:
    root = Path(spec.root)
    seq = root / spec.subject / spec.sequence
    meta_p, pm_p, pv_p = seq / "meta.json", seq / "poses_m.npy", seq / "poses_pv.npy"
    for p in (meta_p, pm_p, pv_p):
        if not p.is_file():
            raise SourceError(f"HO-Cap sequence {seq} has no {p.name}: this adapter reads the current toolkit's layout "
                              f"(meta.json, poses_m.npy, poses_pv.npy, poses_o.npy); download the sequence again.")
    try:
        meta = json.loads(meta_p.read_text())
        serial = meta["hololens"]["serials"][0]
        W, H = int(meta["hololens"]["pv_width"]), int(meta["hololens"]["pv_height"])
        sides = list(meta["mano_sides"])
        subject_id = meta["calibration"]["mano"]
        object_ids = list(meta.get("object_ids") or [])
        T = int(meta["num_frames"])
    except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
        raise SourceError(f"HO-Cap {meta_p}: {type(exc).__name__} {exc}; expected num_frames, mano_sides, object_ids, "
                          f"hololens.serials/pv_width/pv_height, calibration.mano.") from None
    poses_m, poses_pv = np.load(pm_p), np.load(pv_p)
    if poses_m.shape[1:] != (T, 51) or poses_pv.shape != (T, 7):
        raise SourceError(f"HO-Cap {seq}: poses_m.npy {poses_m.shape} / poses_pv.npy {poses_pv.shape} do not match "
                          f"num_frames {T} (expected (2, {T}, 51) and ({T}, 7)).")
    beta_p = root / "calibration" / "mano" / subject_id / "mano.json"
    try:
        betas = np.asarray(json.loads(beta_p.read_text())["betas"], float)
    except (OSError, ValueError, KeyError) as exc:
        raise SourceError(f"HO-Cap MANO calibration {beta_p} could not be read ({exc}); download calibration/.") from None
    K_p = root / "calibration" / "hololens" / serial / "personal_video" / f"1000_{W}_{H}" / "intrinsics.bin"
    try:
        K = np.fromfile(K_p, dtype=np.float32).reshape(4, 4)[:3, :3].astype(np.float64)
    except (OSError, ValueError) as exc:
        raise SourceError(f"HO-Cap HoloLens intrinsics {K_p} could not be read ({exc}); download calibration/.") from None
    K[0, 0] = -K[0, 0]
    K = K.T
    wfc = quat_pose(poses_pv)
    cfw = np.linalg.inv(wfc)
    kp = np.zeros((T, 2, 21, 3))
    valid = np.zeros((T, 2), bool)
    for s_i, side in enumerate(SIDES):
        if side not in sides:
            continue
        p = poses_m[_SIDE_INDEX[side]]
        ok = ~((p == 0).all(-1) | (p == -1).all(-1))
        world = mano_model(spec.mano_dir, side).forward(betas, p[:, :3], p[:, 3:48], p[:, 48:51], CONVENTION).joints
        kp[:, s_i] = np.einsum("tij,tkj->tki", cfw[:, :3, :3], world) + cfw[:, None, :3, 3]
        valid[:, s_i] = ok
    hands = tuple(s for s in SIDES if s in sides)
    keep = [SIDES.index(h) for h in hands]
    pose = mesh = None
    obj = None
    po_p = seq / "poses_o.npy"
    if object_ids and po_p.is_file():
        cam_obj = cfw[None] @ quat_pose(np.load(po_p))  # (n,T,4,4)
        wrists = kp[:, keep, 0]
        j = int(np.argmin([np.linalg.norm(wrists - c[:, None, :3, 3], axis=-1).mean() for c in cam_obj]))
        obj, pose = object_ids[j], cam_obj[j]
        mesh = load_mesh(root / "models" / obj / "cleaned_mesh_10000.obj", "HO-Cap object mesh")

    def depth(k: int, intr, size) -> np.ndarray:
        return rasterize_depth(*mesh, pose[k], intr)

    images = [seq / spec.image_pattern.format(serial=serial, frame=k) for k in range(T)]
    return Sequence(
        clip_id=spec.id, keypoints=kp[:, keep], valid=valid[:, keep], hands=hands, images=images, K=K, fps=30.0,
        world_from_camera=wfc, object_pose=pose, object_mesh=mesh, object_depth=depth if mesh is not None else None,
        files=[meta_p, pm_p, pv_p, beta_p, K_p],
        meta={"dataset": "hocap", "subject": spec.subject, "sequence": spec.sequence, "hololens": serial, "object": obj,
              "mano": mano_digest(spec.mano_dir),
              "mano_convention": "manopth, 45 PCA components, flat_hand_mean=True, subject betas; + translation"})
