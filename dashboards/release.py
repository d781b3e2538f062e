"""The release / QA page an operator watches: one static HTML file per store.

    handedit dashboard runs/demo            -> runs/demo/qa.html

It shows what was kept and why the rest was not: frames per stage and status, kept
frames per clip x embodiment, rejections by reason and the ledger, sample triplets
(source | harmonized pseudo-GT | robot mask) and the runs with their Dask dashboard
links (live while a run's cluster is up).
"""

from __future__ import annotations

import base64
import html
from pathlib import Path

import cv2
import numpy as np
import zarr

from handedit.reasons import Reason
from handedit.storage import Unit, read_ledger, status_counts
from handedit.storage.ledger import iter_units
from handedit.storage.store import read_array

MAX_LEDGER_ROWS = 300


def _png(rgb: np.ndarray, width: int = 240) -> str:
    h, w = rgb.shape[:2]
    small = cv2.resize(rgb, (width, max(1, int(h * width / w))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(small, cv2.COLOR_RGB2BGR))
    return f'<img src="data:image/png;base64,{base64.b64encode(buf.tobytes()).decode()}">' if ok else ""


def esc(value) -> str:
    """Any value as inert HTML text (store attributes and manifests are data, not markup)."""
    return html.escape(str(value), quote=True)


def safe_url(url) -> str | None:
    """A link target for a page: http(s) or a relative path (``javascript:``, ``data:`` and
    other schemes are dropped), escaped for an attribute."""
    import urllib.parse

    text = str(url or "").strip()
    scheme = urllib.parse.urlsplit(text).scheme.lower()
    if not text or (scheme and scheme not in ("http", "https")):
        return None
    return esc(text)


def _table(rows: list[dict], columns: list[str]) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(r.get(c, '')))}</td>" for c in columns) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def kept_table(root: zarr.Group) -> list[dict]:
    rows = []
    for unit in iter_units(root):
        if unit.stage != "qc":
            continue
        status = read_array(root[unit.path]["status"])
        rows.append({"clip": unit.clip, "embodiment": unit.embodiment, "frames": int(status.size),
                     "kept": int((status == Reason.OK).sum()), "kept %": f"{100 * (status == Reason.OK).mean():.1f}"})
    return rows


def samples(root: zarr.Group, per_unit: int = 3) -> str:
    out = []
    for unit in iter_units(root):
        if unit.stage != "harmonize":
            continue
        status = read_array(root[unit.path]["status"])
        frames = np.flatnonzero(status == Reason.OK)
        if frames.size == 0:
            continue
        picks = frames[np.linspace(0, frames.size - 1, min(per_unit, frames.size)).astype(int)]
        src = root[Unit("ingest", unit.clip).path]["frames"]
        mask = root[Unit("composite", unit.clip, embodiment=unit.embodiment).path]["robot_mask"]
        cells = []
        for t in picks:
            frame = read_array(src, t)
            overlay = frame.copy()
            m = read_array(mask, t).any(0)  # every hand's robot
            overlay[m] = (0.5 * overlay[m] + 0.5 * np.array([0, 160, 255])).astype(np.uint8)
            cells.append(f"<div class=trip><b>frame {t}</b><br>{_png(frame)}{_png(read_array(root[unit.path]['image'], t))}{_png(overlay)}</div>")
        out.append(f"<h3>{html.escape(unit.clip)} &times; {html.escape(unit.embodiment or '')}</h3>" + "".join(cells))
    return "".join(out) or "<p>no harmonized frames yet</p>"


def render_page(root: zarr.Group, title: str) -> str:
    from handedit.storage.location import location_of
    from handedit.storage.shards import run_logs, shard_ids

    loc = location_of(root)
    runs = sorted((log for s in shard_ids(loc) for log in run_logs(loc, s)), key=lambda r: r.get("finished") or "")
    run_rows = [{"shard": r.get("shard"), "started": r.get("started"), "finished": r.get("finished"),
                 "complete": r.get("complete"),
                 "chunks ran/skipped/failed": " ".join(f"{s}:{c['ran']}/{c['skipped']}/{c['failed']}" for s, c in r.get("stages", {}).items())}
                for r in runs[-10:]]
    ledger = read_ledger(root)
    by_reason = (ledger.groupby(["stage", "reason_name"]).size().reset_index(name="frames").to_dict(orient="records")
                 if len(ledger) else [])
    style = ("body{font-family:sans-serif;margin:1.5em}table{border-collapse:collapse;margin-bottom:1em}"
             "td,th{border:1px solid #ccc;padding:2px 6px;font-size:13px}.trip{display:inline-block;margin:4px}")
    return f"""<!doctype html><html><head><meta charset=utf-8><title>{html.escape(title)}</title>
<style>{style}</style></head><body>
<h1>handedit release / QA: {html.escape(title)}</h1>
<p>schema {esc(root.attrs.get('schema_version'))}, {esc(root.attrs.get('frames_per_chunk'))} frames per chunk,
created {esc(root.attrs.get('created'))} by {esc(root.attrs.get('created_by'))}</p>
<h2>Shard runs (last 10)</h2>{_table(run_rows, ['shard', 'started', 'finished', 'complete', 'chunks ran/skipped/failed'])}
<h2>Kept frames (QC OK)</h2>{_table(kept_table(root), ['clip', 'embodiment', 'frames', 'kept', 'kept %'])}
<h2>Frames per stage and status</h2>{_table(status_counts(root).to_dict(orient='records'), ['stage', 'status', 'frames'])}
<h2>Rejections by reason</h2>{_table(by_reason, ['stage', 'reason_name', 'frames'])}
<h2>Samples: source | pseudo-GT | robot mask</h2>{samples(root)}
<h2>Ledger (first {MAX_LEDGER_ROWS} rows of {len(ledger)})</h2>
{_table(ledger.head(MAX_LEDGER_ROWS).to_dict(orient='records'), list(ledger.columns))}
</body></html>"""


def write_page(root: zarr.Group, out: str | Path, title: str = "") -> Path:
    from handedit.storage.location import atomic_write

    out = Path(out)
    return atomic_write(out, render_page(root, title or out.parent.name).encode())
