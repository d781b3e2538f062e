"""The toolkit protocol's output files, shaped as the authors' toolkit writes them.

- ``per_sample.jsonl`` / ``.csv``: one row per item, the toolkit's columns in its order (the
  manifest fields, then every metric column, NaN where not computed), then handedit's own
  (``track``, ``embodiment``, ``pred_size``, ``resized``, ``seconds``, ``error``);
- ``summary.json``: ``_meta`` plus one entry per ``dataset/task`` group with ``n`` and each
  metric's ``_mean`` / ``_std`` (pandas, ddof 1) / ``_median`` over its finite values, and the
  run's pooled ``Full-FID`` / ``ROI-FID`` on every group;
- ``leaderboard.csv`` / ``.md``: the groups sorted by ``VLM_mean`` (descending, NaN last).

``project_rows`` maps the same rows onto the paper protocol's metric names, so that
``handedit bench report`` builds its tables from these numbers.
"""

from __future__ import annotations

import io
import json
import math

import numpy as np
import pandas as pd

from handedit.markdown import md
from handedit.metrics.toolkit import EMBODIED_METRICS, GENERIC_METRICS, VLM_METRICS

HEAD = ["id", "dataset", "task", "instruction", "src_path", "pred_path", "gt_path", "test_mask_path", "gt_mask_path",
        "urdf_ref_paths", "urdf_mask_paths", "roi_mask_path", "human_mask_path", "robot_mask_path", "bg_mask_path",
        "object_mask_path", "urdf_ref_path", "target_name", "replacement_scope"]
METRIC_COLUMNS = GENERIC_METRICS + VLM_METRICS + EMBODIED_METRICS
TAIL = ["track", "embodiment", "pred_size", "resized", "seconds", "error", "vlm_error"]  # vlm_error: the judge's failure
JUDGE = {"vlm_sc": "VLM-SC", "vlm_pq": "VLM-PQ", "vlm": "VLM"}
# toolkit column -> the paper protocol's metric name (handedit.metrics.suite.METRICS)
TO_PROJECT = {"Full-PSNR": "psnr_full", "BG-PSNR": "psnr_bg", "ROI-PSNR": "psnr_roi", "Full-SSIM": "ssim_full",
              "BG-SSIM": "ssim_bg", "ROI-SSIM": "ssim_roi", "Full-LPIPS": "lpips_full", "BG-LPIPS": "lpips_bg",
              "ROI-LPIPS": "lpips_roi", "Removal": "removal", "Fidelity-Shape": "struct_fidelity",
              "Fidelity-ID": "id_fidelity", "Interaction": "interaction", "VLM-SC": "vlm_sc", "VLM-PQ": "vlm_pq",
              "VLM": "vlm", "Fidelity-ID-clip": "id_ref", "Fidelity-ID-lab": "id_lab", "Fidelity-ID-lab-dist": "delta_e"}


def per_sample_row(row: dict, record: dict) -> dict:
    """A task's row with the manifest fields in front, the toolkit's way round."""
    out = {k: record.get(k, "") for k in HEAD}
    out["replacement_scope"] = record.get("replacement_scope", "")
    for src, dst in JUDGE.items():
        if src in row:
            row = {**row, dst: row[src]}
    for m in METRIC_COLUMNS:
        v = row.get(m)
        out[m] = float("nan") if v is None else v
    out.update({k: v for k, v in row.items() if k.startswith("VLM-") and k not in out})  # the judge's passthrough fields
    for k in TAIL:
        out[k] = row.get(k, "")
    return out


def to_csv(rows: list[dict]) -> str:
    return pd.DataFrame(rows).to_csv(index=False)


def to_jsonl(rows: list[dict]) -> str:
    return "".join(json.dumps(r, ensure_ascii=False) + "\n" for r in rows)


def summarize(rows: list[dict], fid: dict[str, float], exp_name: str) -> dict:
    """The toolkit's ``summary.json`` (groups by ``dataset``/``task``)."""
    df = pd.DataFrame(rows)
    metrics = [m for m in METRIC_COLUMNS if m in df.columns]
    out: dict = {"_meta": {"exp_name": exp_name, "group_by": ["dataset", "task"]}}
    if df.empty:
        return out
    for keys, sub in df.groupby(["dataset", "task"], dropna=False):
        row = {"dataset": keys[0], "task": keys[1], "n": int(len(sub))}
        for m in metrics:
            v = pd.to_numeric(sub[m], errors="coerce").dropna()
            row[f"{m}_mean"] = float(v.mean()) if len(v) else float("nan")
            row[f"{m}_std"] = float(v.std()) if len(v) else float("nan")
            row[f"{m}_median"] = float(v.median()) if len(v) else float("nan")
        row.update(fid)
        row["exp_name"] = exp_name
        out[f"{keys[0]}/{keys[1]}"] = row
    return out


def leaderboard(summary: dict) -> tuple[str, str]:
    """(leaderboard.csv, leaderboard.md) from a summary."""
    df = pd.DataFrame([r for k, r in summary.items() if k != "_meta"])
    if df.empty:
        return "", ""
    key = "VLM_mean" if "VLM_mean" in df.columns else ("Fidelity_mean" if "Fidelity_mean" in df.columns else None)
    if key:
        df = df.sort_values(key, ascending=False)
    cols = [c for c in df.columns if c in {"exp_name", "dataset", "task", "n", "Full-FID", "ROI-FID"} or c.endswith("_mean")]
    if "exp_name" in cols:
        cols = ["exp_name"] + [c for c in cols if c != "exp_name"]
    return df.to_csv(index=False), _markdown(df[cols])


def _markdown(df: pd.DataFrame) -> str:
    def cell(v) -> str:
        if isinstance(v, float):
            return "nan" if math.isnan(v) else f"{v:.4g}"
        return md(v)

    buf = io.StringIO()
    buf.write("| " + " | ".join(md(c) for c in df.columns) + " |\n|" + "|".join("---" for _ in df.columns) + "|\n")
    for _, r in df.iterrows():
        buf.write("| " + " | ".join(cell(v) for v in r.tolist()) + " |\n")
    return buf.getvalue()


def project_rows(rows: list[dict]) -> list[dict]:
    """The same rows under the paper protocol's names (for ``handedit bench report``)."""
    out = []
    for r in rows:
        p = {"id": r["id"], "track": r.get("track"), "error": r.get("error", "")}
        for src, dst in TO_PROJECT.items():
            v = r.get(src)
            p[dst] = v if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None
        out.append(p)
    return out


def pooled_fid(feats: dict[str, dict], ids: list[str], fid_fn) -> dict[str, float]:
    """The run's Full-FID and ROI-FID over every item with both features (>= 2 needed, as the toolkit)."""
    out = {}
    for kind, name in (("full", "Full-FID"), ("roi", "ROI-FID")):
        a = [feats[i][f"{kind}_gt"] for i in ids if f"{kind}_gt" in feats.get(i, {})]
        b = [feats[i][f"{kind}_pred"] for i in ids if f"{kind}_pred" in feats.get(i, {})]
        out[name] = fid_fn(np.stack(a), np.stack(b)) if len(a) >= 2 and len(b) >= 2 else float("nan")
    return out
