"""Frame-aligned MP4 files for episodes and video pairs (PyAV, FFmpeg bundled in its wheel).

The defaults are LeRobot's own (``encode_video_frames``): AV1 by SVT-AV1, yuv420p, a key
frame every 2 frames, CRF 30. Short GOPs make random access cheap, which is how a training
loader reads (one frame at a time, anywhere); ``libx264`` is the choice for players that
lack AV1. One frame in, one frame out, presentation times ``i / fps``: frame ``i`` of the
file is frame ``i`` of the episode, so a decoder seeking by timestamp finds it.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Iterable

import numpy as np

CODECS = {"libsvtav1": "av1", "libx264": "h264", "libaom-av1": "av1"}


@dataclass(frozen=True)
class VideoSpec:
    codec: str = "libsvtav1"
    crf: int = 30
    gop: int = 2
    pix_fmt: str = "yuv420p"

    def __post_init__(self) -> None:
        if self.codec not in CODECS:
            raise ValueError(f"video codec {self.codec!r}: use one of {', '.join(CODECS)}")

    def options(self) -> dict[str, str]:
        opts = {"g": str(self.gop), "crf": str(self.crf)}
        if self.codec == "libsvtav1":
            opts["preset"] = "10"  # LeRobot leaves SVT-AV1's default; 10 encodes ~3x faster at this CRF
        elif self.codec == "libx264":
            opts["preset"] = "fast"
        return opts

    def info(self, height: int, width: int, fps: float) -> dict:
        """LeRobot's ``info.json`` description of a video feature."""
        return {"video.height": height, "video.width": width, "video.codec": CODECS[self.codec],
                "video.pix_fmt": self.pix_fmt, "video.is_depth_map": False, "video.fps": fps,
                "video.channels": 3, "has_audio": False}


# release video pairs: near-lossless H.264 (plays everywhere) with a key frame every second; masks
# lossless (QP 0: grey levels come back exact, threshold at 128)
PAIR_SPECS = {"source": VideoSpec("libx264", crf=18, gop=30), "pseudo_gt": VideoSpec("libx264", crf=18, gop=30),
              "robot_mask": VideoSpec("libx264", crf=0, gop=30)}


def encode(frames: Iterable[np.ndarray], path: str | os.PathLike, fps: float, spec: VideoSpec = VideoSpec()) -> int:
    """Write ``frames`` ((H, W, 3) uint8 RGB, or (H, W) bool/uint8 masks shown as grey) to
    ``path``; returns the number of frames. The caller owns atomicity (write to a staging path)."""
    import av

    logging.getLogger("libav").setLevel(logging.ERROR)
    os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its configuration to stderr otherwise: errors only
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = 0
    rate = Fraction(fps).limit_denominator(1001)
    with av.open(str(path), "w") as out:
        stream = None
        for img in frames:
            img = as_rgb(img)
            if stream is None:
                stream = out.add_stream(spec.codec, rate=rate, options=spec.options())
                stream.pix_fmt, stream.height, stream.width = spec.pix_fmt, img.shape[0], img.shape[1]
            frame = av.VideoFrame.from_ndarray(img, format="rgb24")
            frame.pts = n
            frame.time_base = 1 / rate
            out.mux(stream.encode(frame))
            n += 1
        if stream is None:
            raise ValueError(f"{path}: no frames to encode")
        out.mux(stream.encode(None))
    return n


def as_rgb(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim == 2:  # a mask
        img = np.repeat(((img > 0) * 255 if img.dtype == bool or img.max() <= 1 else img).astype(np.uint8)[..., None], 3, -1)
    if img.shape[-1] == 4:
        img = img[..., :3]
    # yuv420p needs even sizes; odd ones lose their last row/column (never the case for the roster's resolutions)
    h, w = img.shape[0] // 2 * 2, img.shape[1] // 2 * 2
    return np.ascontiguousarray(img[:h, :w], dtype=np.uint8)


def decode(path: str | os.PathLike) -> np.ndarray:
    """All frames of a file (T, H, W, 3) uint8: for tests and checks, not for training loaders."""
    import av

    with av.open(str(path)) as f:
        return np.stack([fr.to_ndarray(format="rgb24") for fr in f.decode(video=0)])
