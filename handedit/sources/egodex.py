"""EgoDex (Apple, 2025): ``<root>/<task>/<k>.hdf5`` + ``<k>.mp4``, both hands tracked.

Conventions, as Apple's loader reads them (and as ``../shared/data/egodex/README.md``
documents for the shared episodes):

* ``/transforms/camera`` (N,4,4) is camera-to-world (``world_from_camera``), OpenCV axes
  (x right, y down, z forward); ``/transforms/<joint>`` (N,4,4) is joint-to-world, metres.
  A joint in the camera frame is ``inv(T_world_camera) @ T_world_joint``, column 3.
* ``/camera/intrinsic`` (3,3): the 1920x1080 pinhole camera; no distortion. With a working
  resolution (``resize``) it is scaled consistently (``Intrinsics.scaled``).
* ``/confidences/<joint>`` (N,) in [0, 1], optional: a joint is valid where its confidence
  is at least ``min_confidence``. ARKit rates occluded fingertips low but still tracks them
  (median 0.2-0.3 on the shared clips, never below 0.13), so the default 0.1 keeps them;
  raise it to drop guessed joints.
* The world is ARKit's: stationary per recording, gravity-aligned, **Y up**; it has no
  support plane (the table height is not annotated).
* MANO-21 per side from the EgoDex joint names (``_MANO_NAMES``); the arm extras are
  Forearm (the elbow), Arm (the shoulder joint) and Shoulder (the clavicle), see
  ``handedit.keypoints.ARM_JOINTS``.
* Root attributes (task, LLM descriptions, environment, objects, session) become clip
  metadata.

Both hands are tracked in every frame; the hand axis is (left, right).
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Iterator, Literal

import numpy as np
import pydantic

from handedit.camera import Intrinsics
from handedit.keypoints import SIDES
from handedit.sources.base import ClipChunk, ClipInfo, SourceError, take_clips
from handedit.digests import file_sha256
from handedit.sources.decode import VideoReader

NATIVE_SIZE = (1920, 1080)
_FINGERS = ("Index", "Middle", "Ring", "Little")
# MANO-21 order (handedit.keypoints) in EgoDex names, without the side prefix.
_MANO_NAMES: tuple[str, ...] = (
    "Hand",
    "ThumbKnuckle", "ThumbIntermediateBase", "ThumbIntermediateTip", "ThumbTip",
    *(f"{f}Finger{p}" for f in _FINGERS for p in ("Knuckle", "IntermediateBase", "IntermediateTip", "Tip")),
)
_ARM_NAMES: tuple[str, ...] = ("Forearm", "Arm", "Shoulder")  # elbow, shoulder, clavicle
_META_ATTRS = ("task", "llm_description", "llm_description2", "which_llm_description", "llm_type", "llm_verbs",
               "llm_objects", "environment", "object", "session_name", "extra")
WORLD = {"up": [0.0, 1.0, 0.0], "support_plane": None, "origin": "ARKit world: stationary, gravity-aligned, Y up"}


def joint_names(side: str) -> tuple[list[str], list[str]]:
    """(MANO-21 joint names, arm joint names) of one side in EgoDex's HDF5."""
    return [side + n for n in _MANO_NAMES], [side + n for n in _ARM_NAMES]


def _episode_key(stem: str) -> tuple:
    return (0, int(stem), "") if stem.isdigit() else (1, 0, stem)


def parse_frames(text: str) -> tuple[int, int]:
    """'A:B' -> (A, B): frames A (inclusive) to B (exclusive)."""
    m = re.fullmatch(r"\s*(\d+)\s*:\s*(\d+)\s*", text)
    if not m or int(m.group(1)) >= int(m.group(2)):
        raise ValueError(f"frame range {text!r}: use A:B with 0 <= A < B, e.g. 0:48")
    return int(m.group(1)), int(m.group(2))


class EgoDexSpec(pydantic.BaseModel):
    """One EgoDex episode (what workers receive)."""

    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    kind: Literal["egodex"] = "egodex"
    root: Path
    task: str
    episode: str  # the file stem, e.g. "0"
    clip_id: str | None = None  # default egodex-<task>-<episode>[-f<A>-<B>]
    frames: tuple[int, int] | None = None  # window [A, B) of the episode
    resize: tuple[int, int] | None = None  # working resolution (W, H), e.g. (960, 540)
    min_confidence: float = pydantic.Field(0.1, ge=0, le=1)
    seek: Literal["auto", "sequential"] = "auto"

    @property
    def id(self) -> str:
        if self.clip_id:
            return self.clip_id
        window = f"-f{self.frames[0]}-{self.frames[1]}" if self.frames else ""
        return f"egodex-{self.task}-{self.episode}{window}"

    @property
    def hdf5(self) -> Path:
        return Path(self.root) / self.task / f"{self.episode}.hdf5"

    @property
    def mp4(self) -> Path:
        return Path(self.root) / self.task / f"{self.episode}.mp4"

    def files(self) -> list[Path]:
        return [self.hdf5, self.mp4]

    def open(self) -> "EgoDexSource":
        return EgoDexSource(self)


