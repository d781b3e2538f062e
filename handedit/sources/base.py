"""The source interface: a clip is frames + camera + hand keypoints (+ object, metadata).

A source is described by a small, picklable spec (pydantic) so that Dask workers can
open it themselves and read any frame range: ingest then runs chunk-parallel, and the
driver never ships pixels. Dataset adapters (EgoDex, ARCTIC, OakInk2, HOI4D, HO-Cap)
implement the same two calls; the MANO-parameter datasets convert to 21 keypoints in
their adapter, so every stage downstream sees one representation (see
``handedit.keypoints`` for the joint order and the hand axis).

Hands: a clip tracks ``ClipInfo.hands`` (e.g. ``("left", "right")`` for EgoDex, one side
for a one-hand video); every per-hand array has a hand axis in that order.

World: ``ClipInfo.world`` says what the per-frame ``world_from_camera`` poses mean:
None (no world: identity poses), or ``{"up": [x, y, z]}`` (world up, in world
coordinates) with an optional ``"support_plane": [n, d]`` (the table, n . p + d = height).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Protocol, runtime_checkable

import numpy as np
import pydantic

from handedit.camera import Intrinsics
from handedit.keypoints import ARM_JOINTS, N_JOINTS


class IngestConfig(pydantic.BaseModel):
    """The ingest stage's parameters (none yet); its VERSION is the source-to-store contract's."""

    VERSION: ClassVar[int] = 2  # 2: the object's depth (from the source's mesh and pose)
    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")


class SourceError(ValueError):
    """Bad source input; the message names the file and the fix."""


@dataclass(frozen=True)
class ClipInfo:
    clip_id: str
    n_frames: int
    height: int
    width: int
    fps: float
    intrinsics: Intrinsics
    has_keypoints: bool
    has_object: bool
    fingerprint: str  # content identity of the source (file hash, or generator seed + params)
    meta: dict = field(default_factory=dict)
    ground_truth: tuple[str, ...] = ()  # names of ClipChunk.gt arrays this source provides
    hands: tuple[str, ...] = ("right",)  # sides tracked, in hand-axis order (keypoints.SIDES order)
    world: dict | None = None  # see the module doc
    has_arm: bool = False  # arm_keypoints are real (elbow, shoulder, clavicle per side)
    keypoints_exact: bool = False  # keypoints are pixel-exact by construction (no registration needed)


@dataclass
class ClipChunk:
    """Frames [start, stop) of a clip. Arrays are per frame along axis 0, per hand along axis 1."""

    start: int
    frames: np.ndarray  # (n,H,W,3) uint8 RGB
    world_from_camera: np.ndarray  # (n,4,4) float64
    keypoints: np.ndarray  # (n,S,21,3) float32, camera frame, metres, MANO order; 0 where invalid
    keypoints_valid: np.ndarray  # (n,S,21) bool
    frame_ok: np.ndarray  # (n,) bool: False where the frame could not be decoded
    object_mask: np.ndarray | None = None  # (n,H,W) bool
    object_pose: np.ndarray | None = None  # (n,4,4) camera_from_object
    # (n,H,W) float32 camera-z (metres) of the object's surface, 0 off it, where the source
    # knows its geometry (mesh and pose); None: it does not (the object occludes by its mask)
    object_depth: np.ndarray | None = None
    gt: dict[str, np.ndarray] = field(default_factory=dict)  # ground truth, e.g. hand_mask
    arm_keypoints: np.ndarray | None = None  # (n,S,3,3) camera frame (keypoints.ARM_JOINTS)
    arm_valid: np.ndarray | None = None  # (n,S,3) bool

    @property
    def n(self) -> int:
        return int(self.frames.shape[0])

    def arms(self) -> tuple[np.ndarray, np.ndarray]:
        """(arm_keypoints, arm_valid), zeros/False when the source has none."""
        if self.arm_keypoints is not None and self.arm_valid is not None:
            return self.arm_keypoints, self.arm_valid
        S = self.keypoints.shape[1]
        return np.zeros((self.n, S, len(ARM_JOINTS), 3), np.float32), np.zeros((self.n, S, len(ARM_JOINTS)), bool)


@runtime_checkable
class Source(Protocol):
    def info(self) -> ClipInfo: ...

    def read(self, start: int, stop: int) -> ClipChunk: ...

    def object_mesh(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(vertices (V,3) in the object frame, faces (F,3)) when the source has an object model."""
        ...


def take_clips(groups, max_clips: int | None):
    """(group, specs) pairs of a tree listing, cut after ``max_clips`` specs in all (None: all);
    lazy, so a long listing is read only as far as it is used."""
    left = max_clips
    for name, specs in groups:
        if left is not None:
            specs, left = specs[:left], left - min(left, len(specs))
        if specs:
            yield name, specs
        if left == 0:
            return


def no_keypoints(n: int, sides: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Keypoint arrays for frames without any tracked hand."""
    return np.zeros((n, sides, N_JOINTS, 3), np.float32), np.zeros((n, sides, N_JOINTS), bool)


def on_sides(keypoints: np.ndarray, valid: np.ndarray, have, want) -> tuple[np.ndarray, np.ndarray]:
    """A chunk's (n,S,...) keypoint arrays, on the hand axis ``have``, moved onto ``want``
    (e.g. both sides for a clip whose hands are estimated): the sides it lacks are zero /
    invalid. Either None: unchanged."""
    if want is None or have is None or tuple(want) == tuple(have):
        return keypoints, valid
    have = tuple(have)
    n = keypoints.shape[0]
    kp = np.zeros((n, len(want), *keypoints.shape[2:]), keypoints.dtype)
    ok = np.zeros((n, len(want), *valid.shape[2:]), bool)
    for k, side in enumerate(want):
        if side in have:
            kp[:, k], ok[:, k] = keypoints[:, have.index(side)], valid[:, have.index(side)]
    return kp, ok


def frame_status(chunk: ClipChunk) -> tuple[np.ndarray, dict[int, str]]:
    """Per-frame ingest status: undecodable frames and blank (constant) frames are rejected."""
    from handedit.reasons import Reason

    status = np.full(chunk.n, int(Reason.OK), dtype=np.int16)
    details: dict[int, str] = {}
    for i in range(chunk.n):
        if not chunk.frame_ok[i]:
            status[i], details[i] = Reason.CORRUPT_FRAME, "frame could not be decoded"
        elif int(chunk.frames[i].max()) - int(chunk.frames[i].min()) < 4:
            status[i], details[i] = Reason.BLANK_FRAME, f"blank frame (constant value {int(chunk.frames[i].max())})"
    return status, details
