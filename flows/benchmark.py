"""Benchmark drivers: build a test set from a curated store, run an editor over it.

    build_testset(store, bench, n_sources, bank=...)   -> the folder + toolkit manifest
    run_editor(bench, name, editor, concurrency=4)      -> predictions + records (resumable)

Editors are I/O-bound (HTTP APIs, or local models that own a GPU), so they run in a
bounded thread pool on the driver rather than on the Dask cluster; metric scoring,
which is CPU-bound, is the Prefect/Dask flow in ``flows.evaluate``.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from handedit.benchmark.editors import EditorError, EditRequest
from handedit.benchmark.manifest import ManifestError, ManifestItem
from handedit.benchmark.prices import price_per_image
from handedit.benchmark.testset import TRACK_NAMES, TestItem, instruction, item_id, select_frames
from handedit.embodiments import get_embodiment
from handedit.reasons import Reason
from handedit.storage import Location, Unit, open_store
from handedit.storage.benchmark import (BenchDir, BenchIOError, append_jsonl, decode_image, encode_png, iter_jsonl, read_json,
                               read_image, write_bytes, write_image, write_json, write_jsonl, write_text)
from handedit.storage.integrity import VerifiedReads, require_complete
from handedit.storage.layout import SCOPE_MASK
from handedit.storage.store import now_iso, read_array

log = logging.getLogger("handedit.bench")


# ----------------------------------------------------------------------------- build


def _kept(root, clip: str, emb: str) -> np.ndarray | None:
    unit = Unit("qc", clip, embodiment=emb)
    if unit.path not in root:
        return None
    return read_array(root[unit.path]["status"]) == Reason.OK


def _replaced(root, clip: str, emb: str, frame: int) -> np.ndarray:
    """(S,) hands of a kept frame whose robot replaced them (QC ``hand_status`` OK)."""
    return read_array(root[Unit("qc", clip, embodiment=emb).path]["hand_status"], frame) == Reason.OK


PSEUDO_GT = ("harmonized", "composite")


def build_testset(store: str | Path, bench: str | Path, n_sources: int = 1000, embodiments: list[str] | None = None,
                  bank: str | Path | None = None, seed: int = 0, tracks: tuple[str, ...] = ("hand", "hand_arm"),
                  pseudo_gt: str = "harmonized", toolkit_references: str | Path | None = None) -> dict:
    """Write the two tracks' items (N source frames x the track's embodiments) and the manifest.

    ``pseudo_gt``: the harmonized composite (the paper) or the unharmonized one (what the
    toolkit's README says its main benchmark uses). ``toolkit_references``: the authors'
    reference folder (one render per target, ``hand-only/``, ``hand-arm/``) as the items'
    reference views, with the short descriptions the toolkit conditions on, instead of the
    project's rendered bank. Without either, items have no reference views: editors get no
    render and ID fidelity's S_ref is skipped (logged). Returns the folder's meta.
    """
    from handedit.storage.location import staged_dir

    root = open_store(store)
    from handedit.storage.summary import curated_clips

    clips = curated_clips(root)
    require_complete(Location(store), clips, "bench build")
    if pseudo_gt not in PSEUDO_GT:
        raise ValueError(f"pseudo_gt must be one of {PSEUDO_GT}, got {pseudo_gt!r}")
    with staged_dir(bench) as tmp:  # the folder appears only once complete
        return _build(StoreItems(root, clips, pseudo_gt), store, BenchDir(tmp), n_sources, embodiments, bank, seed, tracks,
                      toolkit_references)


class StoreItems:
    """Test-set inputs from a curated store. A hand-arm frame whose base waits for an operator
    (``review: manual``, not yet decided) is not an item, as it is not released
    (``held_back_unreviewed`` counts them)."""

    def __init__(self, root, clips, pseudo_gt: str = "harmonized"):
        self.root, self.clips, self.pseudo_gt = root, clips, pseudo_gt
        self.reads = VerifiedReads(root)
        self.embodiments = {e: get_embodiment(e).track for c in clips
                            for e in (root[f"clips/{c}/embodiments"].group_keys() if f"clips/{c}/embodiments" in root else [])}
        self.held_back_unreviewed = 0

    def kept(self, clip: str, emb: str) -> np.ndarray | None:
        from handedit.storage.provenance import pending_review
        from handedit.storage.ledger import unit_sides
        from handedit.storage.provenance import read_records

        kept = _kept(self.root, clip, emb)
        if kept is None or self.embodiments.get(emb) != "hand_arm":
            return kept
        pending = pending_review(read_records(self.root, Unit("retarget", clip, embodiment=emb)))
        qc = Unit("qc", clip, embodiment=emb)
        waiting = [k for k, side in enumerate(unit_sides(self.root, qc)) if side in pending]
        if not waiting:
            return kept
        held = kept & (read_array(self.root[qc.path]["hand_status"])[:, waiting] == Reason.OK).any(1)
        self.held_back_unreviewed += int(held.sum())
        return kept & ~held

    def item(self, clip: str, emb: str, frame: int, scope: str):
        """(src, gt, human mask, robot mask, object mask or None) of one kept pair, each
        chunk re-hashed against its record first (``storage.integrity.VerifiedReads``)."""
        root, reads, src = self.root, self.reads, Unit("ingest", clip)
        humans = reads.frame(Unit("segment", clip), SCOPE_MASK[scope], frame)  # (S,H,W) per hand
        obj = reads.frame(src, "object_mask", frame) if "object_mask" in root[src.path] else None
        stage = "harmonize" if self.pseudo_gt == "harmonized" else "composite"
        gt = reads.frame(Unit(stage, clip, embodiment=emb), "image", frame)
        robots = reads.frame(Unit("composite", clip, embodiment=emb), "robot_mask", frame)
        replaced = _replaced(root, clip, emb, frame)
        return reads.frame(src, "frames", frame), gt, humans[replaced].any(0), robots[replaced].any(0), obj


class ReleaseItems:
    """Test-set inputs from a published release: its pairs table and its shards."""

    def __init__(self, release: str):
        from handedit.storage.releases import ShardReader, read_pairs, split_release

        self.loc, self.version = split_release(release)
        self.pairs = read_pairs(self.loc, self.version)
        self.clips = sorted(set(self.pairs["clip"]))
        self.embodiments = dict(zip(self.pairs["embodiment"], self.pairs["track"]))
        self.shards = ShardReader(self.loc)

    def kept(self, clip: str, emb: str) -> np.ndarray | None:
        rows = self.pairs[(self.pairs["clip"] == clip) & (self.pairs["embodiment"] == emb)]
        if not len(rows):
            return None
        k = np.zeros(int(rows["frame"].max()) + 1, bool)
        k[rows["frame"].to_numpy()] = True
        return k

    def item(self, clip: str, emb: str, frame: int, scope: str):
        import json

        from handedit.release.samples import sample_key

        pairs = self.pairs
        shard = pairs.loc[(pairs["clip"] == clip) & (pairs["embodiment"] == emb) & (pairs["frame"] == frame), "shard"].iloc[0]
        key = sample_key(clip, emb, frame)

        def image(name: str) -> np.ndarray:
            return decode_image(self.shards.member(shard, key, name), f"{key}.{name}")

        masks = [image(n)[..., 0] > 127 for n in ("human_mask.png", "robot_mask.png", "object_mask.png")]
        has_obj = json.loads(self.shards.member(shard, key, "json")).get("has_object")
        return image("src.png"), image("gt.png"), masks[0], masks[1], masks[2] if has_obj else None


def build_testset_from_release(release: str | Path, bench: str | Path, n_sources: int = 1000,
                               embodiments: list[str] | None = None, bank: str | Path | None = None, seed: int = 0,
                               tracks: tuple[str, ...] = ("hand", "hand_arm"), pseudo_gt: str = "harmonized",
                               toolkit_references: str | Path | None = None) -> dict:
    """The same test set, from a published release (``<releases>/<version>``) instead of a store."""
    from handedit.storage.location import staged_dir

    if pseudo_gt != "harmonized":
        raise ValueError(f"a release's shards hold the harmonized pseudo-GT only; build from its store (--store) for "
                         f"pseudo_gt={pseudo_gt!r}")
    items = ReleaseItems(str(release))
    with staged_dir(bench) as tmp:
        return _build(items, str(release), BenchDir(tmp), n_sources, embodiments, bank, seed, tracks, toolkit_references)


def _build(source, store, out: BenchDir, n_sources, embodiments, bank, seed, tracks, toolkit_references=None) -> dict:
    stored_embs = source.embodiments
    wanted = embodiments or sorted(stored_embs)
    unknown = [e for e in wanted if e not in stored_embs]
    if unknown:
        raise ValueError(f"embodiment(s) {unknown} were not curated into {store} (it has {sorted(stored_embs)})")
    refs = _toolkit_refs(out, wanted, toolkit_references) if toolkit_references else _write_refs(out, wanted, bank)
    items: list[TestItem] = []
    for scope in tracks:
        embs = [e for e in wanted if stored_embs[e] == scope]
        if not embs:
            continue
        kept = {c: {e: k for e in embs if (k := source.kept(c, e)) is not None} for c in source.clips}
        for sf in select_frames(kept, n_sources, seed):
            for emb in embs:
                if not kept[sf.clip].get(emb, np.zeros(0, bool))[sf.frame:sf.frame + 1].any():
                    continue
                e = get_embodiment(emb)
                iid = item_id(scope, sf.clip, sf.frame, emb)
                src, gt, human, robot, obj = source.item(sf.clip, emb, sf.frame, scope)
                write_image(out.item_file(iid, "src"), src)
                write_image(out.item_file(iid, "gt"), gt)
                write_image(out.item_file(iid, "human_mask"), human)
                write_image(out.item_file(iid, "robot_mask"), robot)
                write_image(out.item_file(iid, "test_mask"), human | robot)
                if obj is not None:
                    write_image(out.item_file(iid, "object_mask"), obj)
                desc = refs.get(emb, {}).get("description") or e.description
                items.append(TestItem(iid, scope, sf.clip, sf.frame, emb, e.name, desc,
                                      instruction(scope, e.name, desc), len(refs.get(emb, {}).get("views", [])),
                                      {"has_object": obj is not None}))
    manifest = [manifest_item(out, it, refs.get(it.embodiment, {}), pred="") for it in items]
    write_jsonl(out.manifest, [m.to_record(out.root) for m in manifest])
    meta = {"created": now_iso(), "store": str(store), "bank": str(bank) if bank else None, "n_sources": n_sources,
            "pseudo_gt": getattr(source, "pseudo_gt", "harmonized"),
            "references": f"toolkit: {toolkit_references}" if toolkit_references else ("bank" if bank else None),
            "seed": seed, "items": [asdict(i) for i in items],
            "held_back_unreviewed": getattr(source, "held_back_unreviewed", 0),
            "tracks": {s: sorted({i.embodiment for i in items if i.scope == s}) for s in tracks}}
    write_json(out.meta, meta)
    return meta


def _write_refs(out: BenchDir, embs: list[str], bank: str | Path | None) -> dict[str, dict]:
    if bank is None:
        log.error("no reference bank given: items get no reference render; ID fidelity's S_ref is skipped "
                  "(build one with `handedit bank build --out bank.zarr`)")
        return {}
    from handedit.storage.bank import read_bank

    refs = {}
    for emb in embs:
        rgb, mask, desc, _name = read_bank(bank, emb)
        views = []
        for v in range(rgb.shape[0]):
            a, b = out.ref_files(emb, v)
            write_image(a, rgb[v])
            write_image(b, mask[v])
            views.append((str(a), str(b)))
        refs[emb] = {"views": views, "description": desc}
    return refs


def _toolkit_refs(out: BenchDir, embs: list[str], folder: str | Path) -> dict[str, dict]:
    """The authors' reference renders (no masks: the toolkit ships none) and short descriptions."""
    import shutil

    from handedit.benchmark.targets import compact_descriptor, toolkit_reference_renders

    renders = toolkit_reference_renders(folder)
    missing = [e for e in embs if e not in renders]
    if not renders:
        raise FileNotFoundError(f"{folder}: no toolkit reference renders (expected hand-only/*.png and hand-arm/*.png, "
                                f"e.g. ../shared/benchmark/handedit-toolkit/reference)")
    if missing:
        raise FileNotFoundError(f"{folder}: no toolkit reference render for {missing}")
    refs = {}
    for emb in embs:
        dst, _ = out.ref_files(emb, 0)
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(renders[emb], dst)
        refs[emb] = {"views": [(str(dst), "")], "description": compact_descriptor(get_embodiment(emb).description) + "."}
    return refs


def manifest_item(out: BenchDir, it: TestItem, ref: dict, pred: str) -> ManifestItem:
    views = ref.get("views", [])
    obj = out.item_file(it.id, "object_mask")
    return ManifestItem(
        id=it.id, replacement_scope=it.scope, target_name=it.target_name,
        src_path=str(out.item_file(it.id, "src")), pred_path=pred, gt_path=str(out.item_file(it.id, "gt")),
        gt_mask_path=str(out.item_file(it.id, "robot_mask")), test_mask_path="",  # the prediction's robot mask: editors give none
        human_mask_path=str(out.item_file(it.id, "human_mask")), robot_mask_path=str(out.item_file(it.id, "robot_mask")),
        object_mask_path=str(obj) if it.extra.get("has_object") else "",
        urdf_ref_paths=[a for a, _ in views], urdf_mask_paths=[b for _, b in views if b],
        extra={"embodiment": it.embodiment, "instruction": it.instruction, "description": it.description,
               "clip": it.clip, "frame": it.frame},
    )


def load_manifest(path: str | Path, relative_to: str = "manifest") -> tuple[list[ManifestItem], list[dict]]:
    """(valid items, per-line errors {line, id, error}); a bad line never stops the rest.

    ``relative_to``: ``manifest`` (the project's test sets) or ``cwd`` (the toolkit's rule)."""
    path = Path(path)
    if relative_to not in ("manifest", "cwd"):
        raise ValueError(f"relative_to must be 'manifest' or 'cwd', got {relative_to!r}")
    base = path.parent if relative_to == "manifest" else Path.cwd()
    items, errors, seen = [], [], set()
    for no, obj, err in iter_jsonl(path):
        if err:
            errors.append({"line": no, "id": None, "error": err})
            continue
        try:
            it = ManifestItem.from_record(obj, base=base, where=f"{path}:{no}: ")
        except ManifestError as exc:
            errors.append({"line": no, "id": obj.get("id"), "error": str(exc)})
            continue
        if it.id in seen:
            errors.append({"line": no, "id": it.id, "error": f"{path}:{no}: duplicate id {it.id!r}"})
            continue
        seen.add(it.id)
        items.append(it)
    return items, errors


def export_manifest(bench: str | Path, editor: str | None, dest: str | Path, absolute: bool = False) -> Path:
    """The test set's manifest with ``pred_path`` pointing at ``editor``'s predictions, in the
    toolkit's spellings: paths relative to ``dest``'s folder, or absolute (what the toolkit's
    ``eval.py`` opens from any working directory)."""
    out = BenchDir(Path(bench))
    items, errors = load_manifest(out.manifest)
    if errors:
        raise BenchIOError(f"{out.manifest} has invalid lines: {errors[:3]}")
    dest = Path(dest)
    if editor:
        for it in items:
            it.pred_path = str(out.prediction(editor, it.id))
    write_jsonl(dest, [it.to_record(None if absolute else dest.parent, absolute=absolute) for it in items])
    return dest


# ----------------------------------------------------------------------------- run an editor


@dataclass
class RunSummary:
    editor: str
    model: str
    ran: int
    ok: int
    failed: int
    skipped: int
    cost_usd: float | None
    seconds: float
    failures: list[dict]
    wrong_size: list[dict] = field(default_factory=list)  # ok, but not the source's size: {id, size, source}


def run_editor(bench: str | Path, name: str, editor, concurrency: int = 4, max_tries: int = 3,
               backoff_s: float = 2.0, limit: int | None = None, price: float | None = None) -> RunSummary:
    """Run ``editor`` (``.edit(EditRequest) -> bytes``, ``.model``) over every item.

    Resumable: an item whose prediction PNG exists is skipped (PNGs are written
    atomically, so an existing file is complete). Transient errors are retried with
    exponential backoff; each finished item appends one record (ok or failed, with the
    error) to ``predictions/<name>/records.jsonl``. Cost = price per image (the
    paper's roster for known models, or ``price``) x successful images.
    """
    out = BenchDir(Path(bench))
    items, errors = load_manifest(out.manifest)
    if errors:
        raise BenchIOError(f"{out.manifest} has invalid lines, rebuild the test set: {errors[:3]}")
    if limit is not None:
        items = items[:limit]
    unit_price = price if price is not None else price_per_image(getattr(editor, "model", name))
    todo = [it for it in items if not out.prediction(name, it.id).is_file()]
    t0 = time.monotonic()
    failures, wrong, ok = [], [], 0

    def one(it: ManifestItem) -> dict:
        req = EditRequest(it.id, Path(it.src_path), Path(it.urdf_ref_paths[0]) if it.urdf_ref_paths else None,
                          it.instruction, out.prediction(name, it.id), Path(it.gt_path))
        started, last = time.monotonic(), ""
        for attempt in range(1, max_tries + 1):
            try:
                data = editor.edit(req)
                image = decode_image(data, f"{name} output for {it.id}")
                write_bytes(req.out_path, encode_png(image))
                rec = {"status": "ok", "attempts": attempt, "height": image.shape[0], "width": image.shape[1],
                       "seconds": time.monotonic() - started}
                src_hw = read_image(req.src_path).shape[:2]
                if tuple(image.shape[:2]) != tuple(src_hw):  # scored only after a resize: say so
                    rec.update(flags=["wrong_size"], src_height=int(src_hw[0]), src_width=int(src_hw[1]))
                return rec
            except (EditorError, BenchIOError, OSError) as exc:
                last = f"{type(exc).__name__}: {exc}"
                if not getattr(exc, "transient", isinstance(exc, OSError)) or attempt == max_tries:
                    break
                time.sleep(backoff_s * 2 ** (attempt - 1))
        return {"status": "failed", "attempts": attempt, "error": last, "seconds": time.monotonic() - started}

    with ThreadPoolExecutor(max_workers=max(1, concurrency)) as pool:
        futures = {pool.submit(one, it): it for it in todo}
        for fut in as_completed(futures):
            it = futures[fut]
            rec = {"id": it.id, "editor": name, "model": getattr(editor, "model", name), "finished": now_iso(), **fut.result()}
            rec["cost_usd"] = unit_price if rec["status"] == "ok" and unit_price is not None else 0.0 if unit_price is not None else None
            append_jsonl(out.records(name), rec)  # only this driver thread appends
            if rec["status"] == "ok":
                ok += 1
                if "wrong_size" in rec.get("flags", []):
                    wrong.append({"id": it.id, "size": f"{rec['width']}x{rec['height']}",
                                  "source": f"{rec['src_width']}x{rec['src_height']}"})
                    log.warning("%s returned %s for %s, whose source is %s", name, wrong[-1]["size"], it.id,
                                wrong[-1]["source"])
            else:
                failures.append({"id": it.id, "error": rec["error"]})
                log.warning("%s failed on %s: %s", name, it.id, rec["error"])
    return RunSummary(name, getattr(editor, "model", name), len(todo), ok, len(failures), len(items) - len(todo),
                      editor_cost(bench, name), time.monotonic() - t0, failures, wrong)


def editor_cost(bench: str | Path, name: str) -> float | None:
    """Total accounted cost over every run of ``name`` (None when no price is known)."""
    path = BenchDir(Path(bench)).records(name)
    if not path.is_file():
        return None
    costs = [r.get("cost_usd") for _, r, e in iter_jsonl(path) if r]
    known = [c for c in costs if c is not None]
    return float(sum(known)) if known else None


def track_title(scope: str) -> str:
    return TRACK_NAMES[scope]


def testset_meta(bench: str | Path) -> dict:
    return read_json(BenchDir(Path(bench)).meta)


# ----------------------------------------------------------------------------- report


def evaluated_metrics(bench: str | Path) -> dict[str, dict[str, dict[str, float]]]:
    """track -> editor -> metric means, from every evaluated editor's results (None for a metric
    not computed)."""
    results = Path(bench) / "results"
    out: dict = {}
    for folder in sorted(results.iterdir()) if results.is_dir() else []:
        if (folder / "summary.json").is_file():
            for track, t in (read_json(folder / "summary.json").get("tracks") or {}).items():
                out.setdefault(track, {})[folder.name] = {k: (float("nan") if v is None else v) for k, v in t["metrics"].items()}
    return out


def write_report(bench: str | Path, editors: list[str] | None = None) -> dict[str, list[Path]]:
    """Tables (Markdown, LaTeX, CSV) and a radar PNG per track from results/*/summary.json."""
    from handedit.benchmark.report import REFERENCE_ROWS, radar_png, track_tables

    out = BenchDir(Path(bench))
    results = out.root / "results"
    found = sorted(p.name for p in results.iterdir() if (p / "summary.json").is_file()) if results.is_dir() else []
    names = editors or found
    if not names:
        raise BenchIOError(f"no results under {results}; run `handedit bench evaluate` first")

    def project_summary(name: str) -> dict:  # a toolkit-protocol run keeps the report's shape beside the toolkit's
        folder = out.results(name)
        return read_json(folder / "report_summary.json" if (folder / "report_summary.json").is_file() else folder / "summary.json")

    summaries = {n: project_summary(n) for n in names}
    human = out.report / "human.md"  # `bench human-report`
    written: dict[str, list[Path]] = {}
    md_all = []
    for scope, title in TRACK_NAMES.items():
        rows = {n: s["tracks"][scope]["metrics"] for n, s in summaries.items() if scope in s.get("tracks", {})}
        if not rows:
            continue
        rows = {n: {k: (float("nan") if v is None else v) for k, v in r.items()} for n, r in rows.items()}
        files = []
        for key, table in track_tables(title, rows).items():
            md_all.append(table.markdown())
            files.append(write_text(out.report / f"{scope}_{key}.tex", table.latex()))
            files.append(write_text(out.report / f"{scope}_{key}.csv", table.csv()))
        editors_only = {n: r for n, r in rows.items() if n not in REFERENCE_ROWS} or rows  # like the paper's radar
        files.append(write_image(out.report / f"{scope}_radar.png", radar_png(title, editors_only)))
        written[scope] = files
    skipped = sorted({m for s in summaries.values() for m in s.get("skipped", [])})
    notes = [f"\nSkipped metrics (missing encoder or judge): {', '.join(skipped)}"] if skipped else []
    for n, s in summaries.items():
        if s.get("n_errors"):
            notes.append(f"\n{n}: {s['n_errors']} item(s) not scored (see results/{n}/items.csv)")
    md = write_text(out.report / "tables.md", "\n".join(md_all) + "\n".join(notes) + "\n"
                    + ("\n" + human.read_text() if human.is_file() else ""))
    written.setdefault("all", []).append(md)
    return written