class EgoDexTree(pydantic.BaseModel):
    """A whole EgoDex tree (or some of its tasks): expands to one ``EgoDexSpec`` per episode.

    Episodes are listed task by task (sorted), episode numbers in numeric order, so the
    listing, and the shards cut from it, are stable as a tree grows.
    """

    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    kind: Literal["egodex"] = "egodex"
    root: Path
    tasks: list[str] = pydantic.Field(default_factory=list, description="task folders; empty: every task")
    max_clips: int | None = pydantic.Field(None, ge=1)
    frames: tuple[int, int] | None = None
    resize: tuple[int, int] | None = None
    min_confidence: float = pydantic.Field(0.1, ge=0, le=1)

    @pydantic.field_validator("frames")
    @classmethod
    def _window(cls, v):
        if v is not None and not (0 <= v[0] < v[1]):
            raise ValueError(f"frames {v}: use (A, B) with 0 <= A < B")
        return v

    def groups(self) -> Iterator[tuple[str, list[EgoDexSpec]]]:
        """(task, its episodes) in listing order; ``max_clips`` truncates the listing."""
        root = Path(self.root)
        if not root.is_dir():
            raise SourceError(f"EgoDex root {root} is not a directory; pass --root DIR holding <task>/<k>.hdf5 + <k>.mp4.")
        tasks = self.tasks or sorted(p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
        missing = [t for t in tasks if not (root / t).is_dir()]
        if missing:
            raise SourceError(f"EgoDex root {root} has no task folder(s) {missing}; tasks there: "
                              f"{sorted(p.name for p in root.iterdir() if p.is_dir())}.")
        def listing():
            for task in tasks:
                stems = {p.stem for p in (root / task).iterdir() if p.suffix in (".hdf5", ".mp4") and not p.name.startswith(".")}
                yield task, [EgoDexSpec(root=root, task=task, episode=s, frames=self.frames, resize=self.resize,
                                        min_confidence=self.min_confidence) for s in sorted(stems, key=_episode_key)]

        yield from take_clips(listing(), self.max_clips)

    def clips(self) -> list[EgoDexSpec]:
        return [s for _, group in self.groups() for s in group]


@dataclass(frozen=True)
class _Annotations:
    n_frames: int
    K: np.ndarray  # (3,3) at the native resolution
    world_from_camera: np.ndarray  # (N,4,4)
    joints: np.ndarray  # (N, S, 21, 4, 4) joint-to-world
    conf: np.ndarray  # (N, S, 21) (1 where the file has no confidences)
    arms: np.ndarray  # (N, S, 3, 4, 4)
    arm_conf: np.ndarray  # (N, S, 3)
    attrs: dict


def _attr(v):
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.ndarray):
        return [_attr(x) for x in v.tolist()]
    if isinstance(v, np.generic):
        return v.item()
    return v


def read_annotations(path: Path) -> _Annotations:
    """Everything this adapter needs from one EgoDex HDF5 (small: ~0.5 MB per episode)."""
    import h5py

    fix = "re-download the episode (the HDF5 is truncated or not an EgoDex file)"
    if not path.is_file():
        raise SourceError(f"EgoDex annotation file {path} does not exist; every <k>.mp4 needs its <k>.hdf5 beside it.")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise SourceError(f"EgoDex annotation file {path} could not be opened ({e}); {fix}.") from None
    try:
        with f:
            for name in ("camera/intrinsic", "transforms/camera"):
                if name not in f:
                    raise SourceError(f"EgoDex annotation file {path} has no /{name}; {fix}.")
            K = np.asarray(f["camera/intrinsic"][:], float)
            wfc = np.asarray(f["transforms/camera"][:], float)
            n = len(wfc)
            need = [joint_names(s) for s in SIDES]
            missing = [j for m, a in need for j in (*m, *a) if f"transforms/{j}" not in f]
            if missing:
                raise SourceError(f"EgoDex annotation file {path} lacks {len(missing)} joint(s): {', '.join(missing[:8])}"
                                  f"{' ...' if len(missing) > 8 else ''}; {fix}.")

            def block(names: list[str]) -> tuple[np.ndarray, np.ndarray]:
                T = np.stack([np.asarray(f[f"transforms/{j}"][:], float) for j in names], axis=1)
                c = np.stack([np.asarray(f[f"confidences/{j}"][:], float) if f"confidences/{j}" in f else np.ones(n)
                              for j in names], axis=1)
                if T.shape[0] != n or c.shape[0] != n:
                    raise SourceError(f"EgoDex annotation file {path}: joint arrays have {T.shape[0]} frames, the camera "
                                      f"{n}; {fix}.")
                return T, c

            hands = [block(m) for m, _ in need]
            arms = [block(a) for _, a in need]
            attrs = {k: _attr(f.attrs[k]) for k in _META_ATTRS if k in f.attrs}
    except SourceError:
        raise
    except Exception as e:  # truncated chunks, bad dtypes, ...
        raise SourceError(f"EgoDex annotation file {path} could not be read ({type(e).__name__}: {e}); {fix}.") from None
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0:
        raise SourceError(f"EgoDex annotation file {path}: /camera/intrinsic is not a valid 3x3 camera matrix; {fix}.")
    return _Annotations(n, K, wfc, np.stack([h[0] for h in hands], 1), np.stack([h[1] for h in hands], 1),
                        np.stack([a[0] for a in arms], 1), np.stack([a[1] for a in arms], 1), attrs)


