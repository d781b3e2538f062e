"""The editors' human-evaluation page (``handedit bench rate``): the paper's blinded study.

Each edited output is shown as the paper's annotators saw it: the source image, the text
instruction, the reference render of the target robot and the edited image, with the editor's
name, the metric scores and the pseudo-GT hidden; outputs come in a fixed shuffled order so
editors interleave. The rater scores it 1-5 on the paper's three axes with its rating guide
(keys 1-5 score the highlighted axis and move to the next; or click). A rating is stored when
its three scores are given (one create-once file each, ``storage.benchmark.add_rating``), and
reopening the page as the same rater resumes at the first output they have not rated.

    GET  /                          the page
    GET  /api/state?rater=R         outputs (opaque numbers, instruction) and R's ratings
    GET  /api/image/<k>/<which>     source | reference | output of output k
    POST /api/rating                {"k", "rater", "target", "scene_interaction", "realism"}
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np
from fastapi import FastAPI, HTTPException, Request
from fastapi.responses import FileResponse, HTMLResponse

from handedit.benchmark.human_eval import AXES, AXIS_TITLES, GUIDE, INSTRUCTION, parse_rating
from handedit.storage.benchmark import BenchDir, add_rating, read_ratings

PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>handedit: rate edited images</title>
<style>
 body { font: 14px system-ui, sans-serif; margin: 16px; background: #fafafa; color: #222; }
 #imgs { display: flex; gap: 8px; margin: 10px 0; }
 #imgs figure { margin: 0; flex: 1; } #imgs img { width: 100%; border: 1px solid #ccc; background: #888; }
 figcaption { font-size: 12px; color: #555; }
 table { border-collapse: collapse; font-size: 12px; } td, th { border: 1px solid #ddd; padding: 3px 6px; vertical-align: top; }
 tr.current { outline: 3px solid #333; } td.scores { white-space: nowrap; }
 button { font: inherit; padding: 4px 10px; margin: 1px; cursor: pointer; } button.given { background: #333; color: #fff; }
 #instruction { font-style: italic; } .note { color: #555; font-size: 12px; }
</style></head><body>
<div><label>rater <input id="rater" placeholder="your name" size="16"></label> <span id="progress"></span>
 <button id="prev" title="previous (left arrow)">&larr;</button> <button id="next" title="next (right arrow)">&rarr;</button></div>
<p class="note">__INSTRUCTION__</p>
<div id="info"></div>
<p id="instruction"></p>
<div id="imgs"><figure><img id="source" alt="source"><figcaption>source</figcaption></figure>
 <figure><img id="reference" alt="reference render"><figcaption>reference render of the target robot</figcaption></figure>
 <figure><img id="output" alt="edited image"><figcaption>edited image</figcaption></figure></div>
<table><tr><th>axis</th><th>score</th><th>1</th><th>3</th><th>5</th></tr>__ROWS__</table>
<p class="note">keys: 1-5 score the outlined axis and move to the next; a rating is saved when its three scores are given.</p>
<script>
const AXES = __AXES__;
let outputs = [], rated = {}, at = 0, axis = 0, draft = {}, loads = 0;
const $ = (id) => document.getElementById(id);
const who = () => $("rater").value.trim();
$("rater").value = new URLSearchParams(location.search).get("rater") || localStorage.getItem("handedit-rater") || "";
async function load() {
  if (!who()) { $("progress").textContent = "type your name to start"; return; }
  localStorage.setItem("handedit-rater", who());
  const mine = ++loads;
  const state = await (await fetch("api/state?rater=" + encodeURIComponent(who()))).json();
  if (mine !== loads) return;
  outputs = state.outputs; rated = state.rated;
  const open = outputs.findIndex((o) => !(o.k in rated));
  show(open < 0 ? 0 : open);
}
function paint() {
  AXES.forEach((a, i) => {
    $("row-" + a).classList.toggle("current", i === axis);
    for (let s = 1; s <= 5; s++) $(a + "-" + s).classList.toggle("given", draft[a] === s);
  });
}
function show(k) {
  if (!outputs.length) return;
  at = Math.max(0, Math.min(outputs.length - 1, k));
  const o = outputs[at];
  draft = Object.assign({}, rated[o.k] || {}); axis = 0;
  ["source", "reference", "output"].forEach((w) => { $(w).src = "api/image/" + o.k + "/" + w; });
  $("instruction").textContent = o.instruction;
  $("info").textContent = "output " + (at + 1) + " of " + outputs.length + (o.k in rated ? " (rated; a new rating replaces it)" : "");
  const n = Object.keys(rated).length;
  $("progress").textContent = n + " of " + outputs.length + " rated by " + who();
  $("progress").dataset.rated = n;
  paint();
}
async function score(a, s) {
  if (!who() || !outputs.length) return;
  draft[a] = s; axis = Math.min(AXES.indexOf(a) + 1, AXES.length - 1); paint();
  if (!AXES.every((x) => draft[x])) return;
  const o = outputs[at], body = Object.assign({k: o.k, rater: who()}, draft);
  const r = await fetch("api/rating", {method: "POST", headers: {"content-type": "application/json"}, body: JSON.stringify(body)});
  if (!r.ok) { alert((await r.json()).detail); return; }
  rated[o.k] = Object.assign({}, draft);
  const next = outputs.findIndex((x, i) => i > at && !(x.k in rated));
  show(next < 0 ? at : next);
}
AXES.forEach((a) => { for (let s = 1; s <= 5; s++) $(a + "-" + s).onclick = () => score(a, s); });
$("prev").onclick = () => show(at - 1);
$("next").onclick = () => show(at + 1);
$("rater").onchange = () => { $("rater").blur(); load(); };
document.addEventListener("keydown", (e) => {
  if (e.target === $("rater")) { if (e.key === "Enter") $("rater").blur(); return; }
  if (e.key >= "1" && e.key <= "5") score(AXES[axis], Number(e.key));
  else if (e.key === "ArrowRight") show(at + 1);
  else if (e.key === "ArrowLeft") show(at - 1);
});
load();
</script></body></html>
"""


