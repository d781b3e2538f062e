"""The rejection ledger: every rejected frame with its stage, reason code and detail.

The ledger is derived from the chunk provenance records (which the driver writes right
after each chunk), so it can never disagree with the per-frame status arrays, and a
re-run that changes an outcome replaces its rows instead of appending stale ones.
``write_ledger_table`` materialises it as columns under ``ledger/`` for readers that
only have plain zarr.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import zarr

from handedit.reasons import Reason
from handedit.storage.layout import LEDGER_COLUMNS, LEDGER_PATH, STAGE_LEVEL, Unit
from handedit.storage.provenance import read_records


def iter_units(root: zarr.Group):
    """Every unit present in the store."""
    if "clips" not in root:
        return
    for clip in sorted(root["clips"].group_keys()):
        cg = root[f"clips/{clip}"]
        for stage, level in STAGE_LEVEL.items():
            if level == "clip":
                unit = Unit(stage, clip)
                if unit.path in root:
                    yield unit
            elif level == "scope" and stage in cg:
                for scope in sorted(cg[stage].group_keys()):
                    yield Unit(stage, clip, scope=scope)
        if "embodiments" in cg:
            for emb in sorted(cg["embodiments"].group_keys()):
                for stage, level in STAGE_LEVEL.items():
                    unit = Unit(stage, clip, embodiment=emb) if level == "embodiment" else None
                    if unit is not None and unit.path in root:
                        yield unit


def _reason_name(code: int) -> str:
    try:
        return Reason(code).name
    except ValueError:
        return f"UNKNOWN_{code}"


def read_ledger(root: zarr.Group) -> pd.DataFrame:
    """All rejections as a table: stage, clip, scope, embodiment, frame, reason, detail.

    A clip whose source could not be opened at all appears once, with frame -1.
    """
    rows = [
        {"stage": "ingest", "clip": clip, "scope": "", "embodiment": "", "side": "", "frame": -1,
         "reason": int(entry.get("reason", Reason.SOURCE_UNREADABLE)),
         "reason_name": _reason_name(int(entry.get("reason", Reason.SOURCE_UNREADABLE))), "detail": entry["error"]}
        for clip, entry in (root.attrs.get("clips") or {}).items()
        if entry.get("error")
    ]
    for unit in iter_units(root):
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


def status_counts(root: zarr.Group, by_side: bool = False) -> pd.DataFrame:
    """Frames per (stage, status name) over the whole store, from the status arrays; with
    ``by_side``, per-hand stages are counted per (stage, side, status) from ``hand_status``."""
    rows = []
    for unit in iter_units(root):
        group = root[unit.path]
        if by_side and "hand_status" in group:
            hs = group["hand_status"][:]
            for k, side in enumerate(unit_sides(root, unit)):
                codes, counts = np.unique(hs[:, k], return_counts=True)
                rows += [{"stage": unit.stage, "side": side, "status": _reason_name(int(c)), "frames": int(n)}
                         for c, n in zip(codes, counts)]
            continue
        codes, counts = np.unique(group["status"][:], return_counts=True)
        rows += [{"stage": unit.stage, "side": None, "status": _reason_name(int(c)), "frames": int(n)}
                 for c, n in zip(codes, counts)]
    cols = ["stage", "side", "status", "frames"] if by_side else ["stage", "status", "frames"]
    df = pd.DataFrame(rows, columns=["stage", "side", "status", "frames"])[cols]
    return df.groupby(cols[:-1], sort=False, as_index=False, dropna=False)["frames"].sum()


def write_ledger_table(root: zarr.Group, ledger: pd.DataFrame | None = None) -> int:
    """Driver only: materialise the ledger as one array per column under ``ledger/``."""
    ledger = read_ledger(root) if ledger is None else ledger
    if LEDGER_PATH in root:
        del root[LEDGER_PATH]
    group = root.require_group(LEDGER_PATH)
    n = len(ledger)
    for name, dtype in LEDGER_COLUMNS:
        values = ledger[name].to_numpy()
        values = values.astype(str) if dtype == "str" else values.astype(dtype)
        arr = group.create_array(name, shape=(n,), dtype=dtype, chunks=(max(n, 1),), dimension_names=("row",))
        if n:
            arr[:] = values
    group.attrs.update({"columns": [c for c, _ in LEDGER_COLUMNS], "rows": n})
    return n
