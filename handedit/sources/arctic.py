"""ARCTIC (Fan et al., CVPR 2023): bimanual manipulation of articulated objects, egocentric view 0.

Layout (the official release, ``arctic_data/data``), as its loader reads it:

* ``raw_seqs/<subject>/<seq>.mano.npy``: a pickled dict ``{"right"|"left": {"rot" (T,3),
  "pose" (T,45), "trans" (T,3), "shape" (10,), "fitting_err"}}``; MANO axis-angle, **not**
  flat-hand-mean (``flat_hand_mean=False``, smplx's MANO layer), metres, world (Vicon) frame.
* ``raw_seqs/<subject>/<seq>.egocam.dist.npy``: ``{"R_k_cam_np" (T,3,3), "T_k_cam_np" (T,3,1),
  "intrinsics" (3,3), "dist8" (8,)}``: world-to-egocentric-camera per frame, metres; the ego
  images are *distorted* with OpenCV's 8-coefficient rational model.
* ``raw_seqs/<subject>/<seq>.object.npy`` (T,7): articulation angle (rad), axis-angle
  rotation, translation in **millimetres**; ``meta/object_vtemplates/<object>/mesh.obj``
  (millimetres) with ``parts.json`` (per vertex: 1 = top part, rotated about the object's z
  axis by the articulation angle, before the global pose).
* ``meta/misc.json``: per subject ``ioi_offset``: image ``k`` shows mocap frame
  ``k - ioi_offset``; ``images/<subject>/<seq>/0/<k:05d>.jpg``.

What this adapter does with it: MANO-21 per side from the user's MANO model
(``handedit.hands.mano``, ARCTIC's convention below), moved into the egocentric camera;
frames **undistorted** (``cv2.undistort`` with ``dist8``), so the pinhole ``intrinsics``
project the camera-frame joints onto the pixels; the object's mask per frame from its
articulated mesh; its pose and mesh (rigid, at the clip's median articulation: the contact
QC's approximation of a two-part object). Frame ``i`` of a clip is mocap frame ``i`` (+ the
window start); a mocap frame without its image is an undecodable frame.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import numpy as np

from handedit.hands.mano import TIPS_SMPLX, ManoConvention, rodrigues
from handedit.keypoints import SIDES
from handedit.sources.base import SourceError
from handedit.sources.mano_model import mano_digest, mano_model
from handedit.sources.sequence import ManoSpecBase, ManoTreeBase, Sequence, SequenceSource, load_mesh, load_pickle
from handedit.vision.object_depth import rasterize_depth

CONVENTION = ManoConvention(pca=False, flat_hand_mean=False, tips=TIPS_SMPLX)  # smplx MANO, as ARCTIC builds it
EGO_VIEW = 0


class ArcticSpec(ManoSpecBase):
    """One ARCTIC sequence (what workers receive)."""

    kind: Literal["arctic"] = "arctic"
    root: Path  # the folder holding raw_seqs/, meta/, images/
    subject: str
    sequence: str

    @property
    def id(self) -> str:
        window = f"-f{self.frames[0]}-{self.frames[1]}" if self.frames else ""
        return self.clip_id or f"arctic-{self.subject}-{self.sequence}{window}"

    def files(self) -> list[Path]:
        base = Path(self.root) / "raw_seqs" / self.subject / self.sequence
        return [Path(f"{base}.mano.npy"), Path(f"{base}.egocam.dist.npy"), Path(f"{base}.object.npy")]

    def open(self) -> SequenceSource:
        return SequenceSource(load_sequence(self), self.frames, self.resize, "ARCTIC")


class ArcticTree(ManoTreeBase):
    """Every sequence under ``raw_seqs/`` (subjects sorted, sequences sorted), one group per subject."""

    kind: Literal["arctic"] = "arctic"

    def _spec(self, **kw) -> ArcticSpec:
        return ArcticSpec(root=self.root, **kw)

    def _groups(self):
        seqs = Path(self.root) / "raw_seqs"
        if not seqs.is_dir():
            raise SourceError(f"ARCTIC root {self.root} has no raw_seqs/ folder; pass --root the folder holding "
                              f"raw_seqs/, meta/ and images/ (arctic_data/data).")
        for sub in self.tasks or sorted(p.name for p in seqs.iterdir() if p.is_dir()):
            names = sorted(p.name[: -len(".mano.npy")] for p in (seqs / sub).glob("*.mano.npy"))
            yield sub, [{"subject": sub, "sequence": n} for n in names]


def load_sequence(spec: ArcticSpec) -> Sequence:
    """Everything of one sequence but its pixels (see the module doc for the conventions)."""
    root, base = Path(spec.root), Path(spec.root) / "raw_seqs" / spec.subject / spec.sequence
    fix = "download the sequence's raw_seqs files (mano, egocam.dist, object) from the official release"
    mano = load_pickle(Path(f"{base}.mano.npy"), "ARCTIC MANO file", fix)
    ego = load_pickle(Path(f"{base}.egocam.dist.npy"), "ARCTIC egocentric camera file", fix)
    obj = np.asarray(load_pickle(Path(f"{base}.object.npy"), "ARCTIC object file", fix), np.float64)
    misc_p = root / "meta" / "misc.json"
    try:
        ioi = int(json.loads(misc_p.read_text())[spec.subject]["ioi_offset"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SourceError(f"ARCTIC {misc_p}: no ioi_offset for subject {spec.subject} ({exc}); download meta/ "
                          f"from the official release.") from None
    try:
        R, t = np.asarray(ego["R_k_cam_np"], float), np.asarray(ego["T_k_cam_np"], float).reshape(-1, 3)
        K, dist = np.asarray(ego["intrinsics"], float), np.asarray(ego["dist8"], float).reshape(-1)
        params = {s: {k: np.asarray(mano[s][k], float) for k in ("rot", "pose", "trans", "shape")} for s in SIDES}
    except (KeyError, TypeError, ValueError) as exc:
        raise SourceError(f"ARCTIC {base}: {type(exc).__name__} {exc} reading the MANO / egocam files: not the "
                          f"layout this adapter reads (raw_seqs of the official release).") from None
    T = len(R)
    lens = {"egocam": T, "object": len(obj), **{f"mano.{s}": len(params[s]["rot"]) for s in SIDES}}
    if len(set(lens.values())) != 1 or obj.shape[1:] != (7,) or dist.shape != (8,) or K.shape != (3, 3):
        raise SourceError(f"ARCTIC {base}: the files disagree ({lens} frames, object {obj.shape}, dist8 "
                          f"{dist.shape}, K {K.shape}); re-download the sequence.")
    w2c = np.tile(np.eye(4), (T, 1, 1))
    w2c[:, :3, :3], w2c[:, :3, 3] = R, t
    joints = []
    for side in SIDES:
        p = params[side]
        world = mano_model(spec.mano_dir, side).forward(p["shape"], p["rot"], p["pose"], p["trans"], CONVENTION).joints
        joints.append(np.einsum("tij,tkj->tki", R, world) + t[:, None])
    name = spec.sequence.split("_")[0]
    verts_mm, faces, top = _object_template(root / "meta" / "object_vtemplates" / name)
    a, b = spec.frames or (0, T)
    rest = float(np.median(obj[a:b, 0]))  # the contact QC's rigid mesh: the window's median articulation

    def articulated(angle: float) -> np.ndarray:
        v = verts_mm.copy()
        v[top] = v[top] @ rodrigues(np.array([[0.0, 0.0, angle]]))[0].T
        return v / 1000.0

    wfo = np.tile(np.eye(4), (T, 1, 1))
    wfo[:, :3, :3], wfo[:, :3, 3] = rodrigues(obj[:, 1:4]), obj[:, 4:] / 1000.0
    pose = w2c @ wfo

    def depth(k: int, intr, size) -> np.ndarray:  # each frame's own articulation
        return rasterize_depth(articulated(obj[k, 0]), faces, pose[k], intr)

    images = [root / "images" / spec.subject / spec.sequence / str(EGO_VIEW) / f"{k + ioi:05d}.jpg" for k in range(T)]
    return Sequence(
        clip_id=spec.id, keypoints=np.stack(joints, 1), valid=np.ones((T, 2), bool), hands=SIDES, images=images, K=K,
        fps=30.0, world_from_camera=np.linalg.inv(w2c), dist=dist, object_pose=pose,
        object_mesh=(articulated(rest), faces), object_depth=depth, files=spec.files(),
        meta={"dataset": "arctic", "subject": spec.subject, "sequence": spec.sequence, "object": name, "ioi_offset": ioi,
              "mano": mano_digest(spec.mano_dir),
              "mano_convention": "smplx MANO, axis-angle, flat_hand_mean=False, smplx fingertip vertices",
              "distortion": "frames undistorted with dist8 (OpenCV rational model); intrinsics are the pinhole K",
              "object_mesh": "rigid at the window's median articulation angle (contact QC); masks and depth use each frame's"})


def _object_template(d: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices mm, faces, top-part flags) of an ARCTIC object template."""
    verts, faces = load_mesh(d / "mesh.obj", "ARCTIC object template")
    try:
        top = np.asarray(json.loads((d / "parts.json").read_text()), bool)
    except (OSError, ValueError) as exc:
        raise SourceError(f"ARCTIC object template {d / 'parts.json'} could not be read ({exc}); download "
                          f"meta/object_vtemplates from the official release.") from None
    if len(top) != len(verts):
        raise SourceError(f"ARCTIC {d}: parts.json has {len(top)} flags for {len(verts)} vertices.")
    return verts, faces, top
