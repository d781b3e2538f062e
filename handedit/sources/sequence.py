"""What the MANO-based dataset adapters share: a clip whose frames are image files and whose
annotations are already in memory (keypoints per side in the camera frame, camera, object).

An adapter (ARCTIC, OakInk2, HOI4D, HO-Cap) only reads its own layout into a ``Sequence``;
``SequenceSource`` then serves windows of it at the working resolution: frames (undistorted
when the dataset's images are distorted), keypoints, object masks and poses.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np
import pydantic

from handedit.camera import Intrinsics
from handedit.digests import file_digest, file_sha256
from handedit.images import read_rgb
from handedit.sources.base import ClipChunk, ClipInfo, SourceError, take_clips


@dataclass
class Sequence:
    clip_id: str
    keypoints: np.ndarray  # (T,S,21,3) camera frame, metres, MANO-21
    valid: np.ndarray  # (T,S) bool: the side is annotated in that frame
    hands: tuple[str, ...]  # SIDES order
    images: list[Path]  # (T,) one image file per frame (empty when ``video`` holds them)
    K: np.ndarray  # (3,3) at the images' native size
    fps: float
    world_from_camera: np.ndarray | None = None  # (T,4,4)
    dist: np.ndarray | None = None  # OpenCV distortion of the images (frames are undistorted with it)
    object_pose: np.ndarray | None = None  # (T,4,4) camera_from_object
    object_mesh: tuple[np.ndarray, np.ndarray] | None = None  # (V,3) object frame metres, (F,3)
    object_mask: Callable[[int, Intrinsics, tuple[int, int]], np.ndarray] | None = None  # frame k -> (H,W) bool
    # frame k -> (H,W) float32 depth of the object's surface (0 off it); the mask, when not
    # given, is where it is > 0
    object_depth: Callable[[int, Intrinsics, tuple[int, int]], np.ndarray] | None = None
    files: list[Path] = field(default_factory=list)  # annotation files (their digests identify the clip)
    meta: dict = field(default_factory=dict)
    video: Path | None = None  # the frames as one video file instead of image files


class SequenceSource:
    """A window [a, b) of a ``Sequence`` at the working resolution ``resize`` (W, H)."""

    def __init__(self, seq: Sequence, frames: tuple[int, int] | None, resize: tuple[int, int] | None, what: str):
        self.seq, self.what = seq, what
        T = len(seq.keypoints)
        a, b = frames or (0, T)
        if not (0 <= a < b <= T):
            raise SourceError(f"{what} {seq.clip_id}: frames {a}:{b} outside its {T} frames; use --frames A:B within 0:{T}.")
        self.window = (a, b)
        self.resize = tuple(resize) if resize else None

    @cached_property
    def video(self):
        from handedit.sources.decode import VideoReader

        return VideoReader(self.seq.video, what=f"{self.what} video") if self.seq.video else None

    @cached_property
    def native_size(self) -> tuple[int, int]:
        if self.video is not None:
            return self.video.size
        for k in range(*self.window):
            img = cv2.imread(str(self.seq.images[k]), cv2.IMREAD_UNCHANGED)
            if img is not None:
                return img.shape[1], img.shape[0]
        raise SourceError(f"{self.what} {self.seq.clip_id}: no image of frames {self.window[0]}:{self.window[1]} could be "
                          f"read (first expected: {self.seq.images[self.window[0]]}); download the sequence's images.")

    @cached_property
    def size(self) -> tuple[int, int]:
        return self.resize or self.native_size

    @cached_property
    def intrinsics(self) -> Intrinsics:
        return Intrinsics.from_K(self.seq.K, *self.native_size).scaled(*self.size)

    def info(self) -> ClipInfo:
        s = self.seq
        digests = {p.name: file_sha256(p) for p in s.files}
        ident = {"files": digests, "window": self.window, "size": list(self.size), "meta": s.meta}
        a, b = self.window  # the pixels, by content: the window's image files (or the video)
        if s.images:
            ident["images"] = hashlib.sha256("".join(file_digest(p) for p in s.images[a:b]).encode()).hexdigest()
        if s.video is not None and s.video not in s.files:
            ident["video"] = file_digest(s.video)
        if s.object_mesh is not None:  # the mesh as loaded (contact QC and occlusion depth read it), by content
            ident["object_mesh"] = hashlib.sha256(b"".join(np.ascontiguousarray(a).tobytes() for a in s.object_mesh)).hexdigest()
        w, h = self.size
        return ClipInfo(
            clip_id=s.clip_id, n_frames=self.window[1] - self.window[0], height=h, width=w, fps=s.fps,
            intrinsics=self.intrinsics, has_keypoints=True, has_object=s.object_pose is not None,
            fingerprint=hashlib.sha256(json.dumps(ident, sort_keys=True, default=str).encode()).hexdigest(), hands=s.hands,
            meta={**s.meta, "frames": list(self.window), "files": digests,
                  "resolution": {"file": list(self.native_size), "working": [w, h]}},
        )

    def object_mesh(self):
        return self.seq.object_mesh

    def read(self, start: int, stop: int) -> ClipChunk:
        a, b = self.window
        if not (0 <= start <= stop <= b - a):
            raise SourceError(f"read({start}, {stop}) outside the {b - a} frames of {self.seq.clip_id}.")
        s, n = self.seq, stop - start
        w, h = self.size
        frames = np.zeros((n, h, w, 3), np.uint8)
        ok = np.zeros(n, bool)
        decoded = self.video.read(a + start, a + stop) if self.video is not None else None
        for i in range(n):
            if decoded is not None:
                img = decoded[0][i] if decoded[1][i] else None
            else:
                img = read_rgb(s.images[a + start + i], expect=self.native_size)
            if img is None:
                continue
            if s.dist is not None:
                img = cv2.undistort(img, s.K, s.dist)
            frames[i] = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA) if (w, h) != self.native_size else img
            ok[i] = True
        lo, hi = a + start, a + stop
        kp = s.keypoints[lo:hi].astype(np.float32)
        valid = np.repeat(s.valid[lo:hi, :, None], kp.shape[2], 2) & np.isfinite(kp).all(-1)
        kp[~valid] = 0.0
        wfc = s.world_from_camera[lo:hi] if s.world_from_camera is not None else np.tile(np.eye(4), (n, 1, 1))
        chunk = ClipChunk(start=start, frames=frames, world_from_camera=wfc, keypoints=kp, keypoints_valid=valid, frame_ok=ok)
        if s.object_pose is not None:
            chunk.object_pose = s.object_pose[lo:hi].copy()
            if s.object_depth is not None:
                chunk.object_depth = np.stack([s.object_depth(k, self.intrinsics, (w, h)) for k in range(lo, hi)])
            if s.object_mask is not None:
                chunk.object_mask = np.stack([s.object_mask(k, self.intrinsics, (w, h)) for k in range(lo, hi)])
            else:
                chunk.object_mask = chunk.object_depth > 0 if chunk.object_depth is not None else np.zeros((n, h, w), bool)
        return chunk


def load_pickle(path: Path, what: str, fix: str):
    """A dataset's pickle or .npy dict, or one SourceError naming the file and the fix."""
    import pickle

    if not path.is_file():
        raise SourceError(f"{what} {path} does not exist; {fix}.")
    try:
        if path.suffix == ".npy":
            d = np.load(path, allow_pickle=True)
            return d.item() if d.dtype == object and d.shape == () else d
        with open(path, "rb") as f:
            return pickle.load(f, encoding="latin1")
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the same fix
        raise SourceError(f"{what} {path} could not be read ({type(exc).__name__}: {exc}); {fix}.") from None


