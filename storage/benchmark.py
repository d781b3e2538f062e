"""Benchmark folder I/O: PNG images and masks, JSONL manifests and records, result tables.

Paths come from ``storage.layout`` (the BENCH_* section); writes are atomic (temp file
+ rename) so an interrupted run never leaves a half-written PNG that a resumed run
would mistake for a finished prediction.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator

import cv2
import numpy as np

from handedit import images
from handedit.secrets import redact_obj
from handedit.storage.location import atomic_write
from handedit.storage.layout import (BENCH_ITEM_FILES, BENCH_MANIFEST, BENCH_META, BENCH_REPORT, BENCH_VLM_CACHE,
                            bench_item_dir, bench_prediction_dir, bench_ref_paths, bench_results_dir)
from handedit.storage.store import jsonable


RATINGS = "human/ratings"  # the rating page's ratings, one create-once file each


def add_rating(bench: str | Path, row: dict) -> None:
    """Store one checked rating as given (a crash loses nothing given; raters never share a file)."""
    from handedit.storage.location import Location

    Location(str(bench)).add_entry(RATINGS, row)


def read_ratings(bench: str | Path) -> list[dict]:
    """The page's ratings in the order given (a rater's later rating of an output replaces the earlier)."""
    from handedit.storage.location import Location

    return Location(str(bench)).entries(RATINGS)


class BenchIOError(RuntimeError):
    """A benchmark file that is missing or unreadable; the message names it."""


@dataclass(frozen=True)
class BenchDir:
    """The paths of one benchmark folder (see ``storage.layout``)."""

    root: Path

    @property
    def meta(self) -> Path:
        return self.root / BENCH_META

    @property
    def manifest(self) -> Path:
        return self.root / BENCH_MANIFEST

    def item_file(self, item_id: str, kind: str) -> Path:
        return self.root / bench_item_dir(item_id) / BENCH_ITEM_FILES[kind]

    def ref_files(self, embodiment: str, view: int) -> tuple[Path, Path]:
        a, b = bench_ref_paths(embodiment, view)
        return self.root / a, self.root / b

    def predictions(self, editor: str) -> Path:
        return self.root / bench_prediction_dir(editor)

    def prediction(self, editor: str, item_id: str) -> Path:
        return self.predictions(editor) / f"{item_id}.png"

    def records(self, editor: str) -> Path:
        return self.predictions(editor) / "records.jsonl"

    def results(self, editor: str) -> Path:
        return self.root / bench_results_dir(editor)

    @property
    def vlm_cache(self) -> Path:
        return self.root / BENCH_VLM_CACHE

    @property
    def report(self) -> Path:
        return self.root / BENCH_REPORT


def encode_png(image: np.ndarray) -> bytes:
    try:
        return images.encode_png(image)
    except ValueError as exc:
        raise BenchIOError(str(exc)) from None


def write_image(path: str | Path, image: np.ndarray) -> Path:
    """uint8 RGB/RGBA or bool mask -> PNG (masks as 0/255 grey)."""
    path = Path(path)
    atomic_write(path, encode_png(image))
    return path


def write_bytes(path: str | Path, data: bytes) -> Path:
    path = Path(path)
    atomic_write(path, data)
    return path


def decode_image(data: bytes, what: str = "image") -> np.ndarray:
    a = images.decode_rgb(data)
    if a is None:
        raise BenchIOError(f"{what}: not a decodable image ({len(data)} bytes)")
    return a


def _imread(path: str | Path, flags: int, what: str, fix: str = "") -> np.ndarray:
    """cv2.imread with errors that name the file: missing, or not a decodable image."""
    path = Path(path)
    if not path.is_file():
        raise BenchIOError(f"{what} not found: {path}")
    a = cv2.imread(str(path), flags)
    if a is None:
        raise BenchIOError(f"cannot decode {what} {path} (corrupt or not an image){fix}")
    return a


def read_image(path: str | Path) -> np.ndarray:
    """PNG/JPEG -> uint8 (H,W,3) RGB; a clear error naming the file otherwise."""
    a = _imread(path, cv2.IMREAD_COLOR, "image", "; re-run the editor for this item")
    return cv2.cvtColor(a, cv2.COLOR_BGR2RGB)


def read_mask(path: str | Path) -> np.ndarray:
    """Grey/colour PNG -> bool mask (any channel > 127)."""
    a = _imread(path, cv2.IMREAD_UNCHANGED, "mask")
    return (a > 127) if a.ndim == 2 else (a[..., :3] > 127).any(axis=-1)


def write_json(path: str | Path, obj: Any) -> Path:
    path = Path(path)
    atomic_write(path, (json.dumps(redact_obj(jsonable(obj)), indent=2, sort_keys=True) + "\n").encode())
    return path


def read_json(path: str | Path) -> Any:
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise BenchIOError(f"{path} not found") from None
    except json.JSONDecodeError as exc:
        raise BenchIOError(f"{path} is not valid JSON ({exc})") from None


def write_jsonl(path: str | Path, rows: Iterable[dict]) -> Path:
    path = Path(path)
    data = "".join(json.dumps(redact_obj(jsonable(r)), sort_keys=True) + "\n" for r in rows)
    atomic_write(path, data.encode())
    return path


def append_jsonl(path: str | Path, row: dict) -> None:
    """One line per call with O_APPEND: safe for the one process that owns the file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(redact_obj(jsonable(row)), sort_keys=True) + "\n")


def iter_jsonl(path: str | Path) -> Iterator[tuple[int, dict | None, str | None]]:
    """(line number, object, error) per non-blank line; a bad line is an error, not a crash."""
    path = Path(path)
    if not path.is_file():
        raise BenchIOError(f"{path} not found")
    with open(path, encoding="utf-8") as f:
        for no, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                obj = json.loads(line)
            except json.JSONDecodeError as exc:
                yield no, None, f"{path}:{no}: not valid JSON ({exc.msg} at column {exc.colno})"
                continue
            if not isinstance(obj, dict):
                yield no, None, f"{path}:{no}: expected a JSON object, got {type(obj).__name__}"
                continue
            yield no, obj, None


def write_text(path: str | Path, text: str) -> Path:
    path = Path(path)
    atomic_write(path, text.encode())
    return path
