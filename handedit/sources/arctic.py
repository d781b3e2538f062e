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

import hashlib
import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Iterator, Literal

import cv2
import numpy as np
import pydantic

from handedit.camera import Intrinsics
from handedit.digests import file_sha256
from handedit.hands.mano import TIPS_SMPLX, ManoConvention, ManoError, ManoModel, rodrigues
from handedit.keypoints import SIDES
from handedit.sources.base import ClipChunk, ClipInfo, SourceError
from handedit.vision.object_depth import rasterize_depth

CONVENTION = ManoConvention(pca=False, flat_hand_mean=False, tips=TIPS_SMPLX)  # smplx MANO, as ARCTIC builds it
EGO_VIEW = 0


class ArcticSpec(pydantic.BaseModel):
    """One ARCTIC sequence (what workers receive)."""

    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    kind: Literal["arctic"] = "arctic"
    root: Path  # the folder holding raw_seqs/, meta/, images/
    subject: str
    sequence: str
    mano_dir: Path | None = None  # MANO_RIGHT.pkl + MANO_LEFT.pkl (default $HANDEDIT_MANO_DIR)
    frames: tuple[int, int] | None = None
    resize: tuple[int, int] | None = None
    clip_id: str | None = None

    @property
    def id(self) -> str:
        window = f"-f{self.frames[0]}-{self.frames[1]}" if self.frames else ""
        return self.clip_id or f"arctic-{self.subject}-{self.sequence}{window}"

    def files(self) -> list[Path]:
        base = Path(self.root) / "raw_seqs" / self.subject / self.sequence
        return [Path(f"{base}.mano.npy"), Path(f"{base}.egocam.dist.npy"), Path(f"{base}.object.npy")]

    def open(self) -> "ArcticSource":
        return ArcticSource(self)


class ArcticTree(pydantic.BaseModel):
    """Every sequence under ``raw_seqs/`` (subjects sorted, sequences sorted), one group per subject."""

    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    kind: Literal["arctic"] = "arctic"
    root: Path
    tasks: list[str] = pydantic.Field(default_factory=list, description="subjects (e.g. s01); empty: every subject")
    max_clips: int | None = pydantic.Field(None, ge=1)
    frames: tuple[int, int] | None = None
    resize: tuple[int, int] | None = None
    mano_dir: Path | None = None

    def groups(self) -> Iterator[tuple[str, list[ArcticSpec]]]:
        seqs = Path(self.root) / "raw_seqs"
        if not seqs.is_dir():
            raise SourceError(f"ARCTIC root {self.root} has no raw_seqs/ folder; pass --root the folder holding "
                              f"raw_seqs/, meta/ and images/ (arctic_data/data).")
        subjects = self.tasks or sorted(p.name for p in seqs.iterdir() if p.is_dir())
        left = self.max_clips
        for sub in subjects:
            names = sorted(p.name[: -len(".mano.npy")] for p in (seqs / sub).glob("*.mano.npy"))
            specs = [ArcticSpec(root=self.root, subject=sub, sequence=n, mano_dir=self.mano_dir, frames=self.frames,
                                resize=self.resize) for n in names]
            if left is not None:
                specs, left = specs[:left], left - min(left, len(specs))
            if specs:
                yield sub, specs
            if left == 0:
                return

    def clips(self) -> list[ArcticSpec]:
        return [s for _, g in self.groups() for s in g]


def _load_dict(path: Path, what: str) -> dict:
    if not path.is_file():
        raise SourceError(f"ARCTIC {what} {path} does not exist; download the sequence's raw_seqs files (mano, egocam.dist, "
                          f"object) from the official release.")
    try:
        d = np.load(path, allow_pickle=True)
        return d.item() if d.dtype == object and d.shape == () else d
    except Exception as exc:  # noqa: BLE001
        raise SourceError(f"ARCTIC {what} {path} could not be read ({type(exc).__name__}: {exc}); re-download it.") from None


@dataclass(frozen=True)
class _Sequence:
    joints: np.ndarray  # (T,S,21,3) camera frame
    world2cam: np.ndarray  # (T,4,4)
    K: np.ndarray
    dist: np.ndarray  # (8,)
    obj_params: np.ndarray  # (T,7)
    obj_name: str
    ioi_offset: int