def _in_camera(world_from_camera: np.ndarray, world_from_joint: np.ndarray) -> np.ndarray:
    """(n, ..., 3) joint positions in the camera frame: inv(T_wc) @ T_wj, column 3."""
    cam_from_world = np.linalg.inv(world_from_camera)  # (n,4,4)
    p = world_from_joint[..., :3, 3]
    extra = p.ndim - 2
    R = cam_from_world[:, :3, :3].reshape(len(p), *([1] * extra), 3, 3)
    t = cam_from_world[:, :3, 3].reshape(len(p), *([1] * extra), 3)
    return np.einsum("...ij,...j->...i", R, p) + t


class EgoDexSource:
    """One EgoDex episode (or a window of it) at the working resolution."""

    def __init__(self, spec: EgoDexSpec):
        self.spec = spec
        self.ann = read_annotations(spec.hdf5)
        if not spec.mp4.is_file():
            raise SourceError(f"EgoDex video {spec.mp4} does not exist; every <k>.hdf5 needs its <k>.mp4 beside it "
                              f"(re-download the episode).")
        self.video = VideoReader(spec.mp4, seek=spec.seek, resize=spec.resize, what="EgoDex video")
        if self.video.probe.n_frames != self.ann.n_frames:
            raise SourceError(f"EgoDex episode {spec.hdf5.parent / spec.episode}: the video has {self.video.probe.n_frames} "
                              f"frames, the HDF5 {self.ann.n_frames}; EgoDex pairs them frame by frame, so the files do not "
                              f"belong together (re-download both).")
        a, b = spec.frames or (0, self.ann.n_frames)
        if b > self.ann.n_frames:
            raise SourceError(f"EgoDex episode {spec.hdf5}: frames {a}:{b} exceed its {self.ann.n_frames} frames; "
                              f"use --frames A:B within 0:{self.ann.n_frames}.")
        self.window = (a, b)

    @cached_property
    def intrinsics(self) -> Intrinsics:
        p = self.video.probe
        return Intrinsics.from_K(self.ann.K, p.width, p.height).scaled(*self.video.size)

    def info(self) -> ClipInfo:
        s, p = self.spec, self.video.probe
        h5, mp4 = file_sha256(s.hdf5), file_sha256(s.mp4)
        w, h = self.video.size
        ident = {"hdf5": h5, "mp4": mp4, "window": self.window, "size": [w, h], "min_confidence": s.min_confidence}
        return ClipInfo(
            clip_id=s.id, n_frames=self.window[1] - self.window[0], height=h, width=w, fps=p.fps or 30.0,
            intrinsics=self.intrinsics, has_keypoints=True, has_object=False,
            fingerprint=hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest(),
            hands=SIDES, world=WORLD, has_arm=True,
            meta={"dataset": "egodex", "task_folder": s.task, "episode": s.episode, **self.ann.attrs,
                  "hdf5": str(s.hdf5), "mp4": str(s.mp4), "hdf5_sha256": h5, "mp4_sha256": mp4,
                  "frames": list(self.window), "min_confidence": s.min_confidence, "codec": p.codec,
                  "seek": "pts-verified" if self.video.seekable else "sequential",
                  "resolution": {"file": [p.width, p.height], "working": [w, h]}},
        )

    def object_mesh(self) -> None:
        return None

    def read(self, start: int, stop: int) -> ClipChunk:
        a, b = self.window
        if not (0 <= start <= stop <= b - a):
            raise SourceError(f"read({start}, {stop}) outside the {b - a} frames of {self.spec.id}.")
        lo, hi = a + start, a + stop
        frames, frame_ok = self.video.read(lo, hi)
        ann, thr = self.ann, self.spec.min_confidence
        wfc = ann.world_from_camera[lo:hi]
        kp = _in_camera(wfc, ann.joints[lo:hi])
        arm = _in_camera(wfc, ann.arms[lo:hi])
        valid = (ann.conf[lo:hi] >= thr) & np.isfinite(kp).all(-1)
        arm_valid = (ann.arm_conf[lo:hi] >= thr) & np.isfinite(arm).all(-1)
        kp[~valid], arm[~arm_valid] = 0.0, 0.0
        return ClipChunk(start=start, frames=frames, world_from_camera=wfc, keypoints=kp.astype(np.float32),
                         keypoints_valid=valid, frame_ok=frame_ok, arm_keypoints=arm.astype(np.float32), arm_valid=arm_valid)
