"""A generic source: one video file plus an optional keypoints file.

Frame indices are the decoder's presentation order. Seeking in compressed video is
only as exact as the container's index, so every decoded frame is placed by its
presentation timestamp (``CAP_PROP_POS_MSEC``) rather than by OpenCV's frame counter,
which drifts as soon as one packet fails to decode. When a file has no usable
timestamps we never seek: chunks are decoded sequentially from frame 0.

A frame that fails to decode marks ``frame_ok`` False for that frame only; the rest of
the chunk is still read. Every problem with the inputs themselves (missing file,
container that will not open, malformed keypoints) raises ``SourceError`` with the file
and the fix in the message, never a raw cv2 error.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import pydantic

from handedit.camera import Intrinsics
from handedit.keypoints import N_JOINTS
from handedit.sources.base import ClipChunk, ClipInfo, SourceError

_HASH_BLOCK = 1 << 20
_PTS_PROBE_FRAMES = 8  # frames decoded at open to check that timestamps give frame indices
_MAX_CONSECUTIVE_FAILURES = 8  # failed grabs in a row that we read as end of stream
_SEQUENTIAL_GAP = 48  # decode forward instead of seeking when the next read starts this close


class VideoSpec(pydantic.BaseModel):
    """Picklable description of a video clip (what workers receive)."""

    model_config = pydantic.ConfigDict(frozen=True, extra="forbid")

    kind: Literal["video"] = "video"
    path: Path
    # .npy (T,21,3) camera-frame metres, MANO order, NaN = missing; or .npz with
    # 'keypoints' (T,21,3), optional 'valid' (T,21) bool and optional 'K' (3,3).
    keypoints_path: Path | None = None
    clip_id: str | None = None  # default: the video's file stem
    intrinsics: tuple[float, float, float, float] | None = None  # fx, fy, cx, cy
    max_frames: int | None = pydantic.Field(default=None, ge=1)
    # "auto": seek, then place frames by timestamp (falls back to sequential when the
    # file has no usable timestamps); "sequential": always decode from frame 0.
    seek: Literal["auto", "sequential"] = "auto"

    def open(self) -> "VideoSource":
        return VideoSource(self)


@dataclass(frozen=True)
class _Probe:
    n_frames: int  # frames the container reports (or that a scan found)
    width: int
    height: int
    fps: float
    codec: str
    frame_count_origin: str  # "container" | "scanned"
    use_pts: bool  # timestamps map to frame indices (seek + verify is safe)


@dataclass(frozen=True)
class _Keypoints:
    xyz: np.ndarray  # (T,21,3) float32, 0 where invalid
    valid: np.ndarray  # (T,21) bool
    K: np.ndarray | None  # (3,3) from the file, if any
    sha256: str


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(_HASH_BLOCK):
            h.update(block)
    return h.hexdigest()


def _fourcc(value: float) -> str:
    code = int(value)
    chars = "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4))
    return chars if chars.isprintable() else str(code)


class VideoSource:
    """Reads frame ranges of one video; keeps its decoder open between reads.

    Consecutive ``read`` calls (chunk k then k+1) continue decoding without a seek.
    The open decoder is dropped when the object is pickled; the spec is what travels.
    """

    def __init__(self, spec: VideoSpec):
        self.spec = spec
        self.path = Path(spec.path)
        if not self.path.is_file():
            raise SourceError(f"video file {self.path} does not exist (or is not a file); fix the 'path' of the video source.")
        self._probe = self._probe_video()
        self._kp = self._load_keypoints() if spec.keypoints_path is not None else None
        self._info: ClipInfo | None = None
        self._cap: cv2.VideoCapture | None = None
        self._next: int | None = None  # index of the frame the open decoder yields next

    # -- pickling: the decoder handle is process-local --------------------------------
    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_cap"], state["_next"] = None, None
        return state

    # -- opening ----------------------------------------------------------------------
    def _open_capture(self) -> cv2.VideoCapture:
        try:
            cap = cv2.VideoCapture(str(self.path))
            opened = cap.isOpened()
        except cv2.error as e:  # pragma: no cover - backend-specific
            raise SourceError(f"video file {self.path} could not be opened ({e}); re-encode it (e.g. H.264 MP4).") from None
        if not opened:
            raise SourceError(
                f"video file {self.path} could not be opened: the file is corrupt, truncated (e.g. an MP4 "
                f"whose index/moov atom is missing) or not a video; re-download or re-encode it (e.g. H.264 MP4)."
            )
        return cap

    def _probe_video(self) -> _Probe:
        cap = self._open_capture()
        try:
            w = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
            h = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
            fps = float(cap.get(cv2.CAP_PROP_FPS))
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            codec = _fourcc(cap.get(cv2.CAP_PROP_FOURCC))
            # Check on the first frames that timestamps give frame indices.
            use_pts = fps > 0 and math.isfinite(fps)
            decoded = 0
            for i in range(_PTS_PROBE_FRAMES if n <= 0 else min(_PTS_PROBE_FRAMES, n)):
                if not cap.grab():
                    break
                decoded += 1
                if use_pts and self._pts_index(cap, fps) != i:
                    use_pts = False
            if decoded == 0:
                raise SourceError(
                    f"video file {self.path} opened but no frame could be decoded; the file is corrupt or uses "
                    f"an unsupported codec ({codec}); re-encode it (e.g. H.264 MP4)."
                )
            origin = "container"
            if n <= 0:  # container does not say: count by decoding
                n, origin = decoded, "scanned"
                while cap.grab():
                    n += 1
        except cv2.error as e:
            raise SourceError(f"video file {self.path} could not be decoded ({e}); re-encode it (e.g. H.264 MP4).") from None
        finally:
            cap.release()
        if w <= 0 or h <= 0:
            raise SourceError(f"video file {self.path} reports no frame size; re-encode it (e.g. H.264 MP4).")
        return _Probe(n, w, h, fps if fps > 0 and math.isfinite(fps) else 0.0, codec, origin, use_pts)

    @staticmethod
    def _pts_index(cap: cv2.VideoCapture, fps: float) -> int:
        return int(round(cap.get(cv2.CAP_PROP_POS_MSEC) * fps / 1000.0))

    def _load_keypoints(self) -> _Keypoints:
        path = Path(self.spec.keypoints_path)  # type: ignore[arg-type]
        T = self._probe.n_frames
        fix = f"expected keypoints (T,21,3) in metres with T = {T} (the video's frame count), NaN where missing"
        if not path.is_file():
            raise SourceError(f"keypoints file {path} does not exist; fix 'keypoints_path' or leave it empty.")
        K = None
        valid = None
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
            else:
                raise SourceError(f"keypoints file {path} must be .npy or .npz; {fix}.")
        except SourceError:
            raise
        except Exception as e:  # corrupt archive, pickled objects, ...
            raise SourceError(f"keypoints file {path} could not be read ({type(e).__name__}: {e}); {fix}.") from None

        if not np.issubdtype(xyz.dtype, np.number) or xyz.ndim != 3 or xyz.shape[1:] != (N_JOINTS, 3):
            raise SourceError(f"keypoints file {path} holds an array of shape {xyz.shape} ({xyz.dtype}); {fix}.")
        if xyz.shape[0] != T:
            raise SourceError(f"keypoints file {path} has {xyz.shape[0]} frames but the video {self.path} has {T}; {fix}.")
        xyz = xyz.astype(np.float32)
        ok = np.isfinite(xyz).all(axis=-1)
        if valid is not None:
            if valid.shape != (T, N_JOINTS):
                raise SourceError(f"keypoints file {path}: 'valid' has shape {valid.shape}, expected ({T}, {N_JOINTS}) bool.")
            ok &= valid.astype(bool)
        if K is not None:
            K = np.asarray(K, dtype=float)
            if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
                raise SourceError(f"keypoints file {path}: 'K' must be a finite 3x3 intrinsics matrix, got shape {K.shape}.")
        xyz[~ok] = 0.0
        return _Keypoints(xyz, ok, K, _sha256(path))

    # -- Source interface -------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        n = self._probe.n_frames
        return min(n, self.spec.max_frames) if self.spec.max_frames else n

    def _intrinsics(self) -> tuple[Intrinsics, str]:
        p = self._probe
        if self.spec.intrinsics is not None:
            fx, fy, cx, cy = self.spec.intrinsics
            return Intrinsics(fx, fy, cx, cy, p.width, p.height), "spec"
        if self._kp is not None and self._kp.K is not None:
            return Intrinsics.from_K(self._kp.K, p.width, p.height), "keypoints_file:K"
        return Intrinsics.default_for(p.width, p.height), "default: Intrinsics.default_for(W,H) (70 deg hfov guess, uncalibrated)"

    def info(self) -> ClipInfo:
        if self._info is None:
            p = self._probe
            intr, origin = self._intrinsics()
            video_sha = _sha256(self.path)
            kp_sha = self._kp.sha256 if self._kp is not None else None
            # Everything that changes what read() returns goes into the fingerprint.
            ident = {"video": video_sha, "keypoints": kp_sha, "intrinsics": intr.to_dict(), "max_frames": self.spec.max_frames}
            fp = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()
            self._info = ClipInfo(
                clip_id=self.spec.clip_id or self.path.stem,
                n_frames=self.n_frames,
                height=p.height,
                width=p.width,
                fps=p.fps if p.fps > 0 else 30.0,
                intrinsics=intr,
                has_keypoints=self._kp is not None,
                has_object=False,
                fingerprint=fp,
                meta={
                    "path": str(self.path),
                    "intrinsics_origin": origin,
                    "video_sha256": video_sha,
                    "keypoints_sha256": kp_sha,
                    "codec": p.codec,
                    "fps_origin": "container" if p.fps > 0 else "default 30.0 (container has none)",
                    "frame_count_origin": p.frame_count_origin,
                    "seek": "pts-verified" if (p.use_pts and self.spec.seek == "auto") else "sequential",
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
        p = self._probe
        frames = np.zeros((n, p.height, p.width, 3), np.uint8)
        frame_ok = np.zeros(n, bool)
        if n:
            try:
                self._decode(start, stop, frames, frame_ok)
            except cv2.error:
                # A decoder error mid-chunk: keep what was decoded, drop the handle.
                self._close()
        if self._kp is not None:
            kp, valid = self._kp.xyz[start:stop].copy(), self._kp.valid[start:stop].copy()
        else:
            kp, valid = np.zeros((n, N_JOINTS, 3), np.float32), np.zeros((n, N_JOINTS), bool)
        return ClipChunk(
            start=start,
            frames=frames,
            world_from_camera=np.tile(np.eye(4), (n, 1, 1)),
            keypoints=kp,
            keypoints_valid=valid,
            frame_ok=frame_ok,
        )

    # -- decoding ---------------------------------------------------------------------
    def _close(self) -> None:
        if self._cap is not None:
            self._cap.release()
        self._cap, self._next = None, None

    def _position(self, start: int, from_zero: bool) -> bool:
        """Prepare the decoder so its next frame has index <= start; True if it seeked."""
        seekable = self._probe.use_pts and self.spec.seek == "auto"
        if not from_zero and self._cap is not None and self._next is not None and self._next <= start:
            if not seekable or start - self._next <= _SEQUENTIAL_GAP:
                return False  # continue decoding: exact, and cheaper than a seek for short gaps
        if seekable and start > 0 and not from_zero:
            if self._cap is None:
                self._cap = self._open_capture()
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, float(start))
            self._next = None  # unknown until a grab reports its timestamp
            return True
        self._close()
        self._cap, self._next = self._open_capture(), 0
        return False

    def _decode(self, start: int, stop: int, frames: np.ndarray, frame_ok: np.ndarray) -> None:
        for attempt in range(2):
            seeked = self._position(start, from_zero=attempt > 0)
            first = self._decode_from(start, stop, frames, frame_ok)
            if seeked and (first is None or first > start):
                # The seek landed past start (inexact index, or frame `start` is broken):
                # decode from frame 0 instead, which is exact.
                frames[:] = 0
                frame_ok[:] = False
                continue
            return

    def _decode_from(self, start: int, stop: int, frames: np.ndarray, frame_ok: np.ndarray) -> int | None:
        """Grab until frame stop-1; returns the index of the first frame grabbed."""
        use_pts = self._probe.use_pts and self.spec.seek == "auto"
        cap = self._cap
        assert cap is not None
        expected = self._next  # counter-based index, used when timestamps are unusable
        failures, first = 0, None
        while True:
            if not cap.grab():
                failures += 1
                if not use_pts and expected is not None:
                    expected += 1  # a failed packet is (most likely) one lost frame
                if failures >= _MAX_CONSECUTIVE_FAILURES:
                    self._close()  # end of stream (truncated file): the rest stays frame_ok False
                    return first
                continue
            failures = 0
            idx = self._pts_index(cap, self._probe.fps) if use_pts else int(expected or 0)
            expected = idx + 1
            self._next = idx + 1
            first = idx if first is None else first
            if idx < start:
                continue
            if idx >= stop:
                break
            ok, img = cap.retrieve()
            if ok and img is not None and img.ndim == 3 and img.shape[:2] == frames.shape[1:3]:
                frames[idx - start] = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
                frame_ok[idx - start] = True
            if idx == stop - 1:
                break
        return first
