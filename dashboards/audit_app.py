"""The audit's review page (``handedit audit serve``): one sampled pair at a time, as the
paper's annotator saw it, keep or reject with a primary cause, by keyboard or mouse.

Each verdict is stored the moment it is given (``storage.audit.add_verdict``: one file each),
so closing the tab or a crash loses nothing; reopening the page as the same reviewer resumes
at the first item they have not judged. Reviewers are told apart by the name they type (kept
in the browser); a reviewer's later verdict on an item replaces the earlier one.

    GET  /                       the page
    GET  /api/state?reviewer=R   the items and R's latest verdicts
    GET  /api/view/<k>.png       item k's annotator view
    POST /api/verdict            {"item", "verdict", "cause", "reviewer"} -> 400 with the reason if bad
"""

from __future__ import annotations

import html

import cv2
import pandas as pd
from fastapi import FastAPI, HTTPException, Request
from fastapi.responses import HTMLResponse, Response

from handedit.audit import CAUSES, annotator_view, latest, parse_verdict
from handedit.storage import Location, open_store
from handedit.storage.audit import add_verdict, pair_views, read_sample, read_verdicts

KEYS = {cause: str(i + 1) for i, cause in enumerate(CAUSES)}  # 1-5: reject with that cause; k: keep

PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>handedit audit: __NAME__</title>
<style>
 body { font: 14px system-ui, sans-serif; margin: 16px; background: #fafafa; color: #222; }
 #bar { display: flex; gap: 16px; align-items: center; flex-wrap: wrap; }
 #view { width: 100%; max-width: 1600px; border: 1px solid #ccc; margin: 12px 0; background: #888; }
 .legend { color: #555; font-size: 12px; }
 button { font: inherit; padding: 6px 12px; margin: 2px; cursor: pointer; }
 #keep { background: #d9f2d9; } .reject { background: #f7dcdc; }
 .given { outline: 3px solid #333; }
 #info { font-family: monospace; }
</style></head><body>
<div id="bar">
 <label>reviewer <input id="reviewer" placeholder="your name" size="16"></label>
 <span id="progress"></span>
 <button id="prev" title="previous (left arrow)">&larr;</button>
 <button id="next" title="next (right arrow)">&rarr;</button>
</div>
<div id="info"></div>
<img id="view" alt="annotator view">
<div class="legend">source | human mask | restored background | pseudo-GT | robot mask</div>
<p>
 <button id="keep" title="k">keep (k)</button>
 __REJECT_BUTTONS__
</p>
<p class="legend">keys: k keep; 1-5 reject with that primary cause; arrows move; a verdict is saved at once and moves on.</p>
<script>
const CAUSES = __CAUSES__;
let items = [], mine = {}, at = 0, loads = 0;
const $ = (id) => document.getElementById(id);
const who = () => $("reviewer").value.trim();
$("reviewer").value = new URLSearchParams(location.search).get("reviewer") || localStorage.getItem("handedit-reviewer") || "";

async function load() {
  if (!who()) { $("progress").textContent = "type your name to start"; return; }
  localStorage.setItem("handedit-reviewer", who());
  const mine_load = ++loads;
  const state = await (await fetch("api/state?reviewer=" + encodeURIComponent(who()))).json();
  if (mine_load !== loads) return;  // a newer load (another name) answers instead
  items = state.items; mine = state.verdicts;
  const open = items.findIndex((it) => !(it.id in mine));
  show(open < 0 ? 0 : open);
}
function show(k) {
  if (!items.length) return;
  at = Math.max(0, Math.min(items.length - 1, k));
  const it = items[at], v = mine[it.id];
  $("view").src = "api/view/" + at + ".png";
  $("info").textContent = "item " + (at + 1) + " of " + items.length + ": " + it.id + " (" + it.track + ")"
    + (v ? " \u2014 your verdict: " + v.verdict + (v.cause ? " / " + v.cause : "") : "");
  const n = Object.keys(mine).length;
  $("progress").textContent = n + " of " + items.length + " reviewed by " + who();
  $("progress").dataset.reviewed = n;
  document.querySelectorAll("button").forEach((b) => b.classList.remove("given"));
  if (v) $(v.verdict === "keep" ? "keep" : "reject-" + v.cause).classList.add("given");
}
async function give(verdict, cause) {
  if (!who() || !items.length) return;
  const it = items[at];
  const r = await fetch("api/verdict", {method: "POST", headers: {"content-type": "application/json"},
    body: JSON.stringify({item: it.id, verdict: verdict, cause: cause, reviewer: who()})});
  if (!r.ok) { alert((await r.json()).detail); return; }
  mine[it.id] = {verdict: verdict, cause: cause};
  const next = items.findIndex((x, i) => i > at && !(x.id in mine));
  show(next < 0 ? at : next);
}
$("keep").onclick = () => give("keep", null);
CAUSES.forEach((c) => { $("reject-" + c).onclick = () => give("reject", c); });
$("prev").onclick = () => show(at - 1);
$("next").onclick = () => show(at + 1);
$("reviewer").onchange = () => { $("reviewer").blur(); load(); };
document.addEventListener("keydown", (e) => {
  if (e.target === $("reviewer")) { if (e.key === "Enter") $("reviewer").blur(); return; }  // blur: change: load
  if (e.key === "k") give("keep", null);
  else if (e.key >= "1" && e.key <= String(CAUSES.length)) give("reject", CAUSES[Number(e.key) - 1]);
  else if (e.key === "ArrowRight") show(at + 1);
  else if (e.key === "ArrowLeft") show(at - 1);
});
load();
</script></body></html>
"""


def page(name: str) -> str:
    buttons = " ".join(f'<button id="reject-{c}" class="reject" title="{KEYS[c]}">reject: {c} ({KEYS[c]})</button>'
                       for c in CAUSES)
    return (PAGE.replace("__NAME__", html.escape(name)).replace("__REJECT_BUTTONS__", buttons)
            .replace("__CAUSES__", "[" + ", ".join(f'"{c}"' for c in CAUSES) + "]"))


def make_app(run: str, name: str):
    """The FastAPI app of one audit of one run."""
    loc = Location(run)
    found = read_sample(loc, name)
    if found is None:
        raise ValueError(f"no audit '{name}' in {loc.url}: run `handedit audit sample {run} --n N --name {name}` first")
    _, items = found
    root = open_store(run)
    known = set(items["id"])
    app = FastAPI(title=f"handedit audit {name}")

    @app.get("/", response_class=HTMLResponse)
    def index() -> str:
        return page(name)

    @app.get("/api/state")
    def state(reviewer: str = "") -> dict:
        verdicts = latest(read_verdicts(loc, name))
        own = verdicts[verdicts["reviewer"] == reviewer.strip()]
        rows = items[["id", "clip", "embodiment", "track", "frame"]].to_dict(orient="records")
        return {"items": [{**r, "frame": int(r["frame"])} for r in rows],
                "verdicts": {r.item: {"verdict": r.verdict, "cause": None if pd.isna(r.cause) else r.cause}
                             for r in own.itertuples(index=False)}}

    @app.get("/api/view/{k}.png")
    def view(k: int) -> Response:
        if not 0 <= k < len(items):
            raise HTTPException(404, f"no item {k}")
        it = items.iloc[k]
        img = annotator_view(**pair_views(root, it["clip"], it["embodiment"], it["track"], int(it["frame"])))
        ok, png = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        return Response(png.tobytes(), media_type="image/png", headers={"cache-control": "max-age=3600"})

    @app.post("/api/verdict")
    async def verdict(request: Request) -> dict:
        try:
            v = parse_verdict(await request.json(), known)
        except ValueError as exc:
            raise HTTPException(400, str(exc))
        add_verdict(loc, name, v)
        return {"ok": True}

    return app


__all__ = ["make_app", "page"]