class ArcticSource:
    def __init__(self, spec: ArcticSpec):
        self.spec = spec
        self.root = Path(spec.root)
        self.base = self.root / "raw_seqs" / spec.subject / spec.sequence
        self.seq = self._load()
        T = len(self.seq.joints)
        a, b = spec.frames or (0, T)
        if not (0 <= a < b <= T):
            raise SourceError(f"ARCTIC {spec.id}: frames {a}:{b} outside its {T} mocap frames; use --frames A:B within 0:{T}.")
        self.window = (a, b)

    # -- annotations ------------------------------------------------------------------
    def _load(self) -> _Sequence:
        mano = _load_dict(Path(f"{self.base}.mano.npy"), "MANO file")
        ego = _load_dict(Path(f"{self.base}.egocam.dist.npy"), "egocentric camera file")
        obj = np.asarray(_load_dict(Path(f"{self.base}.object.npy"), "object file"), np.float64)
        misc_p = self.root / "meta" / "misc.json"
        try:
            misc = json.loads(misc_p.read_text())[self.spec.subject]
            ioi = int(misc["ioi_offset"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise SourceError(f"ARCTIC {misc_p}: no ioi_offset for subject {self.spec.subject} ({exc}); download meta/ "
                              f"from the official release.") from None
        try:
            R, t = np.asarray(ego["R_k_cam_np"], float), np.asarray(ego["T_k_cam_np"], float).reshape(-1, 3)
            K, dist = np.asarray(ego["intrinsics"], float), np.asarray(ego["dist8"], float).reshape(-1)
            params = {s: {k: np.asarray(mano[s][k], float) for k in ("rot", "pose", "trans", "shape")} for s in SIDES}
        except (KeyError, TypeError, ValueError) as exc:
            raise SourceError(f"ARCTIC {self.base}: {type(exc).__name__} {exc} reading the MANO / egocam files: not the "
                              f"layout this adapter reads (raw_seqs of the official release).") from None
        T = len(R)
        lens = {"egocam": T, "object": len(obj), **{f"mano.{s}": len(params[s]["rot"]) for s in SIDES}}
        if len(set(lens.values())) != 1 or obj.shape[1:] != (7,) or dist.shape != (8,) or K.shape != (3, 3):
            raise SourceError(f"ARCTIC {self.base}: the files disagree ({lens} frames, object {obj.shape}, dist8 "
                              f"{dist.shape}, K {K.shape}); re-download the sequence.")
        w2c = np.tile(np.eye(4), (T, 1, 1))
        w2c[:, :3, :3], w2c[:, :3, 3] = R, t
        joints = []
        for side in SIDES:
            try:
                model = ManoModel.find(self.spec.mano_dir, side)
            except ManoError as exc:
                raise SourceError(str(exc)) from None
            p = params[side]
            world = model.forward(p["shape"], p["rot"], p["pose"], p["trans"], CONVENTION).joints
            joints.append(np.einsum("tij,tkj->tki", R, world) + t[:, None])
        return _Sequence(np.stack(joints, 1), w2c, K, dist, obj, self.spec.sequence.split("_")[0], ioi)

    def _image(self, mocap: int) -> Path:
        return self.root / "images" / self.spec.subject / self.spec.sequence / str(EGO_VIEW) / f"{mocap + self.seq.ioi_offset:05d}.jpg"

    @cached_property
    def _native_size(self) -> tuple[int, int]:
        for k in range(*self.window):
            img = cv2.imread(str(self._image(k)), cv2.IMREAD_UNCHANGED)
            if img is not None:
                return img.shape[1], img.shape[0]
        raise SourceError(f"ARCTIC {self.spec.id}: no egocentric image found (first expected: {self._image(self.window[0])}); "
                          f"download images/ (view 0) of the sequence.")

    @cached_property
    def size(self) -> tuple[int, int]:
        return tuple(self.spec.resize) if self.spec.resize else self._native_size

    @cached_property
    def intrinsics(self) -> Intrinsics:
        w, h = self._native_size
        return Intrinsics.from_K(self.seq.K, w, h).scaled(*self.size)

    @cached_property
    def _object(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vertices mm, faces, top-part flags) of the object template."""
        import trimesh

        d = self.root / "meta" / "object_vtemplates" / self.seq.obj_name
        try:
            mesh = trimesh.load(d / "mesh.obj", process=False, force="mesh")
            parts = np.asarray(json.loads((d / "parts.json").read_text()), bool)
        except (OSError, ValueError) as exc:
            raise SourceError(f"ARCTIC object template {d} (mesh.obj, parts.json) could not be read ({exc}); download "
                              f"meta/object_vtemplates from the official release.") from None
        if len(parts) != len(mesh.vertices):
            raise SourceError(f"ARCTIC {d}: parts.json has {len(parts)} flags for {len(mesh.vertices)} vertices.")
        return np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64), parts

    def _object_in_camera(self, k: int, angle: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(camera_from_object 4x4, object vertices in the object frame, metres) at mocap frame k;
        the top part articulated by ``angle`` (default: frame k's)."""
        v, _, top = self._object
        arti, aa, trans = self.seq.obj_params[k, 0], self.seq.obj_params[k, 1:4], self.seq.obj_params[k, 4:]
        v = v.copy()
        v[top] = v[top] @ rodrigues(np.array([[0.0, 0.0, arti if angle is None else angle]]))[0].T
        wfo = np.eye(4)
        wfo[:3, :3], wfo[:3, 3] = rodrigues(aa[None])[0], trans / 1000.0
        return self.seq.world2cam[k] @ wfo, v / 1000.0

    # -- Source interface -------------------------------------------------------------
    def info(self) -> ClipInfo:
        files = self.spec.files()
        digests = {p.name: file_sha256(p) for p in files}
        ident = {"files": digests, "window": self.window, "size": list(self.size),
                 "mano": ManoModel.find(self.spec.mano_dir, "right").v_template[:4].round(9).tolist()}
        w, h = self.size
        return ClipInfo(
            clip_id=self.spec.id, n_frames=self.window[1] - self.window[0], height=h, width=w, fps=30.0,
            intrinsics=self.intrinsics, has_keypoints=True, has_object=True,
            fingerprint=hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest(), hands=SIDES,
            meta={"dataset": "arctic", "subject": self.spec.subject, "sequence": self.spec.sequence,
                  "object": self.seq.obj_name, "ioi_offset": self.seq.ioi_offset, "frames": list(self.window),
                  "mano_convention": "smplx MANO, axis-angle, flat_hand_mean=False, smplx fingertip vertices",
                  "distortion": "frames undistorted with dist8 (OpenCV rational model); intrinsics are the pinhole K",
                  "object_mesh": "rigid at the clip's median articulation angle (contact QC); masks use each frame's",
                  "files": digests},
        )

    def object_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        a, b = self.window
        _, verts = self._object_in_camera(a, angle=float(np.median(self.seq.obj_params[a:b, 0])))
        return verts, self._object[1]

    def read(self, start: int, stop: int) -> ClipChunk:
        a, b = self.window
        if not (0 <= start <= stop <= b - a):
            raise SourceError(f"read({start}, {stop}) outside the {b - a} frames of {self.spec.id}.")
        w, h = self.size
        nw, nh = self._native_size
        n = stop - start
        frames = np.zeros((n, h, w, 3), np.uint8)
        ok = np.zeros(n, bool)
        masks = np.zeros((n, h, w), bool)
        poses = np.tile(np.eye(4), (n, 1, 1))
        K, faces = self.seq.K, self._object[1]
        for i in range(n):
            k = a + start + i
            img = cv2.imread(str(self._image(k)), cv2.IMREAD_COLOR)
            if img is not None and img.shape[:2] == (nh, nw):
                und = cv2.undistort(img, K, self.seq.dist)
                frames[i] = cv2.cvtColor(cv2.resize(und, (w, h), interpolation=cv2.INTER_AREA) if (w, h) != (nw, nh) else und,
                                         cv2.COLOR_BGR2RGB)
                ok[i] = True
            poses[i], verts = self._object_in_camera(k)  # the mask: this frame's articulation
            masks[i] = rasterize_depth(verts, faces, poses[i], self.intrinsics) > 0
        kp = self.seq.joints[a + start:a + stop].astype(np.float32)
        valid = np.isfinite(kp).all(-1)
        kp[~valid] = 0.0
        wfc = np.linalg.inv(self.seq.world2cam[a + start:a + stop])
        return ClipChunk(start=start, frames=frames, world_from_camera=wfc, keypoints=kp, keypoints_valid=valid, frame_ok=ok,
                         object_mask=masks, object_pose=poses)
