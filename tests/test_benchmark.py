"""The benchmark end to end: curate a tiny synthetic store, build the test set with a
reference bank, run editors through the command and HTTP adapters, score them with
small ONNX encoders and a fake judge on 127.0.0.1 (Prefect flow on Dask), report.

The oracle editor (returns the pseudo-GT) must beat the copy-the-source editor on every
similarity metric, and the report must say so; bad manifest lines, missing images
and wrong-size predictions are per-item errors while the rest is scored.
"""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest

from _bench_onnx import TOOLKIT_SIZES, write_encoders
from _fake_openai import FakeOpenAI
from handedit.flows.benchmark import build_testset, editor_cost, export_manifest, load_manifest, run_editor, write_report
from handedit.flows.config import ClusterConfig, CurateConfig
from handedit.flows.curate import run_curate
from handedit.flows.evaluate import EvaluateConfig, run_evaluate
from handedit.benchmark.editors import CommandEditor, HttpEditorConfig, HttpImageEditor
from handedit.benchmark.manifest import TOOLKIT_FIELDS
from handedit.embodiments import get_embodiment
from handedit.metrics.vlm import JudgeConfig
from handedit.render.bank import BankConfig, render_bank_views
from handedit.reasons import Reason
from handedit.sources import open_source
from handedit.sources.synthetic import make_clip_specs
from handedit.storage import ChunkRecord, Unit, create_or_open_store, create_unit, write_chunk, write_records
from handedit.storage.bank import BankEntry, write_bank_entry
from handedit.storage.store import set_attrs
from handedit.storage.benchmark import BenchDir, iter_jsonl, read_image, read_mask, write_image

EMB = "allegro"
N_SOURCES = 4
SIMILARITY = {  # metric -> higher is better
    "psnr_full": True, "psnr_bg": True, "psnr_roi": True, "ssim_full": True, "ssim_bg": True, "ssim_roi": True,
    "lpips_full": False, "lpips_bg": False, "lpips_roi": False, "fid_full": False, "fid_roi": False,
    "struct_fidelity": True, "id_fidelity": True,
}


