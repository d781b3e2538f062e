"""``handedit bench evaluate --manifest FILE --protocol toolkit --out DIR`` on the authors' own example
manifest (placeholder paths rewritten to files made here; no project test set): the toolkit's
output files, every non-neural metric without encoders (the neural ones empty, loudly), and
the neural ones with encoders."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
from PIL import Image

from _bench_onnx import TOOLKIT_SIZES, write_encoders
from handedit.flows.cli import main


def _example(shared_dir, tmp_path):
    """The example manifest with its /abs/path/ placeholders pointing at images made here."""
    example = shared_dir / "benchmark" / "handedit-toolkit" / "examples" / "manifest.example.jsonl"
    root = tmp_path / "files"
    text = example.read_text().replace("/abs/path/", f"{root}/")
    rng = np.random.default_rng(2)
    for line in text.splitlines():
        rec = json.loads(line)
        src = rng.integers(0, 255, (72, 96, 3), np.uint8)
        pred = src.copy()
        pred[20:40, 30:60] = (90, 90, 95)  # the "robot"
        mask = np.zeros((72, 96), np.uint8)
        mask[20:40, 30:60] = 255
        human = np.zeros_like(mask)
        human[22:42, 28:55] = 255
        images = {"src_path": src, "pred_path": pred[::2, ::2] if rec["id"] == "000002" else pred, "gt_path": pred,
                  "gt_mask_path": mask, "test_mask_path": mask, "human_mask_path": human, "robot_mask_path": mask,
                  "object_mask_path": np.roll(mask, 12, axis=1)}
        for key, im in images.items():
            if rec.get(key):
                Path(rec[key]).parent.mkdir(parents=True, exist_ok=True)
                Image.fromarray(im).save(rec[key])
        for ref in rec["urdf_ref_paths"]:
            Path(ref).parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(np.full((64, 64, 3), 90, np.uint8)).save(ref)
    manifest = tmp_path / "manifest.jsonl"
    manifest.write_text(text)
    return manifest


def test_example_manifest_under_the_toolkit_protocol(shared_dir, tmp_path, prefect_api, dask_cluster, capsys):
    manifest = _example(shared_dir, tmp_path)
    out = tmp_path / "bare"
    args = ["bench", "evaluate", "--manifest", str(manifest), "--out", str(out), "--name", "example",
            "--address", dask_cluster.scheduler_address]
    assert main(args + ["--protocol", "toolkit"]) == 0
    captured = capsys.readouterr()
    assert "left empty (encoder or judge missing)" in captured.err and "Fidelity-Shape" in captured.err
    for name in ("per_sample.jsonl", "per_sample.csv", "summary.json", "leaderboard.csv", "leaderboard.md"):
        assert (out / name).is_file(), name
    rows = [json.loads(line) for line in (out / "per_sample.jsonl").read_text().splitlines()]
    assert [r["id"] for r in rows] == ["000001", "000002"] and all(not r["error"] for r in rows)
    a, b = rows
    assert a["replacement_scope"] == "hand-only" and b["replacement_scope"] == "hand-arm"
    assert b["pred_size"] == "48x36" and b["resized"] is True  # resized to the GT, not rejected
    assert a["Full-PSNR"] == math.inf and b["Full-PSNR"] > 10  # pred = GT; a resized copy is close
    assert 0 <= a["Removal"] <= 1 and a["Fidelity-ID-lab"] == 1.0 and math.isnan(a["Fidelity-ID"])
    assert math.isnan(a["Full-LPIPS"]) and math.isnan(a["Interaction"]) and math.isnan(a["VLM"])
    header = next(csv.reader(open(out / "per_sample.csv")))
    assert header[:3] == ["id", "dataset", "task"] and {"Full-PSNR", "ROI-SSIM", "BG-LPIPS", "Fidelity-ID", "VLM-SC"} <= set(header)
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary) == {"_meta", "HandEdit/handedit"} and summary["HandEdit/handedit"]["n"] == 2
    assert summary["_meta"]["protocol"] == "toolkit" and "Full-FID" in summary["_meta"]["skipped"]
    assert math.isnan(summary["HandEdit/handedit"]["Full-FID"])
    assert "| exp_name | dataset | task | n |" in (out / "leaderboard.md").read_text()

    models = write_encoders(tmp_path / "models", sizes=TOOLKIT_SIZES)
    full = tmp_path / "full"
    assert main(args[:4] + ["--out", str(full), "--name", "example", "--address", dask_cluster.scheduler_address,
                            "--models", str(models)]) == 0  # the default protocol is the toolkit's
    rows = [json.loads(line) for line in (full / "per_sample.jsonl").read_text().splitlines()]
    for r in rows:
        assert 0 <= r["Fidelity-Shape"] <= 1 and 0 <= r["Fidelity-ID"] <= 1 and 0 <= r["Interaction"] <= 1
        assert r["Fidelity-ID-bank-size"] == 6.0 and r["Fidelity-ID-best-ref"].endswith(".png")
    assert rows[0]["Full-LPIPS"] == 0.0
    summary = json.loads((full / "summary.json").read_text())
    assert summary["_meta"]["skipped"] == ["VLM", "VLM-PQ", "VLM-SC"]
    assert isinstance(summary["HandEdit/handedit"]["Full-FID"], float)


def test_toolkit_judge_protocol_with_distractors_and_its_own_cache(shared_dir, tmp_path, prefect_api, dask_cluster,
                                                                    monkeypatch):
    from _fake_openai import FakeOpenAI

    manifest = _example(shared_dir, tmp_path)
    base = ["bench", "evaluate", "--manifest", str(manifest), "--name", "example", "--address",
            dask_cluster.scheduler_address]
    with FakeOpenAI() as server:
        monkeypatch.setenv("HANDEDIT_VLM_BASE_URL", server.base_url)
        assert main(base + ["--out", str(tmp_path / "a")]) == 0  # toolkit protocol, so the toolkit judge
        sc = [r for r in server.requests if "chosen_reference" in r["text"]]
        assert len(sc) == 2 and len(server.requests) == 4  # SC + PQ per item
        for r in sc:  # the other target (the other track: none of its own) is the one distractor
            assert r["labels"][:3] == ["Source image:", "Edited image:", "Edited region (zoom):"]
            assert "Reference A (the target robot):" in r["labels"] and "Reference B (another robot):" in r["labels"]
        rows = [json.loads(x) for x in (tmp_path / "a" / "per_sample.jsonl").read_text().splitlines()]
        for r in rows:
            assert r["VLM-SC"] == 0.75 and r["VLM-PQ"] == 0.5 and r["VLM"] == math.sqrt(0.75 * 0.5)
            assert r["VLM-correct_ref_alignment"] == 5 and r["VLM-identity_margin"] == 5  # clamped
            assert r["VLM-target_choice_correct"] == 1 and r["VLM-vlm_num_distractors"] == 1
        summary = json.loads((tmp_path / "a" / "summary.json").read_text())
        assert summary["_meta"]["vlm_protocol"] == "toolkit" and "VLM" not in summary["_meta"]["skipped"]
        n = len(server.requests)
        assert main(base + ["--out", str(tmp_path / "a")]) == 0
        assert len(server.requests) == n  # answers cached (in the results folder's vlm_cache)
        assert main(base + ["--out", str(tmp_path / "a"), "--judge-protocol", "paper"]) == 0
        assert len(server.requests) == n + 4  # another protocol never reuses them
        server.wrong_choice = True
        assert main(base + ["--out", str(tmp_path / "d")]) == 0
        rows = [json.loads(x) for x in (tmp_path / "d" / "per_sample.jsonl").read_text().splitlines()]
        assert all(r["VLM-target_embodiment_match"] == 3 and r["VLM-target_choice_correct"] == 0 for r in rows)


def test_judge_failures_are_counted_under_both_protocols(shared_dir, tmp_path, prefect_api, dask_cluster, monkeypatch,
                                                         capsys):
    from _fake_openai import FakeOpenAI

    manifest = _example(shared_dir, tmp_path)
    base = ["bench", "evaluate", "--manifest", str(manifest), "--name", "example", "--address",
            dask_cluster.scheduler_address]
    with FakeOpenAI() as server:
        server.echo_errors = True  # 401 to every call
        monkeypatch.setenv("HANDEDIT_VLM_BASE_URL", server.base_url)
        for protocol in ("toolkit", "paper"):
            out = tmp_path / protocol
            main(base + ["--out", str(out), "--judge-protocol", protocol])
            said = "".join(capsys.readouterr())
            rows = [json.loads(x) for x in (out / "per_sample.jsonl").read_text().splitlines()]
            assert rows and all("401" in r.get("vlm_error", "") for r in rows), (protocol, rows[0])
            summary = json.loads((out / "summary.json").read_text())
            meta = summary.get("_meta", summary)  # the paper protocol's summary is flat
            assert meta["n_judge_failures"] == len(rows), (protocol, meta)
            assert "judge failed" in said and "401" in said, (protocol, said)
