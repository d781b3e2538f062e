"""The audit: how often a person agrees with QC, from a stratified sample of a run's pairs.

The paper screens its pairs by hand: an annotator looked at sampled non-kept frames and gave
each one primary cause (retargeting 63.5 %, segmentation 18.5 %, restoration 11.7 %,
rendering/compositing 6.3 %). Here a sample of kept *and* rejected frame x embodiment pairs is
drawn per stratum (clip, embodiment, track, and for rejected pairs the reason), reviewers give
each item keep / reject with a cause, and the report answers "of the kept pairs, a person
accepts X % (Wilson 95 % interval)", the agreement between QC and reviewers (Cohen's kappa)
and between reviewers (Fleiss' kappa), per embodiment and track.

Pure functions on tables: the run's files are ``handedit.storage.audit``'s.
"""

from __future__ import annotations

import math
from typing import Iterable

import numpy as np
import pandas as pd

from handedit.metrics.human import fleiss_kappa

CAUSES = ("retargeting", "segmentation", "restoration", "rendering", "input")
VERDICTS = ("keep", "reject")
# the stage that first rejected a pair -> the paper's primary cause
CAUSE_OF_STAGE = {"ingest": "input", "estimate_hands": "input", "registration": "input", "segment": "segmentation",
                  "restore_background": "restoration", "retarget": "retargeting", "render": "rendering",
                  "composite": "rendering", "harmonize": "rendering", "qc": "rendering"}
ITEM_COLUMNS = ("id", "clip", "embodiment", "track", "frame", "kept", "stage", "reason")


def item_id(clip: str, embodiment: str, frame: int) -> str:
    """The pair's id, as releases name it."""
    return f"{clip}/{embodiment}/{int(frame)}"


def _allocate(sizes: pd.Series, n: int) -> pd.Series:
    """``n`` draws over strata of ``sizes``: every stratum one while ``n`` covers them all, then
    one at a time to the stratum furthest below its proportional share (never more than a
    stratum holds)."""
    total = int(sizes.sum())
    n = min(n, total)
    out = np.ones(len(sizes), int) if n >= len(sizes) else np.zeros(len(sizes), int)
    share, size = sizes.to_numpy() / max(total, 1) * n, sizes.to_numpy()
    while out.sum() < n:
        deficit = np.where(out < size, share - out, -np.inf)
        out[int(np.argmax(deficit))] += 1
    return pd.Series(out, index=sizes.index)


def sample(universe: pd.DataFrame, n: int, kept_share: float = 0.5, seed: int = 0) -> pd.DataFrame:
    """A stratified sample of ``n`` items from ``universe`` (``ITEM_COLUMNS``): ``kept_share``
    of them kept pairs (by clip, embodiment and track), the rest rejected pairs (by clip,
    embodiment, track and reason); where one side has too few, the other makes up the count.
    The same universe and seed give the same items."""
    rng = np.random.default_rng(seed)
    kept, rejected = universe[universe["kept"]], universe[~universe["kept"]]
    n_kept = min(len(kept), round(n * kept_share))
    n_rej = min(len(rejected), n - n_kept)
    n_kept = min(len(kept), n - n_rej)
    parts = []
    for rows, k, keys in ((kept, n_kept, ["clip", "embodiment", "track"]),
                          (rejected, n_rej, ["clip", "embodiment", "track", "stage", "reason"])):
        if k <= 0:
            continue
        rows = rows.sort_values(["clip", "embodiment", "frame"], kind="stable")
        groups = rows.groupby(keys, sort=True)
        take = _allocate(groups.size(), k)
        for key, group in groups:
            m = int(take[key])
            if m:
                parts.append(group.iloc[np.sort(rng.choice(len(group), m, replace=False))])
    out = pd.concat(parts, ignore_index=True) if parts else universe.iloc[:0]
    return out.sort_values(["clip", "embodiment", "frame"], kind="stable").reset_index(drop=True)


