"""Reference-bank I/O: canonical renders + frozen descriptions per embodiment (layout in
``storage.layout``). One writer (``handedit bank build``) writes whole embodiment groups;
readers (the benchmark) get plain numpy arrays and strings.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

from handedit.storage.layout import BANK_GROUP, BANK_SCHEMA_VERSION, bank_embodiment_path
from handedit.storage.store import COLOUR_CODEC, IMAGE_CODEC, StoreError, jsonable, read_array


@dataclass(frozen=True)
class BankEntry:
    embodiment_id: str
    name: str
    track: str
    description: str
    rgb: np.ndarray  # (V,H,W,3) uint8
    mask: np.ndarray  # (V,H,W) bool
    camera_from_root: np.ndarray  # (V,4,4)
    qpos: np.ndarray  # (V,dof)
    K: np.ndarray  # (3,3)


def open_bank(path: str | Path, mode: str = "r") -> zarr.Group:
    path = Path(path)
    if mode == "r" and not path.exists():
        raise StoreError(f"reference bank {path} does not exist; build it with `handedit bank build --out {path}`")
    root = zarr.open_group(str(path), mode=mode, zarr_format=3)
    if mode != "r" and "bank_schema" not in root.attrs:
        root.attrs.update({"bank_schema": BANK_SCHEMA_VERSION})
    if root.attrs.get("bank_schema") != BANK_SCHEMA_VERSION:
        raise StoreError(f"{path} is not a handedit reference bank (schema {root.attrs.get('bank_schema')!r}, "
                         f"expected {BANK_SCHEMA_VERSION}); rebuild it with `handedit bank build`")
    return root


def write_bank_entry(path: str | Path, entry: BankEntry, rig: dict) -> None:
    """Write (replace) one embodiment's group. Single writer: the bank builder."""
    root = open_bank(path, mode="a")
    root.attrs.update(jsonable({"rig": rig}))
    gpath = bank_embodiment_path(entry.embodiment_id)
    if gpath in root:
        del root[gpath]
    g = root.require_group(BANK_GROUP).create_group(entry.embodiment_id)
    V, H, W = entry.mask.shape
    g.create_array("rgb", data=np.asarray(entry.rgb, np.uint8), chunks=(1, H, W, 3), compressors=COLOUR_CODEC)
    g.create_array("mask", data=np.asarray(entry.mask, bool), chunks=(1, H, W), compressors=IMAGE_CODEC)
    g.create_array("camera_from_root", data=np.asarray(entry.camera_from_root, np.float64))
    g.create_array("qpos", data=np.asarray(entry.qpos, np.float32))
    g.create_array("K", data=np.asarray(entry.K, np.float64))
    g.attrs.update({"name": entry.name, "track": entry.track, "description": entry.description, "views": int(V)})


def bank_embodiments(path: str | Path) -> list[str]:
    """Embodiment ids present in a bank."""
    root = open_bank(path)
    if BANK_GROUP not in root:
        return []
    return sorted(name for name, _ in root[BANK_GROUP].groups())


def read_bank_entry(path: str | Path, embodiment_id: str) -> BankEntry:
    root = open_bank(path)
    gpath = bank_embodiment_path(embodiment_id)
    if gpath not in root:
        raise StoreError(f"embodiment {embodiment_id!r} is not in reference bank {path} "
                         f"(has: {bank_embodiments(path)}); build it with `handedit bank build --embodiment {embodiment_id}`")
    g = root[gpath]
    return BankEntry(
        embodiment_id=embodiment_id,
        name=str(g.attrs["name"]),
        track=str(g.attrs["track"]),
        description=str(g.attrs["description"]),
        rgb=read_array(g["rgb"], ...),
        mask=read_array(g["mask"], ...),
        camera_from_root=read_array(g["camera_from_root"], ...),
        qpos=read_array(g["qpos"], ...),
        K=read_array(g["K"], ...),
    )


def read_bank(path: str | Path, embodiment_id: str) -> tuple[np.ndarray, np.ndarray, str, str]:
    """(rgb (V,H,W,3) uint8, mask (V,H,W) bool, frozen description, display name)."""
    e = read_bank_entry(path, embodiment_id)
    return e.rgb, e.mask, e.description, e.name
