"""What a run produced, as tables and as one JSON object (``handedit status DIR --json``).

The index (one row per clip x embodiment x hand, and one per unreadable clip) is what each
shard flow writes as its partition (``handedit.storage.shards``); the same rows computed
from the store give the status of a store without shards (a test's, a bench's).

``handedit status --json`` schema (every count is frames)::

    {"store": "<path or URL>",
     "units": [{"clip", "embodiment", "side", "frames", "kept"}, ...],
     "stages": [{"stage", "side", "status", "frames"}, ...],
     "rejections": [{"stage", "reason", "count"}, ...]}

``units``: one per clip x embodiment, or per clip x embodiment x side for a source that
tracks several hands (``side`` is "left" / "right"; null for a one-hand source). ``kept``:
frames whose QC status is OK, and, for a side, in which that side's robot replaced its
hand. ``stages``: frames per stage and status name, per side for the per-hand stages of
multi-hand clips (``side`` null otherwise). ``rejections``: ledger rows per (stage, reason).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import zarr

from handedit.reasons import Reason
from handedit.storage.layout import Unit
from handedit.storage.ledger import iter_units, read_ledger, status_counts, unit_sides
from handedit.storage.location import Location, location_of
from handedit.storage.shards import INDEX, read_partitions
from handedit.storage.store import read_array

INDEX_COLUMNS = ("clip", "embodiment", "scope", "side", "frames", "kept", "error")


def index_rows(root: zarr.Group, clips, source_errors: dict[str, str] | None = None,
               embodiments: dict[str, dict] | None = None) -> pd.DataFrame:
    """The index rows of ``clips`` (see module doc), from their QC arrays."""
    rows = []
    for unit in iter_units(root, clips):
        if unit.stage != "qc":
            continue
        group = root[unit.path]
        status = read_array(group["status"])
        hs = read_array(group["hand_status"]) if "hand_status" in group else None
        sides = unit_sides(root, unit)
        scope = (embodiments or {}).get(unit.embodiment, {}).get("scope", "")
        if hs is None or len(sides) == 1:
            rows.append({"clip": unit.clip, "embodiment": unit.embodiment, "scope": scope, "side": None,
                         "frames": int(len(status)), "kept": int((status == Reason.OK).sum()), "error": ""})
            continue
        for k, side in enumerate(sides):
            kept = (status == Reason.OK) & (hs[:, k] == Reason.OK)
            rows.append({"clip": unit.clip, "embodiment": unit.embodiment, "scope": scope, "side": side,
                         "frames": int(len(status)), "kept": int(kept.sum()), "error": ""})
    for clip, err in sorted((source_errors or {}).items()):
        rows.append({"clip": clip, "embodiment": "", "scope": "", "side": None, "frames": 0, "kept": 0, "error": err})
    return pd.DataFrame(rows, columns=list(INDEX_COLUMNS))


def read_index(loc: Location) -> pd.DataFrame | None:
    """Every shard's index partition (the newest row set per clip), or None without shards."""
    return read_partitions(loc, INDEX)


def source_errors(root: zarr.Group) -> dict[str, str]:
    """Unreadable clips and their errors, from the shards' index beside the store."""
    index = read_index(location_of(root))
    if index is None or "error" not in index.columns:
        return {}
    bad = index[index["error"].astype(str) != ""]
    return dict(zip(bad["clip"], bad["error"]))


def curated_clips(root: zarr.Group) -> list[str]:
    """Clips with data: from the shards' index when there is one, else by listing."""
    index = read_index(location_of(root))
    if index is not None:
        return sorted(set(index.loc[index["error"].astype(str) == "", "clip"]))
    return sorted(root["clips"].group_keys()) if "clips" in root else []


def run_summary(root: zarr.Group, store: str = "", clips=None) -> dict:
    clips = curated_clips(root) if clips is None else clips
    units = [{k: r[k] for k in ("clip", "embodiment", "side", "frames", "kept")}
             for r in index_rows(root, clips).to_dict(orient="records")]
    for u in units:
        u["side"] = None if u["side"] is None or u["side"] != u["side"] else u["side"]
    # the same rows as `handedit status` prints: per-hand stages per side (a one-hand source's
    # side too), the others with side None
    rows = [{"stage": r["stage"], "side": r["side"] if isinstance(r["side"], str) else None, "status": r["status"],
             "frames": int(r["frames"])} for r in status_counts(root, by_side=True, clips=clips).to_dict(orient="records")]
    ledger = read_ledger(root, clips=None)
    rejections = ([{"stage": s, "reason": r, "count": int(n)}
                   for (s, r), n in ledger.groupby(["stage", "reason_name"]).size().items()] if len(ledger) else [])
    return {"store": store, "units": units, "stages": rows, "rejections": rejections}


def kept_frames(root: zarr.Group, clip: str, embodiment: str) -> np.ndarray:
    """Frame indices of a clip x embodiment that QC kept."""
    return np.flatnonzero(read_array(root[Unit("qc", clip, embodiment=embodiment).path]["status"]) == Reason.OK)
