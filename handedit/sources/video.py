"""A generic source: one video file plus an optional keypoints file.

Decoding (frame-exact seeks, timestamps, broken frames) is ``handedit.sources.decode``.
A keypoints file gives one hand, (T,21,3), whose side is ``VideoSpec.hand``, or several,
(T,S,21,3) with their ``hands`` named in the file. Every problem with the inputs (missing
file, container that will not open, malformed keypoints) raises ``SourceError`` with the
file and the fix in the message, never a raw cv2 error.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pydantic

from handedit.camera import Intrinsics
from handedit.keypoints import N_JOINTS, SIDES
from handedit.sources.base import ClipChunk, ClipInfo, SourceError, no_keypoints
from handedit.digests import file_sha256
from handedit.sources.decode import VideoReader


class VideoSpec(pydantic.BaseModel):
    """Picklable description of a video clip (what workers receive)."""

    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    kind: Literal["video"] = "video"
    path: Path
    # .npy (T,21,3) camera-frame metres, MANO order, NaN = missing; or .npz with
    # 'keypoints' (T,21,3) or (T,S,21,3), optional 'valid' (T,[S,]21) bool, optional 'K'
    # (3,3) and, for S > 1, 'hands' (S,) side names.
    keypoints_path: Path | None = None
    hand: Literal["left", "right"] = "right"  # the side of a one-hand keypoints file (or of the video)
    clip_id: str | None = None  # default: the video's file stem
    intrinsics: tuple[float, float, float, float] | None = None  # fx, fy, cx, cy (at the file's resolution)
    hfov_deg: float | None = pydantic.Field(None, gt=10, lt=170)  # uncalibrated: the horizontal field of view
    max_frames: int | None = pydantic.Field(default=None, ge=1)
    resize: tuple[int, int] | None = None  # working resolution (W, H); intrinsics are scaled to it
    # "auto": seek, then place frames by timestamp (falls back to sequential when the
    # file has no usable timestamps); "sequential": always decode from frame 0.
    seek: Literal["auto", "sequential"] = "auto"

    @property
    def id(self) -> str:
        """``clip_id``, else the file's name with what a clip id cannot hold replaced by '-'."""
        return self.clip_id or re.sub(r"[^A-Za-z0-9._-]+", "-", self.path.stem).strip("-.") or "video"

    def files(self) -> list[Path]:
        return [self.path, *([self.keypoints_path] if self.keypoints_path else [])]

    def open(self) -> "VideoSource":
        return VideoSource(self)


@dataclass(frozen=True)
class _Keypoints:
    xyz: np.ndarray  # (T,S,21,3) float32, 0 where invalid
    valid: np.ndarray  # (T,S,21) bool
    hands: tuple[str, ...]
    K: np.ndarray | None  # (3,3) from the file, if any
    sha256: str