def load_mesh(path: Path, what: str) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    try:
        m = trimesh.load(path, process=False, force="mesh")
    except Exception as exc:  # noqa: BLE001
        raise SourceError(f"{what} {path} could not be read ({type(exc).__name__}: {exc}); download the object models.") from None
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


class ManoSpecBase(pydantic.BaseModel):
    """Fields every MANO-based clip spec has (each adds ``kind`` and where its clip is)."""

    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    mano_dir: Path | None = None  # MANO_RIGHT.pkl + MANO_LEFT.pkl (default $HANDEDIT_MANO_DIR)
    frames: tuple[int, int] | None = None  # window [A, B) of the sequence
    resize: tuple[int, int] | None = None  # working resolution (W, H)
    clip_id: str | None = None


class ManoTreeBase(pydantic.BaseModel):
    """Fields and listing every MANO-based tree spec shares: ``_groups`` yields (group name,
    the names of its sequences) in a stable order; ``groups`` makes the specs and applies
    ``max_clips``."""

    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    root: Path
    tasks: list[str] = pydantic.Field(default_factory=list, description="groups to take (subjects, cameras, "
                                      "sequence tokens); empty: all")
    max_clips: int | None = pydantic.Field(None, ge=1)
    frames: tuple[int, int] | None = None
    resize: tuple[int, int] | None = None
    mano_dir: Path | None = None

    def _groups(self) -> Iterator[tuple[str, list[dict]]]:
        raise NotImplementedError

    def _spec(self, **where):
        raise NotImplementedError

    def groups(self):
        common = {"mano_dir": self.mano_dir, "frames": self.frames, "resize": self.resize}
        yield from take_clips(((name, [self._spec(**common, **w) for w in wheres]) for name, wheres in self._groups()),
                              self.max_clips)

    def clips(self) -> list:
        return [s for _, g in self.groups() for s in g]
