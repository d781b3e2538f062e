"""``handedit models fetch``: MediaPipe's hand models out of the mediapipe 0.10.21 wheel.

That wheel (Apache-2.0) is the last mediapipe release that ships the palm detection and
hand landmark ``.tflite`` files; newer releases download them at run time. We never install
it (see ``handedit.models.mediapipe_hands`` for why): ``pip download --no-deps`` fetches
the wheel through the user's own pip configuration (index, mirror, proxy), and the four
model files are taken out of it, checked against the sha256 below and written atomically
with a ``PROVENANCE.json`` (wheel, licence, digests). ``--wheel FILE`` does the same from a
wheel already on disk (offline machines). A file already in place with the right digest is
kept, so a second run downloads nothing.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

from handedit.digests import file_sha256
from handedit.files import atomic_write

WHEEL = "mediapipe==0.10.21"
WHEEL_PLATFORM = ("--python-version", "3.11", "--platform", "manylinux_2_28_x86_64", "--only-binary=:all:")
LICENSE = "Apache-2.0 (google-ai-edge/mediapipe; the models' model cards: MediaPipe Hands)"
# file name -> (path inside the wheel, sha256)
MODELS: dict[str, tuple[str, str]] = {
    "palm_detection_full.tflite": ("mediapipe/modules/palm_detection/palm_detection_full.tflite",
                                   "1b14e9422c6ad006cde6581a46c8b90dd573c07ab7f3934b5589e7cea3f89a54"),
    "hand_landmark_full.tflite": ("mediapipe/modules/hand_landmark/hand_landmark_full.tflite",
                                  "11c272b891e1a99ab034208e23937a8008388cf11ed2a9d776ed3d01d0ba00e3"),
    "palm_detection_lite.tflite": ("mediapipe/modules/palm_detection/palm_detection_lite.tflite",
                                   "e9a4aaddf90dda56a87235303cf00e4c2d3fb28725f68fd88772997dac905c18"),
    "hand_landmark_lite.tflite": ("mediapipe/modules/hand_landmark/hand_landmark_lite.tflite",
                                  "048edd3645c9bf7397d19a9f6e3a42957d6e414c9bea6598030a2e9b624156e6"),
}


class ModelFetchError(RuntimeError):
    """The wheel could not be downloaded or does not hold the expected files."""


def default_model_dir() -> Path:
    from handedit.cache import cache_root

    return cache_root() / "models" / "mediapipe-hands-0.10.21"


@dataclass
class FetchResult:
    dest: Path
    fetched: list[str]
    present: list[str]

    def summary(self) -> str:
        return (f"{self.dest}: {len(self.fetched)} model file(s) written, {len(self.present)} already in place "
                f"({LICENSE})")


def _in_place(dest: Path) -> list[str]:
    return [n for n, (_, sha) in MODELS.items() if (dest / n).is_file() and file_sha256(dest / n) == sha]


def _download_wheel(into: Path) -> Path:
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--quiet", WHEEL, *WHEEL_PLATFORM, "-d", str(into)]
    try:
        subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=1800)
    except (subprocess.CalledProcessError, subprocess.TimeoutExpired, OSError) as exc:
        err = getattr(exc, "stderr", "") or str(exc)
        raise ModelFetchError(f"`{' '.join(cmd)}` failed ({err.strip().splitlines()[-1] if err.strip() else exc}); "
                              f"check the pip index/proxy, or download the wheel elsewhere and pass --wheel FILE") from None
    wheels = sorted(into.glob("mediapipe-0.10.21-*.whl"))
    if not wheels:
        raise ModelFetchError(f"pip download left no mediapipe 0.10.21 wheel in {into}; pass --wheel FILE")
    return wheels[0]


def fetch(dest: Path | None = None, wheel: Path | None = None) -> FetchResult:
    """Put the hand models in ``dest`` (default: the cache the stage reads)."""
    dest = Path(dest or default_model_dir()).expanduser()
    present = _in_place(dest)
    if len(present) == len(MODELS):
        return FetchResult(dest, [], present)
    with tempfile.TemporaryDirectory(prefix="handedit-wheel-") as tmp:
        whl = Path(wheel).expanduser() if wheel else _download_wheel(Path(tmp))
        if not whl.is_file():
            raise ModelFetchError(f"wheel {whl} does not exist; pass the mediapipe 0.10.21 wheel's path")
        try:
            zf = zipfile.ZipFile(whl)
        except (zipfile.BadZipFile, OSError) as exc:
            raise ModelFetchError(f"{whl} is not a readable wheel ({exc}); download mediapipe 0.10.21 again") from None
        fetched = []
        with zf:
            names = set(zf.namelist())
            for name, (inner, sha) in MODELS.items():
                if name in present:
                    continue
                if inner not in names:
                    raise ModelFetchError(f"{whl} has no {inner}; it is not the mediapipe 0.10.21 wheel (pass that one)")
                data = zf.read(inner)
                got = hashlib.sha256(data).hexdigest()
                if got != sha:
                    raise ModelFetchError(f"{inner} in {whl} has sha256 {got[:16]}..., expected {sha[:16]}...: "
                                          f"not the published model; nothing was written for it")
                atomic_write(dest / name, data)
                fetched.append(name)
        prov = {"wheel": whl.name, "requirement": WHEEL, "license": LICENSE,
                "files": {n: {"path_in_wheel": p, "sha256": s} for n, (p, s) in MODELS.items()}}
        atomic_write(dest / "PROVENANCE.json", json.dumps(prov, indent=2).encode())
    return FetchResult(dest, fetched, present)