def parse_verdict(obj: object, items: set[str]) -> dict:
    """One verdict, checked: ``{"item", "verdict": keep|reject, "cause": one of CAUSES or null
    (a rejection may name one; a keep names none), "reviewer"}``. Raises ValueError saying what
    is wrong."""
    if not isinstance(obj, dict):
        raise ValueError("not a JSON object")
    unknown = set(obj) - {"item", "verdict", "cause", "reviewer", "time"}
    if unknown:
        raise ValueError(f"unknown field(s) {sorted(unknown)}")
    if obj.get("item") not in items:
        raise ValueError(f"item {obj.get('item')!r} is not in this audit's sample")
    if obj.get("verdict") not in VERDICTS:
        raise ValueError(f"verdict {obj.get('verdict')!r}: expected one of {list(VERDICTS)}")
    cause = obj.get("cause")
    if cause is not None and cause not in CAUSES:
        raise ValueError(f"cause {cause!r}: expected one of {list(CAUSES)} or null")
    if obj["verdict"] == "keep" and cause is not None:
        raise ValueError("a keep verdict names no cause")
    reviewer = obj.get("reviewer")
    if not isinstance(reviewer, str) or not reviewer.strip():
        raise ValueError("reviewer: a non-empty name is required")
    return {"item": obj["item"], "verdict": obj["verdict"], "cause": cause, "reviewer": reviewer.strip(),
            "time": str(obj.get("time") or "")}


def latest(verdicts: Iterable[dict]) -> pd.DataFrame:
    """One verdict per (item, reviewer): the last given (verdicts in the order they were given)."""
    frame = pd.DataFrame(list(verdicts), columns=["item", "verdict", "cause", "reviewer", "time"])
    return frame.drop_duplicates(["item", "reviewer"], keep="last").reset_index(drop=True)


