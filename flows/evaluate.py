"""The evaluate flow: the full metric suite over a toolkit manifest, on a Dask cluster.

    manifest.jsonl -> chunks of items -> tasks.evaluate (per item: PSNR/SSIM/LPIPS x
    full/BG/ROI, Removal, Struct/ID fidelity, Interaction, VLM judge; Inception
    features) -> driver: FID per track (full, ROI), per-track means -> results/

Encoders missing from ``model_dir`` disable only their metrics, listed in the
summary's ``skipped`` and logged as errors. Bad manifest lines and bad items are
per-item errors in ``items.csv`` / ``summary.json``; everything else is scored.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
from prefect import flow, get_run_logger
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from handedit.benchmark.targets import toolkit_reference_bank
from handedit.flows.benchmark import load_manifest
from handedit.flows.config import ClusterConfig
from handedit.metrics.embodied import EmbodiedConfig
from handedit.metrics.encoders import ENCODERS, missing_encoders
from handedit.metrics.frechet import fid
from handedit.metrics.suite import EXTRAS, METRICS
from handedit.metrics.vlm import JudgeConfig
from handedit.storage.benchmark import write_json, write_text
from handedit.secrets import redact_obj
from handedit.storage.store import now_iso
from handedit.tasks.evaluate import EvalJob, evaluate_chunk

ITEMS_CSV, SUMMARY_JSON = "items.csv", "summary.json"
REPORT_SUMMARY_JSON = "report_summary.json"  # toolkit protocol: the paper protocol's summary shape, same numbers


class EvaluateConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    paths_relative_to: Literal["manifest", "cwd"] = Field(
        "manifest", description="relative paths: to the manifest's folder (the project's) or the working directory (the toolkit's)")
    manifest: Path = Field(description="toolkit JSONL manifest with pred_path filled")
    out: Path = Field(description="results folder (items.csv, summary.json)")
    editor: str = Field(description="the editor's display name in reports")
    model_dir: Path | None = Field(None, description="folder with the encoder ONNX files")
    judge: JudgeConfig | None = None
    embodied: EmbodiedConfig = EmbodiedConfig()
    chunk_size: int = Field(16, ge=1, description="items per task")
    roi_dilate_px: int = Field(0, ge=0, description="toolkit protocol: grow the ROI by a disc of this radius (its --roi-dilate-px)")
    protocol: Literal["toolkit", "paper"] = Field(
        "toolkit", description="toolkit: every metric as the authors' toolkit computes it (published numbers); "
                               "paper: this project's reading of the paper's equations")
    cluster: ClusterConfig = ClusterConfig()


@flow(name="evaluate", log_prints=True)
def evaluate(cfg: EvaluateConfig) -> dict:
    logger = get_run_logger()
    items, line_errors = load_manifest(cfg.manifest, cfg.paths_relative_to)
    for e in line_errors:
        logger.error("manifest: %s", e["error"])
    missing = missing_encoders(cfg.model_dir)
    skipped = [m for name in missing for m in ENCODERS[name].metrics]
    for name, why in missing.items():
        logger.error("encoder %s missing (%s): skipping %s", name, why, ", ".join(ENCODERS[name].metrics))
    if cfg.judge is None:
        skipped += ["vlm_sc", "vlm_pq", "vlm"]
        logger.error("no VLM judge configured (HANDEDIT_VLM_BASE_URL): skipping the VLM judge")
    records = [it.to_record() for it in items]
    if cfg.protocol == "toolkit":
        _attach_reference_bank(items, records)
    chunks = [records[i:i + cfg.chunk_size] for i in range(0, len(records), cfg.chunk_size)]
    model_dir = str(cfg.model_dir) if cfg.model_dir else None
    futures = [evaluate_chunk.submit(EvalJob(k, c, model_dir, cfg.judge, cfg.embodied, cfg.protocol, cfg.roi_dilate_px))
               for k, c in enumerate(chunks)]
    rows, feats = [], {}
    for k, fut in enumerate(futures):
        res = fut.result(raise_on_failure=False)
        if isinstance(res, dict):
            rows += res["rows"]
            feats.update(res["features"])
        else:  # the whole chunk failed after retries: every item gets the error
            for rec in chunks[k]:
                rows.append({"id": rec["id"], "track": rec["replacement_scope"], "error": f"chunk failed: {res}"})
    for e in line_errors:
        rows.append({"id": e["id"] or f"line-{e['line']}", "track": None, "error": e["error"]})
    if cfg.protocol == "toolkit":
        return _write_toolkit(cfg, records, rows, feats, skipped, missing, line_errors, logger)
    summary = summarise(rows, feats, cfg.editor, skipped)
    summary.update(manifest=str(cfg.manifest), finished=now_iso(), n_manifest_errors=len(line_errors))
    cfg.out.mkdir(parents=True, exist_ok=True)
    cols = ["id", "track", "embodiment", *METRICS, *EXTRAS, "vlm_calls", "vlm_error", "seconds", "error"]
    df = pd.DataFrame(rows)
    df = df.reindex(columns=[c for c in cols if c in df.columns] + [c for c in df.columns if c not in cols])
    write_text(cfg.out / ITEMS_CSV, df.to_csv(index=False))
    write_json(cfg.out / SUMMARY_JSON, summary)
    n_err = sum(1 for r in rows if r.get("error"))
    logger.info("%s: %d items scored, %d errors", cfg.editor, len(rows) - n_err, n_err)
    return summary


def _attach_reference_bank(items: list, records: list[dict]) -> None:
    """Each record gets the toolkit's reference views and judge distractors of its item
    (``handedit.benchmark.targets.toolkit_reference_bank``)."""
    for rec, (refs, distractors) in zip(records, toolkit_reference_bank(items)):
        rec["toolkit_distractors"] = distractors
        if refs is not None:
            rec["toolkit_refs"] = refs


def _write_toolkit(cfg: "EvaluateConfig", records: list[dict], rows: list[dict], feats: dict, skipped: list[str],
                   missing: dict[str, str], line_errors: list[dict], logger) -> dict:
    """per_sample.jsonl/.csv, summary.json, leaderboard.csv/.md as the toolkit writes them, and
    report_summary.json (the paper protocol's shape, from the same numbers) for ``bench report``."""
    from handedit.benchmark import toolkit_report as tr
    from handedit.metrics.toolkit import NEURAL, frechet_distance_cleanfid

    by_id = {r["id"]: r for r in records}
    table = redact_obj([tr.per_sample_row(r, by_id.get(r["id"], {"id": r["id"]})) for r in rows])  # error texts may carry keys
    ok = [r["id"] for r in rows if not r.get("error")]
    summary = tr.summarize(table, tr.pooled_fid(feats, ok, frechet_distance_cleanfid), cfg.editor)
    skipped_cols = sorted({c for name, cols in NEURAL.items() if name in missing for c in cols}
                          | ({"VLM-SC", "VLM-PQ", "VLM"} if cfg.judge is None else set()))
    errors = [{"id": r["id"], "error": r["error"]} for r in table if r.get("error")]
    judge_failures = [{"id": r["id"], "error": r["vlm_error"]} for r in table if not r.get("error") and r.get("vlm_error")]
    summary["_meta"].update(protocol="toolkit", editor=cfg.editor, manifest=str(cfg.manifest), finished=now_iso(),
                            skipped=skipped_cols, n_items=len(rows), n_errors=len(errors), errors=errors,
                            n_judge_failures=len(judge_failures), judge_failures=judge_failures,
                            n_manifest_errors=len(line_errors),
                            vlm_protocol=cfg.judge.protocol if cfg.judge else "none")
    cfg.out.mkdir(parents=True, exist_ok=True)
    write_text(cfg.out / "per_sample.jsonl", tr.to_jsonl(table))
    write_text(cfg.out / "per_sample.csv", tr.to_csv(table))
    write_text(cfg.out / SUMMARY_JSON, json.dumps(summary, ensure_ascii=False, indent=2, default=str) + "\n")
    board_csv, board_md = tr.leaderboard(summary)
    write_text(cfg.out / "leaderboard.csv", board_csv)
    write_text(cfg.out / "leaderboard.md", board_md)
    project = summarise(tr.project_rows(table), feats, cfg.editor, skipped)
    project.update(protocol="toolkit", manifest=str(cfg.manifest), finished=now_iso(), n_manifest_errors=len(line_errors))
    write_json(cfg.out / REPORT_SUMMARY_JSON, project)
    for col in skipped_cols:
        logger.error("toolkit protocol: %s left empty (its encoder or judge is missing)", col)
    for f in judge_failures[:10]:
        logger.error("judge failed on %s: %s", f["id"], f["error"])
    logger.info("%s: %d items scored, %d errors, %d judge failures (toolkit protocol)", cfg.editor, len(rows) - len(errors),
                len(errors), len(judge_failures))
    return summary


def summarise(rows: list[dict], feats: dict, editor: str, skipped: list[str]) -> dict:
    """Per-track means over scored items, plus FID (full, ROI) from pooled features."""
    tracks: dict[str, dict] = {}
    for scope in sorted({r["track"] for r in rows if r.get("track")}):
        ok = [r for r in rows if r.get("track") == scope and not r.get("error")]
        means = {}
        for m in [*METRICS, *EXTRAS]:
            vals = [r[m] for r in ok if isinstance(r.get(m), (int, float)) and r[m] is not None and math.isfinite(r[m])]
            means[m] = float(np.mean(vals)) if vals else None
        for kind in ("full", "roi"):
            a = [feats[r["id"]][f"{kind}_pred"] for r in ok if f"{kind}_pred" in feats.get(r["id"], {})]
            b = [feats[r["id"]][f"{kind}_gt"] for r in ok if f"{kind}_gt" in feats.get(r["id"], {})]
            means[f"fid_{kind}"] = fid(np.stack(a), np.stack(b)) if len(a) >= 2 and len(b) >= 2 else None
        tracks[scope] = {"n_items": sum(1 for r in rows if r.get("track") == scope), "n_scored": len(ok), "metrics": means,
                         "n_judge_failed": sum(1 for r in ok if r.get("vlm_error"))}
    errors = [{"id": r["id"], "error": r["error"]} for r in rows if r.get("error")]
    judge_failures = [{"id": r["id"], "error": r["vlm_error"]} for r in rows if not r.get("error") and r.get("vlm_error")]
    return {"editor": editor, "tracks": tracks, "skipped": sorted(set(skipped)), "errors": errors,
            "n_items": len(rows), "n_errors": len(errors), "judge_failures": judge_failures,
            "n_judge_failures": len(judge_failures)}


def run_evaluate(cfg: EvaluateConfig) -> dict:
    from handedit.flows.api import run_api
    from handedit.flows.runner import task_runner

    with run_api(), cfg.cluster.connect() as address:
        return evaluate.with_options(task_runner=task_runner(address))(cfg)


__all__ = ["EvaluateConfig", "evaluate", "run_evaluate", "summarise"]
