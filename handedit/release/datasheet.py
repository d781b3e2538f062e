"""The datasheet of a release: what it holds and why the rest was not kept.

- pairs per source dataset, task, embodiment and track;
- kept rate per stage: frames each stage produced OK over the frames it was given;
- the rejection breakdown by primary cause, laid out like the paper's failure-breakdown
  table (stage family, count, share): every frame x embodiment not kept counts once, for
  the earliest stage that rejected it (the ledger names each cause once; later stages
  only mark it UPSTREAM).
"""

from __future__ import annotations

import pandas as pd

# the paper's four families (Table "pseudogt_failure_breakdown"), plus the input stages;
# keyed in pipeline order
FAMILY = {"ingest": "Input / source", "estimate_hands": "Input / source", "registration": "Input / source", "segment": "Segmentation",
          "restore_background": "Background restoration / inpainting", "retarget": "Hand retargeting",
          "render": "Rendering / compositing", "composite": "Rendering / compositing",
          "harmonize": "Rendering / compositing", "qc": "Rendering / compositing"}


def primary_causes(ledger: pd.DataFrame, embodiments: list[str], stages=tuple(FAMILY)) -> pd.DataFrame:
    """One row per rejected (clip, embodiment, frame): its earliest rejecting stage
    (``stages``: the pipeline order)."""
    if ledger is None or not len(ledger):
        return pd.DataFrame(columns=["clip", "embodiment", "frame", "stage", "reason_name"])
    rank = {s: i for i, s in enumerate(stages)}
    rows = ledger[ledger["frame"] >= 0]
    clip_level = rows[rows["embodiment"] == ""]
    expanded = pd.concat([rows[rows["embodiment"] != ""],
                          *(clip_level.assign(embodiment=e) for e in embodiments)], ignore_index=True)
    expanded = expanded.assign(rank=expanded["stage"].map(rank))
    first = expanded.sort_values("rank", kind="stable").drop_duplicates(["clip", "embodiment", "frame"])
    return first[["clip", "embodiment", "frame", "stage", "reason_name"]].reset_index(drop=True)


def build(pairs: pd.DataFrame, status: pd.DataFrame, ledger: pd.DataFrame, embodiments: list[str]) -> dict:
    """``status``: frames per (stage, status) over the released clips (``status_counts``)."""
    counts = {k: {str(a): int(n) for a, n in pairs.groupby(k).size().items()} if len(pairs) else {}
              for k in ("dataset", "task", "embodiment", "track")}
    kept = {}
    for stage, g in status.groupby("stage", sort=False):
        given = int(g.loc[g["status"] != "UPSTREAM", "frames"].sum())
        ok = int(g.loc[g["status"] == "OK", "frames"].sum())
        kept[stage] = {"ok": ok, "given": given, "rate": ok / given if given else None}
    causes = primary_causes(ledger, embodiments)
    total = len(causes)
    by_family = causes.groupby(causes["stage"].map(FAMILY)).size().sort_values(ascending=False) if total else pd.Series()
    breakdown = [{"cause": fam, "count": int(n), "share": n / total} for fam, n in by_family.items()]
    by_reason = causes.groupby(["stage", "reason_name"]).size().sort_values(ascending=False) if total else pd.Series()
    reasons = [{"stage": s, "reason": r, "count": int(n), "share": n / total} for (s, r), n in by_reason.items()]
    return {"pairs": int(len(pairs)), "counts": counts, "kept_rate": kept,
            "rejections": {"total": total, "by_cause": breakdown, "by_reason": reasons}}


def markdown(sheet: dict, title: str) -> str:
    from handedit.markdown import md

    out = [f"# {md(title)}", "", f"{sheet['pairs']} pairs.", ""]
    for k, rows in sheet["counts"].items():
        out += [f"## Pairs per {md(k)}", "", f"| {md(k)} | pairs |", "|---|---:|"]
        out += [f"| {md(name)} | {n:,} |" for name, n in sorted(rows.items())] + [""]
    out += ["## Kept rate per stage", "", "| stage | OK | given | rate |", "|---|---:|---:|---:|"]
    for stage, r in sheet["kept_rate"].items():
        rate = f"{100 * r['rate']:.2f}%" if r["rate"] is not None else "-"
        out.append(f"| {stage} | {r['ok']:,} | {r['given']:,} | {rate} |")
    rej = sheet["rejections"]
    total = rej["total"]
    out += ["", "## Rejections by primary cause", "", "| Primary failure cause | Share of non-kept frames |", "|---|---:|"]
    out += [f"| {md(r['cause'])} | {r['count']:,} / {total:,} ({100 * r['share']:.2f}%) |" for r in rej["by_cause"]]
    out += [f"| Total | {total:,} / {total:,} ({100 if total else 0}%) |", "",
            "| stage | reason | count | share |", "|---|---|---:|---:|"]
    out += [f"| {md(r['stage'])} | {md(r['reason'])} | {r['count']:,} | {100 * r['share']:.2f}% |" for r in rej["by_reason"]]
    if sheet.get("audits"):
        out += ["", "## Audits: kept pairs a reviewer accepts", "",
                "| audit | kept pairs reviewed | accepted | 95 % interval (Wilson) |", "|---|---:|---:|---:|"]
        for name, a in sorted(sheet["audits"].items()):
            p, (lo, hi) = a["precision"], a["precision_ci"]
            out.append(f"| {md(name)} | {a['n_kept_reviewed']:,} | {'-' if p is None else f'{100 * p:.1f}%'} | "
                       f"{'-' if p is None else f'{100 * lo:.1f}-{100 * hi:.1f}%'} |")
    return "\n".join(out) + "\n"