class VideoSource:
    """Reads frame ranges of one video (keeps its decoder open between reads)."""

    def __init__(self, spec: VideoSpec):
        self.spec = spec
        self.path = Path(spec.path)
        self.video = VideoReader(self.path, seek=spec.seek, resize=spec.resize)
        self._probe = self.video.probe
        self._kp = self._load_keypoints() if spec.keypoints_path is not None else None
        self._info: ClipInfo | None = None

    def _load_keypoints(self) -> _Keypoints:
        path = Path(self.spec.keypoints_path)  # type: ignore[arg-type]
        T = self._probe.n_frames
        fix = f"expected keypoints (T,21,3) or (T,S,21,3) in metres with T = {T} (the video's frame count), NaN where missing"
        if not path.is_file():
            raise SourceError(f"keypoints file {path} does not exist; fix 'keypoints_path' or leave it empty.")
        K = valid = hands = None
        try:
            if path.suffix == ".npy":
                xyz = np.load(path, allow_pickle=False)
            elif path.suffix == ".npz":
                with np.load(path, allow_pickle=False) as z:
                    if "keypoints" not in z.files:
                        raise SourceError(f"keypoints file {path} has no 'keypoints' array (found {z.files}); {fix}.")
                    xyz = z["keypoints"]
                    valid = z["valid"] if "valid" in z.files else None
                    K = z["K"] if "K" in z.files else None
                    hands = tuple(str(h) for h in z["hands"]) if "hands" in z.files else None
            else:
                raise SourceError(f"keypoints file {path} must be .npy or .npz; {fix}.")
        except SourceError:
            raise
        except Exception as e:  # corrupt archive, pickled objects, ...
            raise SourceError(f"keypoints file {path} could not be read ({type(e).__name__}: {e}); {fix}.") from None

        if not np.issubdtype(xyz.dtype, np.number) or xyz.ndim not in (3, 4) or xyz.shape[-2:] != (N_JOINTS, 3):
            raise SourceError(f"keypoints file {path} holds an array of shape {xyz.shape} ({xyz.dtype}); {fix}.")
        if xyz.shape[0] != T:
            raise SourceError(f"keypoints file {path} has {xyz.shape[0]} frames but the video {self.path} has {T}; {fix}.")
        one = xyz.ndim == 3
        xyz = (xyz[:, None] if one else xyz).astype(np.float32)
        S = xyz.shape[1]
        hands = (self.spec.hand,) if one or (S == 1 and hands is None) else hands
        if hands is None or len(hands) != S or any(h not in SIDES for h in hands) or len(set(hands)) != S:
            raise SourceError(f"keypoints file {path}: {S} hands need a 'hands' array naming each side "
                              f"({' or '.join(SIDES)}, each once), got {hands}.")
        order = sorted(range(S), key=lambda i: SIDES.index(hands[i]))  # hand axis in SIDES order
        xyz, hands = xyz[:, order], tuple(hands[i] for i in order)
        ok = np.isfinite(xyz).all(axis=-1)
        if valid is not None:
            valid = valid[:, None] if valid.ndim == 2 else valid
            if valid.shape != (T, S, N_JOINTS):
                raise SourceError(f"keypoints file {path}: 'valid' has shape {valid.shape}, expected ({T}, {S}, {N_JOINTS}) bool.")
            ok &= valid[:, order].astype(bool)
        if K is not None:
            K = np.asarray(K, dtype=float)
            if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
                raise SourceError(f"keypoints file {path}: 'K' must be a finite 3x3 intrinsics matrix, got shape {K.shape}.")
        xyz[~ok] = 0.0
        return _Keypoints(xyz, ok, hands, K, file_sha256(path))

    # -- Source interface -------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        n = self._probe.n_frames
        return min(n, self.spec.max_frames) if self.spec.max_frames else n

    def _intrinsics(self) -> tuple[Intrinsics, str]:
        p = self._probe
        if self.spec.intrinsics is not None:
            fx, fy, cx, cy = self.spec.intrinsics
            intr, origin = Intrinsics(fx, fy, cx, cy, p.width, p.height), "spec"
        elif self._kp is not None and self._kp.K is not None:
            intr, origin = Intrinsics.from_K(self._kp.K, p.width, p.height), "keypoints_file:K"
        elif self.spec.hfov_deg is not None:
            intr = Intrinsics.default_for(p.width, p.height, self.spec.hfov_deg)
            origin = f"spec: hfov {self.spec.hfov_deg:g} deg (uncalibrated, centred principal point)"
        else:
            intr, origin = Intrinsics.default_for(p.width, p.height), "default: Intrinsics.default_for(W,H) (70 deg hfov guess, uncalibrated)"
        return intr.scaled(*self.video.size), origin

    def info(self) -> ClipInfo:
        if self._info is None:
            p = self._probe
            intr, origin = self._intrinsics()
            video_sha = file_sha256(self.path)
            kp_sha = self._kp.sha256 if self._kp is not None else None
            # Everything that changes what read() returns goes into the fingerprint.
            ident = {"video": video_sha, "keypoints": kp_sha, "intrinsics": intr.to_dict(), "max_frames": self.spec.max_frames,
                     "hand": self.spec.hand}
            fp = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()
            w, h = self.video.size
            self._info = ClipInfo(
                clip_id=self.spec.id,
                n_frames=self.n_frames,
                height=h,
                width=w,
                fps=p.fps if p.fps > 0 else 30.0,
                intrinsics=intr,
                has_keypoints=self._kp is not None,
                has_object=False,
                fingerprint=fp,
                hands=self._kp.hands if self._kp is not None else (self.spec.hand,),
                meta={
                    "dataset": "video",
                    "path": str(self.path),
                    "intrinsics_origin": origin,
                    "video_sha256": video_sha,
                    "keypoints_sha256": kp_sha,
                    "codec": p.codec,
                    "fps_origin": "container" if p.fps > 0 else "default 30.0 (container has none)",
                    "frame_count_origin": p.frame_count_origin,
                    "seek": "pts-verified" if self.video.seekable else "sequential",
                    "resolution": {"file": [p.width, p.height], "working": [w, h]},
                },
            )
        return self._info

    def object_mesh(self) -> None:
        return None

    def read(self, start: int, stop: int) -> ClipChunk:
        T = self.n_frames
        if not (0 <= start <= stop <= T):
            raise SourceError(f"read({start}, {stop}) outside the {T} frames of {self.path}; use 0 <= start <= stop <= {T}.")
        n = stop - start
        frames, frame_ok = self.video.read(start, stop)
        if self._kp is not None:
            kp, valid = self._kp.xyz[start:stop].copy(), self._kp.valid[start:stop].copy()
        else:
            kp, valid = no_keypoints(n)
        return ClipChunk(start=start, frames=frames, world_from_camera=np.tile(np.eye(4), (n, 1, 1)),
                         keypoints=kp, keypoints_valid=valid, frame_ok=frame_ok)
