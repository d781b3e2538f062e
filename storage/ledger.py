"""The rejection ledger: every rejected frame (or hand) with its stage, reason code and detail.

The ledger is derived from the chunk provenance records (which a task writes right after
each chunk), so it can never disagree with the per-frame status arrays, and a re-run that
changes an outcome replaces its rows instead of appending stale ones. A clip whose source
could not be opened has no units; its one row (frame -1) comes from its shard's index.
Each shard flow writes its clips' ledger as a Parquet partition beside the store
(``handedit.storage.shards``), which is what ``handedit ledger`` reads at scale.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import zarr

from handedit.reasons import Reason
from handedit.storage.layout import LEDGER_COLUMNS, Unit, stage_layouts
from handedit.storage.provenance import read_records
from handedit.storage.store import read_array


def iter_units(root: zarr.Group, clips=None):
    """Every unit present in the store (of ``clips`` only, when given: no listing)."""
    if clips is None:
        if "clips" not in root:
            return
        clips = sorted(root["clips"].group_keys())
    for clip in clips:
        if f"clips/{clip}" not in root:
            continue
        cg = root[f"clips/{clip}"]
        for stage, layout in stage_layouts().items():
            if layout.level == "clip":
                unit = Unit(stage, clip)
                if unit.path in root:
                    yield unit
            elif layout.level == "scope" and stage in cg:
                for scope in sorted(cg[stage].group_keys()):
                    yield Unit(stage, clip, scope=scope)
        if "embodiments" in cg:
            for emb in sorted(cg["embodiments"].group_keys()):
                for stage, layout in stage_layouts().items():
                    unit = Unit(stage, clip, embodiment=emb) if layout.level == "embodiment" else None
                    if unit is not None and unit.path in root:
                        yield unit


def _reason_name(code: int) -> str:
    try:
        return Reason(code).name
    except ValueError:
        return f"UNKNOWN_{code}"


def source_error_rows(errors: dict[str, str]) -> list[dict]:
    """One ledger row (frame -1) per clip whose source could not be opened."""
    code = int(Reason.SOURCE_UNREADABLE)
    return [{"stage": "ingest", "clip": clip, "scope": "", "embodiment": "", "side": "", "frame": -1, "reason": code,
             "reason_name": _reason_name(code), "detail": err} for clip, err in sorted(errors.items())]


def read_ledger(root: zarr.Group, clips=None, source_errors: dict[str, str] | None = None) -> pd.DataFrame:
    """All rejections as a table: stage, clip, scope, embodiment, side, frame, reason, detail.

    ``clips``: only these (default: every clip in the store). A clip whose source could not
    be opened appears once, with frame -1 (``source_errors``; default: from the shards' index).
    """
    if source_errors is None:
        from handedit.storage.summary import source_errors as stored_errors

        source_errors = stored_errors(root)
        if clips is not None:
            source_errors = {c: e for c, e in source_errors.items() if c in set(clips)}
    rows = source_error_rows(source_errors)
    for unit in iter_units(root, clips):
        for rec in read_records(root, unit).values():
            for rej in rec.rejections:
                rows.append(
                    {
                        "stage": unit.stage,
                        "clip": unit.clip,
                        "scope": unit.scope or "",
                        "embodiment": unit.embodiment or "",
                        "side": str(rej.get("side", "")),
                        "frame": int(rej["frame"]),
                        "reason": int(rej["reason"]),
                        "reason_name": _reason_name(int(rej["reason"])),
                        "detail": str(rej.get("detail", "")),
                    }
                )
    frame = pd.DataFrame(rows, columns=[c for c, _ in LEDGER_COLUMNS])
    return frame.sort_values(["clip", "embodiment", "stage", "frame", "side"], kind="stable").reset_index(drop=True)


def unit_sides(root: zarr.Group, unit: Unit) -> list[str]:
    """The hands of a unit's clip, in hand-axis order (one-hand sources: one side)."""
    attrs = root[unit.path].attrs
    hands = attrs.get("hands")
    if hands is None:
        src = root[Unit("ingest", unit.clip).path].attrs if Unit("ingest", unit.clip).path in root else {}
        hands = src.get("hands") or ["right"]
    return list(hands)


def status_counts(root: zarr.Group, by_side: bool = False, clips=None) -> pd.DataFrame:
    """Frames per (stage, status name) over the store (or ``clips``), from the status arrays;
    with ``by_side``, per-hand stages are counted per (stage, side, status) from ``hand_status``."""
    rows = []
    for unit in iter_units(root, clips):
        group = root[unit.path]
        if by_side and "hand_status" in group:
            hs = read_array(group["hand_status"])
            for k, side in enumerate(unit_sides(root, unit)):
                codes, counts = np.unique(hs[:, k], return_counts=True)
                rows += [{"stage": unit.stage, "side": side, "status": _reason_name(int(c)), "frames": int(n)}
                         for c, n in zip(codes, counts)]
            continue
        codes, counts = np.unique(read_array(group["status"]), return_counts=True)
        rows += [{"stage": unit.stage, "side": None, "status": _reason_name(int(c)), "frames": int(n)}
                 for c, n in zip(codes, counts)]
    cols = ["stage", "side", "status", "frames"] if by_side else ["stage", "status", "frames"]
    df = pd.DataFrame(rows, columns=["stage", "side", "status", "frames"])[cols]
    return df.groupby(cols[:-1], sort=False, as_index=False, dropna=False)["frames"].sum()
