"""The QA page of a published release: one static HTML file (images inlined), so it works
from object storage and from a laptop.

    handedit dashboard --release runs/releases/v0002      -> runs/releases/v0002/qa.html

Counts per track, dataset and embodiment; kept rate per stage; the failure breakdown laid
out like the paper's table; per-embodiment galleries (source | pseudo-GT | robot mask)
read from the release's own shards; the changelog against the parent; links to the Dask
dashboard and the Prefect run that published it. ``#qa-check`` reports, once the page has
loaded, how many images decoded (``data-images`` / ``data-broken``), for headless checks.
"""

from __future__ import annotations

import html
import json

import numpy as np

from handedit.dashboards.release import _png, _table, esc, safe_url
from handedit.images import decode_rgb
from handedit.release.samples import sample_key
from handedit.storage import Location
from handedit.storage.layout import stage_names
from handedit.storage.releases import ShardReader, read_pairs, read_release, split_release

PER_EMBODIMENT = 4
CHECK_SCRIPT = """<script>
window.addEventListener('load', () => {
  const imgs = [...document.images];
  const broken = imgs.filter(i => !(i.complete && i.naturalWidth > 0)).length;
  const el = document.getElementById('qa-check');
  el.dataset.images = imgs.length; el.dataset.broken = broken; el.textContent = `${imgs.length} images, ${broken} broken`;
});
</script>"""


def _gallery(loc: Location, pairs) -> str:
    shards = ShardReader(loc)
    out = []
    for emb, rows in pairs.groupby("embodiment"):
        picks = rows.iloc[np.linspace(0, len(rows) - 1, min(PER_EMBODIMENT, len(rows))).astype(int)]
        cells = []
        for _, r in picks.iterrows():
            key = sample_key(r["clip"], r["embodiment"], r["frame"])
            images = [decode_rgb(shards.member(r["shard"], key, n)) for n in ("src.png", "gt.png", "robot_mask.png")]
            cells.append(f"<div class=trip><b>{html.escape(r['clip'])} frame {int(r['frame'])}</b><br>"
                         + "".join(_png(im) for im in images) + "</div>")
        out.append(f"<h3>{html.escape(emb)} ({len(rows)} pairs)</h3>" + "".join(cells))
    return "".join(out) or "<p>no pairs</p>"


def render_release_page(loc: Location, version: str) -> str:
    m = read_release(loc, version)
    pairs = read_pairs(loc, version)
    sheet = json.loads(loc.read_bytes(f"{version}/datasheet.json"))
    log = json.loads(loc.read_bytes(f"{version}/changelog.json"))
    counts = m["counts"]
    order = {s: i for i, s in enumerate(stage_names())}
    kept = [{"stage": s, "OK": r["ok"], "given": r["given"], "kept rate": f"{100 * r['rate']:.1f}%" if r["rate"] is not None else "-"}
            for s, r in sorted(sheet["kept_rate"].items(), key=lambda kv: order.get(kv[0], 99))]
    total = sheet["rejections"]["total"]
    causes = [{"primary failure cause": r["cause"], "share of non-kept frames": f"{r['count']} / {total} ({100 * r['share']:.2f}%)"}
              for r in sheet["rejections"]["by_cause"]]
    per = [{"by": k, "name": name, "pairs": n} for k in ("track", "dataset", "embodiment") for name, n in sheet["counts"][k].items()]
    changes = [{"change": k, "pairs": len(log[k]), "first": ", ".join(log[k][:5])} for k in ("added", "removed", "changed")]
    links = m.get("links") or {}
    link_html = " | ".join(f'<a href="{safe_url(u)}">{esc(k)}</a>' if safe_url(u) else f"{esc(k)}: {esc(u)}"
                           for k, u in links.items() if u) or "none recorded"
    shards = [{"shard": str(s["key"])[:12], "pairs": s["pairs"], "MB": f"{float(s['bytes']) / 1e6:.2f}",
               "sha256": str(s["sha256"])[:16], "reused": s["reused"]} for s in m["shards"]]
    style = ("body{font-family:sans-serif;margin:1.5em}table{border-collapse:collapse;margin-bottom:1em}"
             "td,th{border:1px solid #ccc;padding:2px 6px;font-size:13px}.trip{display:inline-block;margin:4px}")
    return f"""<!doctype html><html><head><meta charset=utf-8><title>handedit release {html.escape(version)}</title>
<style>{style}</style></head><body>
<h1>handedit release {html.escape(version)}</h1>
<p id=counts data-pairs="{esc(counts['pairs'])}" data-shards="{esc(counts['shards'])}">{esc(counts['pairs'])} pairs in
{esc(counts['shards'])} shards ({esc(counts['shards_reused'])} reused from {esc(m['parent'] or '-')}); created
{esc(m['created'])} by {esc(m['code_version'])}</p>
<p>links: {link_html}</p>
<p id=qa-check></p>
<h2>Pairs</h2>{_table(per, ['by', 'name', 'pairs'])}
<h2>Kept rate per stage</h2>{_table(kept, ['stage', 'OK', 'given', 'kept rate'])}
<h2 id=breakdown>Rejections by primary cause</h2>{_table(causes, ['primary failure cause', 'share of non-kept frames'])}
<h2>Changes against {html.escape(str(m['parent'] or '(first release)'))}</h2>{_table(changes, ['change', 'pairs', 'first'])}
<h2>Galleries: source | pseudo-GT | robot mask</h2>{_gallery(loc, pairs)}
<h2>Shards</h2>{_table(shards, ['shard', 'pairs', 'MB', 'sha256', 'reused'])}
{CHECK_SCRIPT}</body></html>"""


def write_release_page(release: str, out: str | None = None) -> str:
    """Write the page (default: ``<release>/qa.html``); returns where."""
    from handedit.storage.location import atomic_write

    loc, version = split_release(release)
    page = render_release_page(loc, version)
    if out or loc.is_local:
        return str(atomic_write(out or loc.path(version, "qa.html"), page.encode()))
    loc.write_bytes(f"{version}/qa.html", page.encode())
    return loc.path(version, "qa.html")
