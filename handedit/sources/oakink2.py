"""OakInk2 (Zhan et al., CVPR 2024): bimanual object manipulation, its egocentric camera.

Layout (the release, as ``oakink2_toolkit.dataset`` reads it):

* ``anno_preview/<seq_token>.pkl`` (``seq_key`` with "/" -> "++"): ``cam_def`` (serial ->
  "egocentric" | "allocentric_*"), ``frame_id_list`` (the image frames, as **mocap** frame
  ids: mocap runs at 120 fps, images at 30), ``cam_intr[cam][fid]`` (3x3),
  ``cam_extr[cam][fid]`` (4x4 **world-to-camera**), ``obj_list``, ``obj_transf[obj][fid]``
  (4x4 world-from-object), ``raw_mano[fid]`` with ``rh__``/``lh__`` ``pose_coeffs`` (16
  quaternions, **w, x, y, z**), ``betas`` (10), ``tsl`` (3). Its values are torch tensors,
  so reading it needs torch (CPU is enough).
* MANO as manotorch builds it: quaternion joint rotations, ``flat_hand_mean=True``, no PCA,
  ``center_idx=0`` (the wrist at the origin) then ``+ tsl``; metres, world frame.
* ``data/<seq_token>/<egocentric serial>/<fid:06d>.png`` (or ``.jpg``): the frames.
* ``object_raw/align_ds/<obj_id>/<one .obj or .ply>``: object meshes (metres).

Clip frame ``i`` is image frame ``frame_id_list[i]``. The clip's object is the one of
``obj_list`` nearest the hands over the clip (the one being manipulated); its mask is its
mesh's silhouette.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np

from handedit.hands.mano import TIPS_MANOPTH, ManoConvention, quat_wxyz_to_axis_angle
from handedit.keypoints import SIDES
from handedit.sources.base import SourceError
from handedit.sources.mano_model import mano_digest, mano_model
from handedit.sources.sequence import ManoSpecBase, ManoTreeBase, Sequence, SequenceSource, load_mesh, load_pickle
from handedit.vision.object_depth import rasterize_depth

CONVENTION = ManoConvention(pca=False, flat_hand_mean=True, tips=TIPS_MANOPTH, center_joint=0)  # manotorch
EGO = "egocentric"
_PREFIX = {"left": "lh__", "right": "rh__"}


class Oakink2Spec(ManoSpecBase):
    kind: Literal["oakink2"] = "oakink2"
    root: Path  # the dataset prefix: anno_preview/, data/, object_raw/
    sequence: str  # seq_token, e.g. scene_01__A001++seq__0123__2023-09-01-10-00-00

    @property
    def id(self) -> str:
        return self.clip_id or "oakink2-" + self.sequence.replace("++", "-")

    def open(self) -> SequenceSource:
        return SequenceSource(load_sequence(self), self.frames, self.resize, "OakInk2")


class Oakink2Tree(ManoTreeBase):
    """Every ``anno_preview/*.pkl`` (sorted), one group (``tasks``: sequence tokens)."""

    kind: Literal["oakink2"] = "oakink2"

    def _spec(self, **kw) -> Oakink2Spec:
        return Oakink2Spec(root=self.root, **kw)

    def _groups(self):
        anno = Path(self.root) / "anno_preview"
        if not anno.is_dir():
            raise SourceError(f"OakInk2 root {self.root} has no anno_preview/ folder; pass --root the dataset prefix "
                              f"(anno_preview/, data/, object_raw/).")
        yield "oakink2", [{"sequence": t} for t in self.tasks or sorted(p.stem for p in anno.glob("*.pkl"))]


def _np(x) -> np.ndarray:
    return np.asarray(x.detach().cpu().numpy() if hasattr(x, "detach") else x, np.float64)


def load_sequence(spec: Oakink2Spec) -> Sequence:
    root = Path(spec.root)
    anno_p = root / "anno_preview" / f"{spec.sequence}.pkl"
    fix = "download anno_preview/ of the release (reading it needs torch: pip install torch)"
    anno = load_pickle(anno_p, "OakInk2 annotation", fix)
    try:
        serial = {v: k for k, v in anno["cam_def"].items()}[EGO]
        fids = [int(f) for f in anno["frame_id_list"]]
        K = _np(next(iter(anno["cam_intr"][EGO].values())))
        extr = np.stack([_np(anno["cam_extr"][EGO][f]) for f in fids])
        raw = [anno["raw_mano"][f] for f in fids]
        objs = list(anno["obj_list"])
        transf = {o: np.stack([_np(anno["obj_transf"][o][f]) for f in fids]) for o in objs}
    except (KeyError, TypeError, ValueError, StopIteration) as exc:
        raise SourceError(f"OakInk2 annotation {anno_p}: {type(exc).__name__} {exc}: not the anno_preview layout "
                          f"(cam_def with an egocentric camera, frame_id_list, cam_intr, cam_extr, raw_mano, obj_transf).") from None
    T = len(fids)
    kp = np.zeros((T, 2, 21, 3))
    for s_i, side in enumerate(SIDES):
        pre = _PREFIX[side]
        q = np.stack([_np(r[pre + "pose_coeffs"]).reshape(16, 4) for r in raw])
        betas = np.stack([_np(r[pre + "betas"]).reshape(10) for r in raw])
        tsl = np.stack([_np(r[pre + "tsl"]).reshape(3) for r in raw])
        aa = quat_wxyz_to_axis_angle(q)
        world = mano_model(spec.mano_dir, side).forward(betas, aa[:, 0], aa[:, 1:].reshape(T, 45), tsl, CONVENTION).joints
        kp[:, s_i] = np.einsum("tij,tkj->tki", extr[:, :3, :3], world) + extr[:, None, :3, 3]
    data = root / "data" / spec.sequence / serial
    ext = ".png" if any(data.glob("*.png")) else ".jpg"
    images = [data / f"{f:06d}{ext}" for f in fids]
    obj = pose = mesh = None
    if objs:  # the object nearest the hands
        wrists = kp[:, :, 0]
        cam_obj = {o: extr @ transf[o] for o in objs}
        obj = min(objs, key=lambda o: float(np.linalg.norm(wrists - cam_obj[o][:, None, :3, 3], axis=-1).mean()))
        pose = cam_obj[obj]
        d = root / "object_raw" / "align_ds" / obj
        files = sorted(p for p in d.glob("*") if p.suffix in (".obj", ".ply")) if d.is_dir() else []
        if len(files) != 1:
            raise SourceError(f"OakInk2 object {obj}: expected one .obj/.ply in {d}, found {len(files)}; download object_raw/.")
        mesh = load_mesh(files[0], "OakInk2 object mesh")

    def depth(k: int, intr, size) -> np.ndarray:
        return rasterize_depth(*mesh, pose[k], intr)

    return Sequence(
        clip_id=spec.id, keypoints=kp, valid=np.ones((T, 2), bool), hands=SIDES, images=images, K=K, fps=30.0,
        world_from_camera=np.linalg.inv(extr), object_pose=pose, object_mesh=mesh,
        object_depth=depth if mesh is not None else None, files=[anno_p],
        meta={"dataset": "oakink2", "sequence": spec.sequence, "camera": serial, "object": obj,
              "mocap_frames": [fids[0], fids[-1]], "mano": mano_digest(spec.mano_dir),
              "mano_convention": "manotorch, quaternions (w, x, y, z), flat_hand_mean=True, centred on the wrist + tsl"})
