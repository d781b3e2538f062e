"""Frame-exact decoding of one video file: seek where it is safe, place frames by timestamp.

Frame indices are the decoder's presentation order. Seeking in compressed video is only as
exact as the container's index, so every decoded frame is placed by its presentation
timestamp (``CAP_PROP_POS_MSEC``) rather than by OpenCV's frame counter, which drifts as
soon as one packet fails to decode. When a file has no usable timestamps we never seek:
chunks are decoded sequentially from frame 0.

A ``VideoReader`` keeps its decoder open between reads, so consecutive chunks (k, then
k+1) continue decoding without a seek: each frame is decoded once per worker. A frame that
fails to decode marks ``frame_ok`` False for that frame only. ``resize`` gives a working
resolution (``Intrinsics.scaled`` scales the camera to match); the decoder still works at
the file's resolution, frames are resized right after decoding.

Every problem with the file itself raises ``SourceError`` naming the file and the fix.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from handedit.sources.base import SourceError

_PTS_PROBE_FRAMES = 8  # frames decoded at open to check that timestamps give frame indices
_MAX_CONSECUTIVE_FAILURES = 8  # failed grabs in a row that we read as end of stream
_SEQUENTIAL_GAP = 48  # decode forward instead of seeking when the next read starts this close


def _fourcc(value: float) -> str:
    code = int(value)
    chars = "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4))
    return chars if chars.isprintable() else str(code)


@dataclass
class DecodeStats:
    """Frames the decoder produced (``decoded``: every grab, including frames passed over on the
    way to a chunk's start) against frames delivered, and the seconds spent: ``decoded ==
    delivered`` means no frame was decoded twice or in vain."""

    decoded: int = 0
    delivered: int = 0
    seconds: float = 0.0

    def since(self, before: "DecodeStats") -> dict:
        return {"decoded": self.decoded - before.decoded, "delivered": self.delivered - before.delivered,
                "decode_seconds": round(self.seconds - before.seconds, 4)}


@dataclass(frozen=True)
class Probe:
    n_frames: int  # frames the container reports (or that a scan found)
    width: int  # the file's resolution (before any resize)
    height: int
    fps: float
    codec: str
    frame_count_origin: str  # "container" | "scanned"
    use_pts: bool  # timestamps map to frame indices (seek + verify is safe)


class VideoReader:
    """Reads frame ranges of one video file (see module doc); picklable (the decoder is not)."""

    def __init__(self, path: Path, seek: str = "auto", resize: tuple[int, int] | None = None, what: str = "video"):
        self.path = Path(path)
        self.what = what
        if not self.path.is_file():
            raise SourceError(f"{what} file {self.path} does not exist (or is not a file); fix the path of the source.")
        self.seek = seek
        self.probe = self._probe()
        self.size = tuple(resize) if resize else (self.probe.width, self.probe.height)  # (W, H) delivered
        self._cap: cv2.VideoCapture | None = None
        self._next: int | None = None  # index of the frame the open decoder yields next
        self.stats = DecodeStats()  # what this reader decoded (``read`` calls only, not the probe)

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_cap"], state["_next"] = None, None
        return state

    @property
    def seekable(self) -> bool:
        return self.probe.use_pts and self.seek == "auto"

    # -- opening ----------------------------------------------------------------------
    def _open_capture(self) -> cv2.VideoCapture:
        try:
            cap = cv2.VideoCapture(str(self.path))
            opened = cap.isOpened()
        except cv2.error as e:  # pragma: no cover - backend-specific
            raise SourceError(f"{self.what} file {self.path} could not be opened ({e}); re-encode it (e.g. H.264 MP4).") from None
        if not opened:
            raise SourceError(
                f"{self.what} file {self.path} could not be opened: the file is corrupt, truncated (e.g. an MP4 "
                f"whose index/moov atom is missing) or not a video; re-download or re-encode it (e.g. H.264 MP4)."
            )
        return cap

    def _probe(self) -> Probe:
        cap = self._open_capture()
        try:
            w = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
            h = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
            fps = float(cap.get(cv2.CAP_PROP_FPS))
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            codec = _fourcc(cap.get(cv2.CAP_PROP_FOURCC))
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
                    f"{self.what} file {self.path} opened but no frame could be decoded; the file is corrupt or uses "
                    f"an unsupported codec ({codec}); re-encode it (e.g. H.264 MP4)."
                )
            origin = "container"
            if n <= 0:  # container does not say: count by decoding
                n, origin = decoded, "scanned"
                while cap.grab():
                    n += 1
        except cv2.error as e:
            raise SourceError(f"{self.what} file {self.path} could not be decoded ({e}); re-encode it (e.g. H.264 MP4).") from None
        finally:
            cap.release()
        if w <= 0 or h <= 0:
            raise SourceError(f"{self.what} file {self.path} reports no frame size; re-encode it (e.g. H.264 MP4).")
        return Probe(n, w, h, fps if fps > 0 and math.isfinite(fps) else 0.0, codec, origin, use_pts)

    @staticmethod
    def _pts_index(cap: cv2.VideoCapture, fps: float) -> int:
        return int(round(cap.get(cv2.CAP_PROP_POS_MSEC) * fps / 1000.0))

    # -- reading ----------------------------------------------------------------------
    def read(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        """Frames [start, stop) as (n,H,W,3) uint8 RGB at the delivered size, and frame_ok (n,)."""
        n = stop - start
        w, h = self.size
        frames = np.zeros((n, h, w, 3), np.uint8)
        frame_ok = np.zeros(n, bool)
        if n:
            t0 = time.perf_counter()
            try:
                self._decode(start, stop, frames, frame_ok)
            except cv2.error:
                self._close()  # a decoder error mid-chunk: keep what was decoded, drop the handle
            self.stats.seconds += time.perf_counter() - t0
            self.stats.delivered += int(frame_ok.sum())
        return frames, frame_ok

    def _close(self) -> None:
        if self._cap is not None:
            self._cap.release()
        self._cap, self._next = None, None

    def _position(self, start: int, from_zero: bool) -> bool:
        """Prepare the decoder so its next frame has index <= start; True if it seeked."""
        if not from_zero and self._cap is not None and self._next is not None and self._next <= start:
            if not self.seekable or start - self._next <= _SEQUENTIAL_GAP:
                return False  # continue decoding: exact, and cheaper than a seek for short gaps
        if self.seekable and start > 0 and not from_zero:
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
        use_pts = self.seekable
        cap = self._cap
        assert cap is not None
        expected = self._next  # counter-based index, used when timestamps are unusable
        failures, first = 0, None
        src_hw = (self.probe.height, self.probe.width)
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
            self.stats.decoded += 1
            idx = self._pts_index(cap, self.probe.fps) if use_pts else int(expected or 0)
            expected = idx + 1
            self._next = idx + 1
            first = idx if first is None else first
            if idx < start:
                continue
            if idx >= stop:
                break
            ok, img = cap.retrieve()
            if ok and img is not None and img.ndim == 3 and img.shape[:2] == src_hw:
                if self.size != (src_hw[1], src_hw[0]):
                    img = cv2.resize(img, self.size, interpolation=cv2.INTER_AREA)
                frames[idx - start] = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
                frame_ok[idx - start] = True
            if idx == stop - 1:
                break
        return first
