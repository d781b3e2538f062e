"""An audit's files in a run (beside its store), and the pairs it samples from.

    audit/<name>/sample.json             the frozen sample: seed, n, kept share, when, items
    audit/<name>/verdicts/<t>-<id>.json  one verdict per file, created once, never rewritten

A verdict is its own create-if-absent file (``Location.add_entry``), written as it is given:
a crash loses nothing already given, several reviewers never write the same file, and the
same code runs on a folder and on object storage. Reading sorts them by name (time first),
so a reviewer's later verdict on an item replaces the earlier one.
"""

from __future__ import annotations

import json
import re
from datetime import datetime, timezone

import numpy as np
import pandas as pd
import zarr

from handedit.audit import ITEM_COLUMNS, item_id
from handedit.reasons import Reason
from handedit.storage.layout import SCOPE_MASK, Unit
from handedit.storage.ledger import iter_units, read_ledger
from handedit.storage.location import Location
from handedit.storage.store import read_array
from handedit.storage.summary import curated_clips


def audit_dir(name: str) -> str:
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}", name):
        raise ValueError(f"audit name {name!r}: letters, digits, '_', '.', '-' (up to 64), starting with a letter or digit")
    return f"audit/{name}"


def _track(embodiment: str) -> str:
    from handedit.embodiments import EmbodimentError, get_embodiment

    try:
        return get_embodiment(embodiment).track
    except EmbodimentError:
        return "unknown"


def pairs(root: zarr.Group) -> pd.DataFrame:
    """Every curated frame x embodiment pair of the store (``ITEM_COLUMNS``): kept by QC or not,
    and for a rejected one the stage that first rejected it and its reason."""
    from handedit.release.datasheet import primary_causes

    clips = curated_clips(root)
    rows = []
    for unit in iter_units(root, clips):
        if unit.stage != "qc":
            continue
        status = read_array(root[unit.path]["status"])
        track = _track(unit.embodiment)
        rows += [{"clip": unit.clip, "embodiment": unit.embodiment, "track": track, "frame": f, "kept": bool(s == Reason.OK)}
                 for f, s in enumerate(status)]
    frame = pd.DataFrame(rows, columns=["clip", "embodiment", "track", "frame", "kept"])
    embs = sorted(set(frame["embodiment"]))
    causes = primary_causes(read_ledger(root, clips=clips), embs)[["clip", "embodiment", "frame", "stage", "reason_name"]]
    frame = frame.merge(causes.rename(columns={"reason_name": "reason"}), how="left", on=["clip", "embodiment", "frame"])
    frame.loc[frame["kept"], ["stage", "reason"]] = ""
    frame[["stage", "reason"]] = frame[["stage", "reason"]].fillna("")
    frame["id"] = [item_id(c, e, f) for c, e, f in zip(frame["clip"], frame["embodiment"], frame["frame"])]
    return frame[list(ITEM_COLUMNS)]


def pair_views(root: zarr.Group, clip: str, embodiment: str, track: str, frame: int) -> dict[str, np.ndarray | None]:
    """What the paper's annotator looked at for one pair: the source frame, the human mask of the
    track's scope (both hands), the restored background, the pseudo-GT and the robot mask (both
    hands); None for what the store does not hold (a pair rejected before that stage)."""
    scope = track if track in SCOPE_MASK else "hand"

    def frame_of(unit: Unit, name: str):
        group = root.get(unit.path)
        if group is None or name not in group:
            return None
        return read_array(group[name], int(frame))

    def union(masks):
        return None if masks is None else (np.asarray(masks) > 0).any(axis=0) if np.asarray(masks).ndim == 3 else masks > 0

    return {"source": frame_of(Unit("ingest", clip), "frames"),
            "human_mask": union(frame_of(Unit("segment", clip), SCOPE_MASK[scope])),
            "background": frame_of(Unit("restore_background", clip, scope=scope), "background"),
            "pseudo_gt": frame_of(Unit("harmonize", clip, embodiment=embodiment), "image"),
            "robot_mask": union(frame_of(Unit("composite", clip, embodiment=embodiment), "robot_mask"))}


def write_sample(loc: Location, name: str, items: pd.DataFrame, meta: dict) -> bool:
    """Freeze a sample; False when ``name`` already has one (a sample is never redrawn under
    the same name: its verdicts refer to its items)."""
    body = {**meta, "created": datetime.now(timezone.utc).isoformat(),
            "items": json.loads(items.to_json(orient="records"))}
    return loc.create_json(f"{audit_dir(name)}/sample.json", body)


def read_sample(loc: Location, name: str) -> tuple[dict, pd.DataFrame] | None:
    body = loc.read_json(f"{audit_dir(name)}/sample.json")
    if body is None:
        return None
    items = pd.DataFrame(body.pop("items"), columns=list(ITEM_COLUMNS))
    items["kept"] = items["kept"].astype(bool)
    items["frame"] = items["frame"].astype(np.int64)
    return body, items


def add_verdict(loc: Location, name: str, verdict: dict) -> dict:
    """Store one checked verdict (``handedit.audit.parse_verdict``) as given, now."""
    return loc.add_entry(f"{audit_dir(name)}/verdicts", verdict)


def read_verdicts(loc: Location, name: str) -> list[dict]:
    """Every verdict of the audit, in the order given."""
    return loc.entries(f"{audit_dir(name)}/verdicts")


def audit_names(loc: Location) -> list[str]:
    return [n for n in loc.listdir("audit") if loc.exists(f"audit/{n}/sample.json")]


def release_view(loc: Location) -> tuple[dict[str, dict], dict[str, dict]]:
    """What a release takes from a run's audits: the items reviewers rejected (id -> audit,
    cause, reviewers; the majority rule of ``handedit.audit.item_verdicts``) and each audit's
    precision (name -> precision, its 95 % interval, kept items reviewed)."""
    from handedit.audit import item_verdicts, latest, report

    rejected, summary = {}, {}
    for name in audit_names(loc):
        _, items = read_sample(loc, name)
        verdicts = latest(read_verdicts(loc, name))
        rows = item_verdicts(items, verdicts)
        for r in rows[rows["verdict"] == "reject"].itertuples(index=False):
            rejected[r.id] = {"audit": name, "cause": r.cause, "reviewers": int(r.reviewers)}
        rep = report(items, verdicts)
        summary[name] = {k: rep[k] for k in ("precision", "precision_ci", "n_kept_reviewed", "n_reviewed", "n_items")}
    return rejected, summary


__all__ = ["add_verdict", "audit_dir", "audit_names", "pair_views", "pairs", "release_view", "read_sample", "read_verdicts", "write_sample"]

