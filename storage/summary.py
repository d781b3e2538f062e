"""The run as one JSON object (``handedit status DIR --json``), for scripts and CI.

Schema (every count is frames)::

    {"store": "<path>",
     "units": [{"clip", "embodiment", "side", "frames", "kept"}, ...],
     "stages": [{"stage", "side", "status", "frames"}, ...],
     "rejections": [{"stage", "reason", "count"}, ...]}

``units``: one per clip x embodiment, or per clip x embodiment x side for a source that
tracks several hands (``side`` is "left" / "right"; null for a one-hand source). ``kept``:
frames whose QC status is OK, and, for a side, in which that side's robot replaced its
hand. ``stages``: frames per stage and status name, per side for the per-hand stages
(``side`` null for frame-level stages, or per-hand stages of one-hand sources).
``rejections``: ledger rows per (stage, reason name).
"""

from __future__ import annotations

import numpy as np
import zarr

from handedit.reasons import Reason
from handedit.storage.layout import Unit
from handedit.storage.ledger import iter_units, read_ledger, status_counts, unit_sides


def run_summary(root: zarr.Group, store: str = "") -> dict:
    units = []
    for unit in iter_units(root):
        if unit.stage != "qc":
            continue
        group = root[unit.path]
        status = group["status"][:]
        hs = group["hand_status"][:] if "hand_status" in group else None
        sides = unit_sides(root, unit)
        if hs is None or len(sides) == 1:
            units.append({"clip": unit.clip, "embodiment": unit.embodiment, "side": None, "frames": int(len(status)),
                          "kept": int((status == Reason.OK).sum())})
            continue
        for k, side in enumerate(sides):
            kept = (status == Reason.OK) & (hs[:, k] == Reason.OK)
            units.append({"clip": unit.clip, "embodiment": unit.embodiment, "side": side, "frames": int(len(status)),
                          "kept": int(kept.sum())})
    stages = status_counts(root, by_side=True)
    one_hand = {u.clip for u in iter_units(root) if u.stage == "ingest" and len(unit_sides(root, u)) == 1}
    rows = []
    for r in stages.to_dict(orient="records"):
        side = None if (r["side"] is None or r["side"] != r["side"]) else r["side"]
        rows.append({"stage": r["stage"], "side": side, "status": r["status"], "frames": int(r["frames"])})
    if one_hand and len(one_hand) == len({u.clip for u in iter_units(root)}):
        for r in rows:  # every clip has one hand: sides carry no information
            r["side"] = None
        merged: dict[tuple, int] = {}
        for r in rows:
            key = (r["stage"], None, r["status"])
            merged[key] = merged.get(key, 0) + r["frames"]
        rows = [{"stage": s, "side": d, "status": st, "frames": n} for (s, d, st), n in merged.items()]
    ledger = read_ledger(root)
    rejections = ([{"stage": s, "reason": r, "count": int(n)}
                   for (s, r), n in ledger.groupby(["stage", "reason_name"]).size().items()] if len(ledger) else [])
    return {"store": store, "units": units, "stages": rows, "rejections": rejections}


def kept_frames(root: zarr.Group, clip: str, embodiment: str) -> np.ndarray:
    """Frame indices of a clip x embodiment that QC kept."""
    return np.flatnonzero(root[Unit("qc", clip, embodiment=embodiment).path]["status"][:] == Reason.OK)