def page() -> str:
    rows = "".join(
        f'<tr id="row-{a}"><td>{html.escape(AXIS_TITLES[a])}</td><td class="scores">'
        + "".join(f'<button id="{a}-{s}">{s}</button>' for s in range(1, 6))
        + "</td>" + "".join(f"<td>{html.escape(GUIDE[a][s])}</td>" for s in (1, 3, 5)) + "</tr>" for a in AXES)
    return (PAGE.replace("__ROWS__", rows).replace("__INSTRUCTION__", html.escape(INSTRUCTION))
            .replace("__AXES__", "[" + ", ".join(f'"{a}"' for a in AXES) + "]"))


def outputs(bench: str | Path, seed: int = 0) -> list[dict]:
    """Every (item, editor) with a prediction, in a fixed shuffled order (editors interleave)."""
    from handedit.flows.benchmark import load_manifest

    out = BenchDir(Path(bench))
    items, _ = load_manifest(out.manifest)
    preds = out.root / "predictions"
    editors = sorted(p.name for p in preds.iterdir() if p.is_dir()) if preds.is_dir() else []
    found = [{"item": it, "editor": e, "pred": out.prediction(e, it.id)} for it in items for e in editors
             if out.prediction(e, it.id).is_file()]
    order = np.random.default_rng(seed).permutation(len(found))
    return [found[i] for i in order]


def make_app(bench: str | Path, seed: int = 0) -> FastAPI:
    """The FastAPI app of one benchmark folder's rating study."""
    found = outputs(bench, seed)
    if not found:
        raise ValueError(f"{bench} has no predictions to rate: run `handedit bench run --bench {bench} ...` first")
    tracks = {o["item"].id: o["item"].replacement_scope for o in found}
    editors = {o["editor"] for o in found}
    by_pair = {(o["item"].id, o["editor"]): k for k, o in enumerate(found)}
    app = FastAPI(title="handedit human evaluation")

    @app.get("/", response_class=HTMLResponse)
    def index() -> str:
        return page()

    @app.get("/api/state")
    def state(rater: str = "") -> dict:
        rated = {}
        for r in read_ratings(bench):
            k = by_pair.get((r.get("item"), r.get("editor")))
            if k is not None and r.get("rater") == rater.strip():
                rated[k] = {a: r[a] for a in AXES if a in r}
        return {"outputs": [{"k": k, "instruction": o["item"].instruction} for k, o in enumerate(found)], "rated": rated}

    @app.get("/api/image/{k}/{which}")
    def image(k: int, which: str) -> FileResponse:
        if not 0 <= k < len(found) or which not in ("source", "reference", "output"):
            raise HTTPException(404, "no such image")
        it = found[k]["item"]
        path = {"source": it.src_path, "reference": (it.urdf_ref_paths or [""])[0], "output": str(found[k]["pred"])}[which]
        if not path or not Path(path).is_file():
            raise HTTPException(404, f"{which} of output {k} is not in the benchmark folder")
        return FileResponse(path, media_type="image/png")

    @app.post("/api/rating")
    async def rating(request: Request) -> dict:
        try:
            body = await request.json()
            k = body.pop("k") if isinstance(body, dict) else None
            if not isinstance(k, int) or not 0 <= k < len(found):
                raise ValueError(f"output {k!r} is not one of this study's")
            row = {"item": found[k]["item"].id, "editor": found[k]["editor"], **body}
            parse_rating(row, tracks, editors)
            if set(AXES) - set(row):
                raise ValueError(f"a rating gives all three axes {list(AXES)}")
        except ValueError as exc:
            raise HTTPException(400, str(exc))
        add_rating(bench, row)
        return {"ok": True}

    return app


__all__ = ["make_app", "outputs", "page"]