def wilson(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval of a proportion k/n (95 % by default); (0, 1) without data."""
    if n <= 0:
        return 0.0, 1.0
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def cohen_kappa(a: Iterable[bool], b: Iterable[bool]) -> float | None:
    """Cohen's kappa of two binary raters on the same items (None without items; 1.0 when both
    agree on everything with one class only)."""
    a, b = np.asarray(list(a), bool), np.asarray(list(b), bool)
    if not len(a):
        return None
    po = float((a == b).mean())
    pe = float(a.mean() * b.mean() + (1 - a.mean()) * (1 - b.mean()))
    return 1.0 if pe == 1 else (po - pe) / (1 - pe)


def item_verdicts(items: pd.DataFrame, verdicts: pd.DataFrame) -> pd.DataFrame:
    """Each sampled item with its reviewers' verdict: the majority of its reviewers (a tie
    rejects: a pair two people disagree on is not one to publish) and the most named cause."""
    rows = []
    by_item = {k: g for k, g in verdicts.groupby("item")}
    for it in items.itertuples(index=False):
        g = by_item.get(it.id)
        if g is None:
            rows.append({"verdict": None, "cause": None, "reviewers": 0})
            continue
        keeps = int((g["verdict"] == "keep").sum())
        verdict = "keep" if keeps * 2 > len(g) else "reject"
        causes = g.loc[g["verdict"] == "reject", "cause"].dropna()
        rows.append({"verdict": verdict, "cause": causes.mode().iloc[0] if len(causes) else None, "reviewers": len(g)})
    return pd.concat([items.reset_index(drop=True), pd.DataFrame(rows)], axis=1)


def _measures(rows: pd.DataFrame, verdicts: pd.DataFrame) -> dict:
    reviewed = rows[rows["verdict"].notna()]
    kept = reviewed[reviewed["kept"]]
    rejected = reviewed[~reviewed["kept"]]
    accepted = int((kept["verdict"] == "keep").sum())
    also = int((rejected["verdict"] == "reject").sum())
    lo, hi = wilson(accepted, len(kept))
    rlo, rhi = wilson(also, len(rejected))
    # between reviewers: Fleiss' kappa over keep/reject, on the items with the most common number
    # (two or more) of reviewers, as it needs the same number per item
    multi = verdicts[verdicts["item"].isin(set(reviewed["id"]))].groupby("item")
    counts = np.array([[int((g["verdict"] == "keep").sum()), int((g["verdict"] == "reject").sum())]
                       for _, g in multi if len(g) >= 2]).reshape(-1, 2)
    inter = None
    if len(counts):
        counts = counts[counts.sum(axis=1) == np.bincount(counts.sum(axis=1)).argmax()]
        k = fleiss_kappa(counts)
        inter = None if not np.isfinite(k) else float(k)  # undefined when every verdict is the same
    return {"n_items": int(len(rows)), "n_reviewed": int(len(reviewed)),
            "n_kept_reviewed": int(len(kept)), "accepted": accepted,
            "precision": accepted / len(kept) if len(kept) else None, "precision_ci": [lo, hi],
            "n_rejected_reviewed": int(len(rejected)), "also_rejected": also,
            "rejection_agreement": also / len(rejected) if len(rejected) else None, "rejection_agreement_ci": [rlo, rhi],
            "qc_kappa": cohen_kappa(reviewed["kept"], reviewed["verdict"] == "keep"),
            "inter_reviewer_items": int(len(counts)), "inter_reviewer_kappa": inter}


def breakdown(rows: pd.DataFrame) -> list[dict]:
    """The paper's failure breakdown: share of each primary cause among the pairs reviewers
    rejected (their causes) next to the automatic one (the stage that first rejected the pair,
    over the rejected pairs of the sample)."""
    by_reviewer = rows[(rows["verdict"] == "reject") & rows["cause"].notna()]["cause"].value_counts()
    auto = rows[~rows["kept"]]["stage"].map(CAUSE_OF_STAGE).value_counts()
    out = []
    for cause in CAUSES:
        r, a = int(by_reviewer.get(cause, 0)), int(auto.get(cause, 0))
        out.append({"cause": cause, "reviewers": r, "reviewers_share": r / by_reviewer.sum() if by_reviewer.sum() else None,
                    "qc": a, "qc_share": a / auto.sum() if auto.sum() else None})
    return out


def report(items: pd.DataFrame, verdicts: pd.DataFrame) -> dict:
    """The audit's numbers over all items and per (embodiment, track); ``items`` as ``sample``
    returns them, ``verdicts`` as ``latest`` returns them."""
    rows = item_verdicts(items, verdicts)
    out = {**_measures(rows, verdicts), "breakdown": breakdown(rows), "per_embodiment": []}
    for (emb, track), g in rows.groupby(["embodiment", "track"], sort=True):
        out["per_embodiment"].append({"embodiment": emb, "track": track, **_measures(g, verdicts),
                                      "breakdown": breakdown(g)})
    out["items"] = [{"id": r.id, "clip": r.clip, "embodiment": r.embodiment, "track": r.track, "frame": int(r.frame),
                     "kept": bool(r.kept), "qc_reason": r.reason or None, "verdict": r.verdict, "cause": r.cause,
                     "reviewers": int(r.reviewers)} for r in rows.itertuples(index=False)]
    return out


def annotator_view(source: np.ndarray | None, human_mask: np.ndarray | None, background: np.ndarray | None,
                   pseudo_gt: np.ndarray | None, robot_mask: np.ndarray | None, height: int = 240) -> np.ndarray:
    """The paper's annotator view as one (height, 5 x width, 3) image: source | human-mask overlay
    | restored background | pseudo-GT | robot-mask overlay on the pseudo-GT. A missing panel
    (the pair was rejected before that stage) is grey with a cross."""
    import cv2

    ref = next((a for a in (source, background, pseudo_gt) if a is not None), None)
    h, w = (ref.shape[:2] if ref is not None else (height, height * 4 // 3))
    size = (max(1, round(w * height / h)), height)

    def tint(image, mask, colour):
        if image is None or mask is None:
            return None
        out = image.astype(np.float32)
        out[mask] = 0.5 * out[mask] + 0.5 * np.asarray(colour, np.float32)
        return out.astype(np.uint8)

    panels = []
    for p in (source, tint(source, human_mask, (255, 64, 64)), background, pseudo_gt, tint(pseudo_gt, robot_mask, (64, 128, 255))):
        if p is None:
            p = np.full((h, w, 3), 128, np.uint8)
            cv2.line(p, (0, 0), (w - 1, h - 1), (90, 90, 90), max(1, w // 160))
            cv2.line(p, (0, h - 1), (w - 1, 0), (90, 90, 90), max(1, w // 160))
        panels.append(cv2.resize(np.ascontiguousarray(p[..., :3]), size, interpolation=cv2.INTER_AREA))
    return np.concatenate(panels, axis=1)


__all__ = ["CAUSES", "annotator_view", "CAUSE_OF_STAGE", "ITEM_COLUMNS", "VERDICTS", "breakdown", "cohen_kappa", "item_id", "item_verdicts", "latest",
           "parse_verdict", "report", "sample", "wilson"]