def write_curated_store(path, n_frames: int = 6, rejected: tuple[int, ...] = (2,)):
    """A curated store written through the storage API (what the curate flow leaves
    behind, without its minute of retargeting and rendering): synthetic source frames
    with their exact hand/object masks, a robot mask next to the hand, a pseudo-GT
    that shows the restored background plus a dark-and-white "robot", QC statuses."""
    src = open_source(make_clip_specs(1, seed=5, n_frames=n_frames, width=160, height=120)[0])
    info, ch = src.info(), src.read(0, n_frames)
    clip, f, sizes = info.clip_id, 8, {"H": 120, "W": 160, "S": 1}
    root = create_or_open_store(path, f, "test")
    hand = ch.gt["hand_mask"]
    robot = np.roll(hand, 3, axis=2) | np.roll(hand, -2, axis=1)
    gt = ch.gt["background"].copy()
    stripes = (np.indices((120, 160)).sum(0) // 3 % 2).astype(bool)
    gt[robot & stripes] = (30, 30, 34)
    gt[robot & ~stripes] = (235, 235, 230)
    ok = np.full(n_frames, int(Reason.OK), np.int16)
    qc = ok.copy()
    qc[list(rejected)] = int(Reason.FINGERTIP_ERROR)
    one = ok[:, None]  # one hand
    for unit, arrays, kw in [
        (Unit("ingest", clip), {"frames": ch.frames, "object_mask": ch.object_mask, "status": ok}, {"has_object": True, "has_gt": True}),
        (Unit("segment", clip), {"hand_mask": hand[:, None], "handarm_mask": ch.gt["handarm_mask"][:, None], "status": ok,
                                 "hand_status": one}, {}),
        (Unit("composite", clip, embodiment=EMB), {"image": gt // 2, "robot_mask": robot[:, None], "status": ok,
                                                  "hand_status": one}, {}),  # the unharmonized composite: darker
        (Unit("harmonize", clip, embodiment=EMB), {"image": gt, "status": ok}, {}),
        (Unit("qc", clip, embodiment=EMB), {"status": qc, "hand_status": qc[:, None]}, {}),
    ]:
        create_unit(root, unit, n_frames, sizes, f, **kw)
        digests = write_chunk(root, unit, 0, arrays)  # and its record, as the walk writes it: publishing checks both
        write_records(root, unit, [ChunkRecord(unit.stage, 0, 0, n_frames, "test", 1, {}, {}, outputs=digests)])
    set_attrs(root, "", {"clips": {clip: {"n_frames": n_frames}}, "embodiments": {EMB: {"scope": "hand", "dof": 16}}})
    return path, n_frames - len(rejected)


def write_bank(path):
    e = get_embodiment(EMB)
    r = render_bank_views(EMB, BankConfig(views=2, width=64, height=64))
    write_bank_entry(path, BankEntry(EMB, e.name, e.track, e.description, r.rgb, r.mask, r.camera_from_root, r.qpos, r.K), {})
    return path


@pytest.fixture(scope="module")
def bench(tmp_path_factory, prefect_api, dask_cluster):
    tmp = tmp_path_factory.mktemp("bench")
    store, n_kept = write_curated_store(tmp / "handedit.zarr")
    meta = build_testset(store, tmp / "bench", N_SOURCES, bank=write_bank(tmp / "bank.zarr"))
    assert len(meta["items"]) == min(N_SOURCES, n_kept)
    return {"dir": tmp / "bench", "meta": meta, "models": write_encoders(tmp / "models"), "cluster": dask_cluster, "tmp": tmp}


@pytest.mark.slow
def test_build_from_the_curate_flow(tmp_path, prefect_api, dask_cluster):
    """The same build on a store made by the real curate flow (covered fast above)."""
    specs = make_clip_specs(1, seed=5, n_frames=8, width=160, height=120)
    cfg = CurateConfig(out=tmp_path / "handedit.zarr", clips=specs, embodiments=[EMB], frames_per_chunk=8,
                       cluster=ClusterConfig(address=dask_cluster.scheduler_address))
    run_curate(cfg)
    meta = build_testset(cfg.out, tmp_path / "bench", 3, bank=write_bank(tmp_path / "bank.zarr"))
    items, errors = load_manifest(BenchDir(tmp_path / "bench").manifest)
    assert errors == [] and len(items) == len(meta["items"]) >= 1
    assert read_mask(items[0].robot_mask_path).any() and read_image(items[0].gt_path).shape == (120, 160, 3)


def test_testset_and_toolkit_manifest(bench):
    out = BenchDir(bench["dir"])
    items, errors = load_manifest(out.manifest)
    assert errors == [] and len(items) == len(bench["meta"]["items"]) >= 2
    assert bench["meta"]["tracks"]["hand"] == [EMB]
    for _, obj, _ in iter_jsonl(out.manifest):
        assert set(TOOLKIT_FIELDS) <= set(obj) and not obj["src_path"].startswith("/")  # relative, portable
    it = items[0]
    assert it.replacement_scope == "hand" and it.target_name == "Allegro" and it.pred_path == ""
    src, gt = read_image(it.src_path), read_image(it.gt_path)
    human, robot = read_mask(it.human_mask_path), read_mask(it.robot_mask_path)
    roi = read_mask(str(BenchDir(bench["dir"]).item_file(it.id, "test_mask")))
    assert it.test_mask_path == ""  # the toolkit's meaning: the prediction's robot mask, none before an editor ran
    assert src.shape == gt.shape == (120, 160, 3) and not np.array_equal(src, gt)
    assert "-f000002-" not in " ".join(i.id for i in items)  # QC-rejected frame is not an item
    assert human.any() and robot.any() and np.array_equal(roi, human | robot)
    assert it.object_mask_path and read_mask(it.object_mask_path).any()
    assert len(it.urdf_ref_paths) == 2 and read_mask(it.urdf_mask_paths[0]).any()
    assert it.instruction.startswith("Replace the human hand region with the robot shown in the reference render: Allegro, described as a compact black")
    assert it.instruction.endswith("Preserve the original hand-object interaction, object state, and surrounding scene structure.")


@pytest.fixture(scope="module")
def scored(bench):
    d = bench["dir"]
    copy = run_editor(d, "copy", CommandEditor("cp {src} {out}", model="copy"), concurrency=2)
    oracle = run_editor(d, "oracle", CommandEditor("cp {gt} {out}", model="oracle"), concurrency=2)
    assert copy.failed == oracle.failed == 0 and copy.ok == oracle.ok == len(bench["meta"]["items"])
    summaries = {}
    with FakeOpenAI() as server:
        judge = JudgeConfig(base_url=server.base_url, model="gpt-4o", cache_dir=d / "vlm_cache", backoff_s=0.0)
        for name in ("copy", "oracle"):
            out = BenchDir(d).results(name)
            manifest = export_manifest(d, name, out / "manifest.jsonl")
            cfg = EvaluateConfig(manifest=manifest, out=out, editor=name, model_dir=bench["models"], judge=judge, protocol="paper",
                                 chunk_size=2, cluster=ClusterConfig(address=bench["cluster"].scheduler_address))
            summaries[name] = run_evaluate(cfg)
        n_chat = sum(r["kind"] == "chat" for r in server.requests)
    return summaries, n_chat


def test_oracle_beats_copy_and_report_shows_it(bench, scored):
    summaries, n_chat = scored
    n = len(bench["meta"]["items"])
    assert n_chat == 2 * 2 * n  # SC + PQ per item and editor
    c, o = summaries["copy"]["tracks"]["hand"]["metrics"], summaries["oracle"]["tracks"]["hand"]["metrics"]
    assert summaries["copy"]["n_errors"] == summaries["oracle"]["n_errors"] == 0
    assert summaries["oracle"]["skipped"] == []
    for m, hib in SIMILARITY.items():
        assert c[m] is not None and o[m] is not None, m
        assert (o[m] > c[m]) if hib else (o[m] < c[m]), (m, o[m], c[m])
    assert o["psnr_full"] == 100.0 and o["lpips_full"] == pytest.approx(0, abs=1e-9) and o["fid_full"] == pytest.approx(0, abs=1e-3)
    assert o["vlm"] == pytest.approx(np.sqrt(0.75 * 0.5)) and c["vlm"] == 0.0
    # the copy editor leaves the human hand in place: interaction is perfect but removal is not
    assert c["interaction"] == pytest.approx(1.0) and c["removal"] < o["removal"]
    written = write_report(bench["dir"])
    rep = BenchDir(bench["dir"]).report
    md = (rep / "tables.md").read_text()
    oracle_row = next(line for line in md.splitlines() if line.startswith("| oracle |") and "100.00" in line)
    copy_row = next(line for line in md.splitlines() if line.startswith("| copy |") and "<u>" in line)
    assert oracle_row.count("**") >= 2 * 11 and "<u>" not in oracle_row  # best on every generic column
    assert "**" not in copy_row
    tex = (rep / "hand_generic.tex").read_text()
    assert r"oracle & \textbf{100.00}" in tex and r"\underline{" in tex
    rows = list(csv.DictReader(open(rep / "hand_generic.csv")))
    assert {r["model"] for r in rows} == {"copy", "oracle"}
    radar = read_image(rep / "hand_radar.png")
    assert radar.shape[0] > 300 and (radar < 250).any() and any(p.name == "hand_radar.png" for p in written["hand"])


def test_per_item_errors_while_the_rest_is_scored(bench, scored):
    d, tmp = bench["dir"], bench["tmp"]
    broken = tmp / "broken"
    manifest = export_manifest(d, "copy", broken / "manifest.jsonl")
    lines = manifest.read_text().splitlines()
    recs = [json.loads(x) for x in lines]
    for r in recs:  # private copies of the predictions
        dst = broken / "preds" / f"{r['id']}.png"
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(BenchDir(d).prediction("copy", r["id"]), dst)
        r["pred_path"] = str(dst)
    (broken / "preds" / f"{recs[0]['id']}.png").unlink()  # missing image
    small = read_image(broken / "preds" / f"{recs[1]['id']}.png")[:60, :80]
    write_image(broken / "preds" / f"{recs[1]['id']}.png", small)  # wrong size
    text = "\n".join(json.dumps(r) for r in recs) + '\n{"id": "truncated", "replacement_scope": \n'
    manifest.write_text(text)
    cfg = EvaluateConfig(manifest=manifest, out=broken / "results", editor="broken", model_dir=bench["models"], protocol="paper",
                         judge=None, chunk_size=3, cluster=ClusterConfig(address=bench["cluster"].scheduler_address))
    s = run_evaluate(cfg)
    errs = {e["id"]: e["error"] for e in s["errors"]}
    assert len(errs) == 3, errs
    assert "image not found" in errs[recs[0]["id"]] and f"{recs[0]['id']}.png" in errs[recs[0]["id"]]
    assert "80x60" in errs[recs[1]["id"]] and "160x120" in errs[recs[1]["id"]]
    line_no = len(recs) + 1
    assert f"manifest.jsonl:{line_no}: not valid JSON" in errs[f"line-{line_no}"]
    assert s["tracks"]["hand"]["n_scored"] == len(recs) - 2
    assert s["tracks"]["hand"]["metrics"]["psnr_full"] is not None
    assert set(s["skipped"]) == {"vlm_sc", "vlm_pq", "vlm"}
    rows = list(csv.DictReader(open(broken / "results" / "items.csv")))
    assert sum(1 for r in rows if r["error"]) == 3 and sum(1 for r in rows if not r["error"] and r["psnr_full"]) == len(recs) - 2


def test_http_editor_cost_resume_and_failures(bench):
    d = bench["dir"]
    with FakeOpenAI() as server:
        editor = HttpImageEditor(HttpEditorConfig(base_url=server.base_url, model="gpt-image-2", api_key="sk-x"))
        first = run_editor(d, "gpt-image-2", editor, concurrency=2, limit=2)
        assert (first.ran, first.ok, first.failed) == (2, 2, 0)
        assert first.cost_usd == pytest.approx(2 * 0.211)
        edits = [r for r in server.requests if r["kind"] == "edit"]
        assert len(edits) == 2 and all(r["n_images"] == 2 and r["fields"]["model"] == "gpt-image-2" for r in edits)
        assert edits[0]["fields"]["prompt"].startswith("Replace the human hand region") and edits[0]["auth"] == "Bearer sk-x"
        # resumed: the two done items are skipped, the rest run
        n = len(bench["meta"]["items"])
        second = run_editor(d, "gpt-image-2", editor, concurrency=2)
        assert (second.ran, second.skipped) == (n - 2, 2)
        assert editor_cost(d, "gpt-image-2") == pytest.approx(n * 0.211)
        it0 = load_manifest(BenchDir(d).manifest)[0][0]
        assert np.array_equal(read_image(BenchDir(d).prediction("gpt-image-2", it0.id)), read_image(it0.src_path))
    failing = run_editor(d, "broken-cmd", CommandEditor("echo model crashed >&2; exit 3 # {out}"), max_tries=3, backoff_s=0)
    assert failing.ok == 0 and failing.failed == len(bench["meta"]["items"])
    recs = [r for _, r, _ in iter_jsonl(BenchDir(d).records("broken-cmd"))]
    assert all(r["status"] == "failed" and r["attempts"] == 1 and "exited 3" in r["error"] and "model crashed" in r["error"] for r in recs)
    assert not any(BenchDir(d).predictions("broken-cmd").glob("*.png"))


def test_manifest_roundtrip_and_line_errors(tmp_path):
    from handedit.benchmark.manifest import ManifestItem
    from handedit.benchmark.testset import instruction_for_target
    from handedit.storage.benchmark import write_jsonl

    base = {k: "" for k in TOOLKIT_FIELDS}
    good = {**base, "id": "x1", "replacement_scope": "hand", "target_name": "Allegro", "src_path": "imgs/a.png",
            "gt_path": str(tmp_path / "abs.png"), "urdf_ref_paths": ["r0.png"], "urdf_mask_paths": ["m0.png"]}
    rows = [good, {**good, "id": "x2", "replacement_scope": "arm"}, {k: v for k, v in good.items() if k != "gt_path"},
            {**good, "id": "x3", "urdf_mask_paths": []}, {"id": "x4", "target_name": "Allegro"}]
    write_jsonl(tmp_path / "m.jsonl", rows)
    items, errors = load_manifest(tmp_path / "m.jsonl")
    assert [i.id for i in items] == ["x1", "x3"]  # optional fields may be missing (as in the toolkit)
    assert items[0].src_path == str(tmp_path / "imgs/a.png") and items[0].gt_path == str(tmp_path / "abs.png")
    assert items[1].urdf_ref_paths and items[1].urdf_mask_paths == []
    msgs = [e["error"] for e in errors]
    assert "m.jsonl:2: replacement_scope 'arm' is not a scope" in msgs[0] and "duplicate id 'x1'" in msgs[1]
    assert "m.jsonl:5: missing required field(s) src_path, pred_path" in msgs[2]
    back = ManifestItem.from_record(items[0].to_record(tmp_path), base=tmp_path)
    assert back == items[0] and items[0].to_record(tmp_path)["src_path"] == "imgs/a.png"
    assert items[0].to_record(tmp_path)["replacement_scope"] == "hand-only"  # the toolkit's spelling
    # a toolkit item without handedit's extras still gets the paper's instruction
    assert instruction_for_target("hand", "Allegro").startswith("Replace the human hand region with the robot shown")


def test_report_ranks_and_reference_row():
    from handedit.benchmark.report import radar_scores, track_tables

    rows = {"A": {"psnr_full": 20.0, "lpips_full": 0.30, "vlm": 0.5}, "B": {"psnr_full": 18.0, "lpips_full": 0.20, "vlm": 0.7},
            "C": {"psnr_full": 12.0, "lpips_full": 0.60, "vlm": 0.1}, "Pseudo-GT": {"psnr_full": 100.0, "lpips_full": 0.0, "vlm": 0.9}}
    md = track_tables("Hand-only", rows)["generic"].markdown()
    line = {r.split("|")[1].strip(): r for r in md.splitlines() if r.startswith("| ") and "Model" not in r}
    assert "**20.00**" in line["A"] and "<u>0.300</u>" in line["A"]  # lower LPIPS is better: B best, A second
    assert "<u>18.00</u>" in line["B"] and "**0.200**" in line["B"]
    assert "**" not in line["*Pseudo-GT* (reference)"] and md.index("| C |") < md.index("Pseudo-GT")
    labels, scores = radar_scores(rows)
    assert labels == ["PSNR", "LPIPS*", "VLM"]
    assert scores["Pseudo-GT"] == pytest.approx([1, 1, 1]) and scores["C"] == pytest.approx([0.2, 0.2, 0.2])  # LPIPS inverted


def test_toolkit_example_manifest_imports(tmp_path, monkeypatch, shared_dir):
    """The authors' own example manifest, its placeholder paths rewritten to files made here."""
    from handedit.flows.benchmark import load_manifest as load

    example = shared_dir / "benchmark" / "handedit-toolkit" / "examples" / "manifest.example.jsonl"
    text = example.read_text().replace("/abs/path/", "files/")
    (tmp_path / "manifest.jsonl").write_text(text)
    monkeypatch.chdir(tmp_path)  # the toolkit opens relative paths from the working directory
    items, errors = load(tmp_path / "manifest.jsonl", relative_to="cwd")
    assert errors == [] and [i.id for i in items] == ["000001", "000002"]
    a, b = items
    assert (a.replacement_scope, a.embodiment, b.replacement_scope, b.embodiment) == ("hand", "shadow", "hand_arm", "ur5_shadow")
    assert a.test_mask_path == str(tmp_path / "files/pred_mask/000001.png") and b.test_mask_path == ""
    assert len(b.urdf_ref_paths) == 6 and b.urdf_mask_paths == [] and a.extra["dataset"] == "HandEdit"
    rec = b.to_record(tmp_path)
    assert rec["replacement_scope"] == "hand-arm" and rec["task"] == "handedit"


def test_export_reimport_scores_identically(bench, scored, tmp_path, monkeypatch):
    """A project test set exported in the toolkit's format (absolute paths), read back with the
    toolkit's path rule, scores exactly as the project's own manifest did."""
    import csv as csvmod

    d = bench["dir"]
    exported = export_manifest(d, "copy", tmp_path / "toolkit" / "manifest.jsonl", absolute=True)
    for _, obj, _ in iter_jsonl(exported):
        assert obj["src_path"].startswith("/") and obj["replacement_scope"] == "hand-only" and obj["test_mask_path"] == ""
    monkeypatch.chdir(tmp_path)
    cfg = EvaluateConfig(manifest=exported, out=tmp_path / "res", editor="copy", model_dir=bench["models"], judge=None, protocol="paper",
                         chunk_size=2, paths_relative_to="cwd",
                         cluster=ClusterConfig(address=bench["cluster"].scheduler_address))
    run_evaluate(cfg)
    mine = {r["id"]: r for r in csvmod.DictReader(open(BenchDir(d).results("copy") / "items.csv"))}
    again = {r["id"]: r for r in csvmod.DictReader(open(tmp_path / "res" / "items.csv"))}
    assert set(mine) == set(again)
    for iid, row in again.items():
        for m in ("psnr_full", "ssim_roi", "lpips_bg", "removal", "struct_fidelity", "id_fidelity"):
            assert row[m] == mine[iid][m], (iid, m)


def test_missing_optional_inputs_disable_only_their_metrics(tmp_path, prefect_api, dask_cluster):
    """A toolkit manifest with only the required fields still scores what it can, and says
    per item what was disabled."""
    import csv as csvmod

    rng = np.random.default_rng(0)
    src = rng.integers(0, 255, (40, 48, 3), np.uint8)
    pred = src.copy()
    pred[10:20, 10:20] = 200
    for name, im in (("src.png", src), ("pred.png", pred), ("gt.png", src)):
        write_image(tmp_path / name, im)
    rows = [{"id": "bare", "replacement_scope": "hand-only", "target_name": "Allegro", "src_path": "src.png",
             "pred_path": "pred.png"},
            {"id": "with-gt", "scope": "hand", "robot_name": "allegro", "src_path": "src.png", "pred_path": "pred.png",
             "gt_path": "gt.png"}]
    (tmp_path / "m.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    cfg = EvaluateConfig(manifest=tmp_path / "m.jsonl", out=tmp_path / "res", editor="x", model_dir=None, judge=None, protocol="paper",
                         paths_relative_to="manifest", cluster=ClusterConfig(address=dask_cluster.scheduler_address))
    s = run_evaluate(cfg)
    assert s["n_errors"] == 0
    got = {r["id"]: r for r in csvmod.DictReader(open(tmp_path / "res" / "items.csv"))}
    bare, gt = got["bare"], got["with-gt"]
    assert bare["removal"] and not bare["psnr_full"] and "no pseudo-GT" in bare["disabled"]
    assert "ROI = whole image" in bare["disabled"] and "no object mask" in bare["disabled"]
    assert float(gt["psnr_full"]) > 0 and not gt["psnr_bg"] and "no pseudo-GT" not in gt["disabled"]


def test_toolkit_protocol_on_the_project_test_set(bench, scored, tmp_path):
    """The same editors' predictions under the toolkit protocol: its files, the oracle ahead of
    the copy editor on every similarity metric, and ``bench report`` tables from the same numbers."""
    from handedit.benchmark.toolkit_report import TO_PROJECT

    d = bench["dir"]
    models = write_encoders(tmp_path / "models", sizes=TOOLKIT_SIZES)
    means = {}
    for name in ("copy", "oracle"):
        out = BenchDir(d).results(f"{name}-toolkit")
        cfg = EvaluateConfig(manifest=export_manifest(d, name, out / "manifest.jsonl"), out=out, editor=f"{name}-toolkit",
                             model_dir=models, judge=None, chunk_size=2,
                             cluster=ClusterConfig(address=bench["cluster"].scheduler_address))
        summary = run_evaluate(cfg)
        (group,) = [k for k in summary if k != "_meta"]
        means[name] = summary[group]
        rows = [json.loads(x) for x in (out / "per_sample.jsonl").read_text().splitlines()]
        assert len(rows) == len(bench["meta"]["items"]) and not any(r["error"] for r in rows)
        assert (out / "leaderboard.md").is_file() and (out / "report_summary.json").is_file()
    c, o = means["copy"], means["oracle"]
    assert o["Full-PSNR_mean"] == np.inf and o["Full-LPIPS_mean"] == pytest.approx(0, abs=1e-9)
    for m in ("ROI-PSNR", "BG-PSNR", "Full-SSIM", "ROI-SSIM", "Fidelity-Shape", "Fidelity-ID"):
        assert o[f"{m}_mean"] > c[f"{m}_mean"], m
    assert c["Interaction_mean"] == pytest.approx(1.0) and c["Removal_mean"] < o["Removal_mean"]
    write_report(d, ["copy-toolkit", "oracle-toolkit"])
    md = (BenchDir(d).report / "tables.md").read_text()
    assert "| oracle-toolkit |" in md and "| copy-toolkit |" in md
    project = json.loads((BenchDir(d).results("oracle-toolkit") / "report_summary.json").read_text())
    assert project["tracks"]["hand"]["metrics"][TO_PROJECT["ROI-SSIM"]] == pytest.approx(o["ROI-SSIM_mean"])


def test_pseudo_gt_and_toolkit_references_are_selectable(bench, shared_dir, tmp_path):
    """The unharmonized composite as pseudo-GT (the toolkit README's main benchmark) and the
    authors' reference renders with short descriptions instead of the project's bank."""
    from handedit.storage import open_store

    store = bench["tmp"] / "handedit.zarr"
    refs_dir = shared_dir / "benchmark" / "handedit-toolkit" / "reference"
    meta = build_testset(store, tmp_path / "tk", N_SOURCES, pseudo_gt="composite", toolkit_references=refs_dir)
    assert meta["pseudo_gt"] == "composite" and meta["references"].startswith("toolkit")
    items, errors = load_manifest(BenchDir(tmp_path / "tk").manifest)
    assert errors == [] and items
    root = open_store(store)
    for it in items:
        frame = it.extra["frame"]
        composite = root[Unit("composite", it.extra["clip"], embodiment=EMB).path]["image"][frame]
        harmonized = root[Unit("harmonize", it.extra["clip"], embodiment=EMB).path]["image"][frame]
        gt = read_image(it.gt_path)
        assert np.array_equal(gt, composite) and not np.array_equal(gt, harmonized)
        assert len(it.urdf_ref_paths) == 1 and it.urdf_mask_paths == []
        assert open(it.urdf_ref_paths[0], "rb").read() == (refs_dir / "hand-only" / "allegro.png").read_bytes()
        assert it.extra["description"] == ("A compact black robotic hand with a boxy palm, three straight front fingers "
                                           "made of rectangular joint modules.")  # first sentence cut at 18 words
    with pytest.raises(FileNotFoundError, match="no toolkit reference renders"):
        build_testset(store, tmp_path / "none", N_SOURCES, toolkit_references=tmp_path)
    with pytest.raises(ValueError, match="pseudo_gt must be one of"):
        build_testset(store, tmp_path / "bad", N_SOURCES, pseudo_gt="raw")


def test_human_report_from_raters_scores(bench, scored, tmp_path, capsys):
    """The paper's human evaluation from a ratings file: three raters who agree exactly give
    alpha = ICC(2,k) = 1; the metric-human kappa over the one editor pair is 1 where the metric
    prefers the editor the raters prefer and -1 where it does not; bad lines are refused by
    number; `bench report` carries the table."""
    from handedit.flows.cli import main

    summaries, _ = scored
    items, _ = load_manifest(BenchDir(bench["dir"]).manifest)
    lines = [{"item": it.id, "editor": e, "rater": r, "target": s, "scene_interaction": s, "realism": s}
             for it in items for e, s in (("copy", 1), ("oracle", 5)) for r in ("ann", "bob", "cy")]
    bad = tmp_path / "bad.jsonl"
    bad.write_text(json.dumps(lines[0]) + "\n" + json.dumps({**lines[1], "target": 6}) + "\n"
                   + json.dumps({**lines[2], "editor": "nobody"}) + "\n")
    assert main(["bench", "human-report", "--bench", str(bench["dir"]), "--ratings", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"{bad}:2: target: 6 is not an integer from 1 to 5" in err and f"{bad}:3: editor 'nobody'" in err
    good = tmp_path / "ratings.jsonl"
    good.write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    assert main(["bench", "human-report", "--bench", str(bench["dir"]), "--ratings", str(good)]) == 0
    rep = json.loads((BenchDir(bench["dir"]).report / "human.json").read_text())
    assert rep["raters"] == 3 and rep["outputs"] == 2 * len(items) and rep["ratings"] == 3 * 3 * 2 * len(items)
    c, o = summaries["copy"]["tracks"]["hand"]["metrics"], summaries["oracle"]["tracks"]["hand"]["metrics"]
    for axis, metric in (("target", "id_fidelity"), ("scene_interaction", "interaction"), ("realism", "vlm")):
        a = rep["axes"][axis]
        assert a["krippendorff_alpha"] == pytest.approx(1.0) and a["icc_2k"] == pytest.approx(1.0), (axis, a)
        assert a["mos"]["hand"] == {"copy": 1.0, "oracle": 5.0}
        if c[metric] != o[metric]:
            assert a["pairs"] == 1 and a["kappa"] == pytest.approx(1.0 if o[metric] > c[metric] else -1.0), (axis, a, c, o)
    write_report(bench["dir"])
    assert "Human evaluation" in (BenchDir(bench["dir"]).report / "tables.md").read_text()


def test_the_rating_page_by_keyboard_and_mouse(bench, scored, tmp_path, capsys):
    """``handedit bench rate``, driven by Playwright in Debian's Chromium: the blinded study's page
    (no editor name on it), one output scored by keys and one by clicks, each stored when its three
    scores are given; a reload resumes; `bench human-report` reads them without a file."""
    import re

    from _browser import browser, keep_screenshot, served
    from playwright.sync_api import sync_playwright

    from handedit.flows.cli import main
    from handedit.storage.benchmark import read_ratings

    def rated(n: int) -> str:
        return f"document.getElementById('progress').dataset.rated === '{n}'"

    with served(["bench", "rate", "--bench", str(bench["dir"])]) as url, sync_playwright() as pw:
        chrome = pw.chromium.launch(executable_path=browser(), args=["--no-sandbox", "--disable-gpu"])
        page = chrome.new_page(viewport={"width": 1300, "height": 900})
        page.goto(url)
        page.fill("#rater", "ann")
        page.press("#rater", "Enter")
        page.wait_for_function(rated(0))
        assert not re.search(r"\b(copy|oracle)\b", page.content())  # blinded: no editor name anywhere
        assert "output 1 of " in page.text_content("#info") and page.text_content("#instruction").startswith("Replace")
        for key in ("5", "4", "3"):  # target, scene_interaction, realism
            page.keyboard.press(key)
        page.wait_for_function(rated(1))
        for axis, s in (("target", 1), ("scene_interaction", 2), ("realism", 2)):
            page.click(f"#{axis}-{s}")
        page.wait_for_function(rated(2))
        page.wait_for_function("['source', 'reference', 'output'].every((i) => document.getElementById(i).naturalWidth > 0)")
        page.screenshot(path=str(tmp_path / "bench_rating.png"))
        page.reload()
        page.wait_for_function(rated(2))
        assert "output 3 of " in page.text_content("#info")
        chrome.close()
    keep_screenshot(tmp_path / "bench_rating.png")
    given = read_ratings(bench["dir"])
    assert sorted((r["target"], r["scene_interaction"], r["realism"], r["rater"]) for r in given) == [(1, 2, 2, "ann"), (5, 4, 3, "ann")]
    assert main(["bench", "human-report", "--bench", str(bench["dir"])]) == 0
    rep = json.loads((BenchDir(bench["dir"]).report / "human.json").read_text())
    assert rep["raters"] == 1 and rep["outputs"] == 2 and rep["ratings"] == 6
