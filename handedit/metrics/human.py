"""Human-evaluation statistics (paper appendix "Human Evaluation Details").

- Krippendorff's alpha with the ordinal metric (agreement among annotators on 1-5 scales);
- ICC(2,k): two-way random effects, absolute agreement, mean of k raters (Shrout & Fleiss);
- Fleiss' kappa, and the metric-human pairwise agreement built on it: for every pair
  of editors within a track, the human "rater" prefers the editor with the higher MOS
  and the metric "rater" the one with the better score; pairs are pooled over tracks.
"""

from __future__ import annotations

from itertools import combinations
from typing import Mapping, Sequence

import numpy as np


def krippendorff_alpha_ordinal(ratings: np.ndarray) -> float:
    """alpha for a (raters, units) array of ordinal values; NaN marks a missing rating."""
    r = np.asarray(ratings, dtype=np.float64)
    if r.ndim != 2:
        raise ValueError(f"ratings must be (raters, units), got {r.shape}")
    values = np.unique(r[np.isfinite(r)])
    if values.size < 2:
        return float("nan")
    index = {v: i for i, v in enumerate(values)}
    o = np.zeros((values.size, values.size))
    for u in range(r.shape[1]):
        col = r[:, u][np.isfinite(r[:, u])]
        m = col.size
        if m < 2:
            continue  # unpairable unit
        idx = np.array([index[v] for v in col])
        counts = np.bincount(idx, minlength=values.size).astype(np.float64)
        o += (np.outer(counts, counts) - np.diag(counts)) / (m - 1)
    n_c = o.sum(axis=1)
    n = n_c.sum()
    if n <= 1:
        return float("nan")
    cum = np.cumsum(n_c)
    # ordinal delta^2(c,k) = (sum_{g=c..k} n_g - (n_c + n_k)/2)^2
    lo, hi = np.minimum.outer(np.arange(values.size), np.arange(values.size)), np.maximum.outer(np.arange(values.size), np.arange(values.size))
    between = cum[hi] - np.where(lo > 0, cum[lo - 1], 0.0)
    delta2 = (between - (n_c[:, None] + n_c[None, :]) / 2.0) ** 2
    d_o = (o * delta2).sum()
    d_e = (np.outer(n_c, n_c) * delta2).sum()
    if d_e == 0:
        return float("nan")
    return float(1.0 - (n - 1) * d_o / d_e)


def icc_2k(ratings: np.ndarray) -> float:
    """ICC(2,k) of an (n targets, k raters) array without missing values."""
    x = np.asarray(ratings, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2 or x.shape[1] < 2 or not np.isfinite(x).all():
        raise ValueError(f"ICC(2,k) needs a complete (targets>=2, raters>=2) array, got {x.shape}")
    n, k = x.shape
    grand = x.mean()
    ss_rows = k * ((x.mean(axis=1) - grand) ** 2).sum()
    ss_cols = n * ((x.mean(axis=0) - grand) ** 2).sum()
    ss_err = ((x - grand) ** 2).sum() - ss_rows - ss_cols
    msr, msc, mse = ss_rows / (n - 1), ss_cols / (k - 1), ss_err / ((n - 1) * (k - 1))
    denom = msr + (msc - mse) / n
    return float((msr - mse) / denom) if denom else float("nan")


def fleiss_kappa(counts: np.ndarray) -> float:
    """Fleiss' kappa of an (N subjects, K categories) count table, same raters per subject."""
    c = np.asarray(counts, dtype=np.float64)
    n_raters = c.sum(axis=1)
    if c.ndim != 2 or c.shape[0] == 0 or not np.allclose(n_raters, n_raters[0]) or n_raters[0] < 2:
        raise ValueError("Fleiss' kappa needs >= 1 subject and the same number (>= 2) of ratings per subject")
    n = n_raters[0]
    p_i = ((c**2).sum(axis=1) - n) / (n * (n - 1))
    p_j = c.sum(axis=0) / c.sum()
    p_bar, p_e = p_i.mean(), (p_j**2).sum()
    return float((p_bar - p_e) / (1 - p_e)) if p_e < 1 else float("nan")


def pairwise_choices(human: Mapping[str, float], metric: Mapping[str, float], higher_is_better: bool = True) -> np.ndarray:
    """(2 x pairs, 2) counts: column 0 = 'first editor preferred', column 1 = 'second'.

    Each editor pair with a strict preference from both the MOS and the metric (ties
    and NaNs carry no choice and are left out) appears in both orders, (A,B) and (B,A):
    which editor is "first" is arbitrary, and with one order only, editors listed
    best-first would put every choice in one category and make kappa undefined.
    Both orders leave the observed agreement unchanged and balance the categories.
    """
    editors = sorted(set(human) & set(metric))
    rows = []
    for a, b in combinations(editors, 2):
        h = human[a] - human[b]
        m = (metric[a] - metric[b]) * (1 if higher_is_better else -1)
        if not (np.isfinite(h) and np.isfinite(m)) or h == 0 or m == 0:
            continue
        row = [int(h > 0) + int(m > 0), int(h < 0) + int(m < 0)]
        rows += [row, row[::-1]]
    return np.asarray(rows, dtype=np.float64).reshape(-1, 2)


def metric_human_agreement(tracks: Sequence[tuple[Mapping[str, float], Mapping[str, float]]],
                           higher_is_better: bool = True) -> tuple[float, int]:
    """Fleiss' kappa of human vs metric pairwise choices pooled over tracks -> (kappa, pairs)."""
    table = np.concatenate([pairwise_choices(h, m, higher_is_better) for h, m in tracks] or [np.zeros((0, 2))])
    if len(table) == 0:
        return float("nan"), 0
    return fleiss_kappa(table), len(table) // 2


# Paper: ID Fidelity <-> target-robot correctness, Interaction <-> scene-and-interaction
# preservation, the VLM judge score <-> realism with physical plausibility.
AXIS_METRIC = {"target": "id_fidelity", "scene_interaction": "interaction", "realism": "vlm"}


def agreement_table(ratings, metrics: Mapping[str, Mapping[str, Mapping[str, float]]],
                    axis_metric: Mapping[str, str] = AXIS_METRIC) -> dict[str, dict[str, float]]:
    """The paper's human-agreement table from long-format ratings.

    ``ratings``: a pandas DataFrame with columns track, editor, item, rater, axis, score
    (one row per scalar rating). ``metrics[track][editor][metric]``: the automatic
    scores (e.g. the evaluate flow's per-track means). Returns, per axis: Krippendorff's
    alpha (units = track x editor x item), ICC(2,k) over units rated by all k raters,
    and the metric-human Fleiss' kappa over editor pairs pooled across tracks.
    """
    out: dict[str, dict[str, float]] = {}
    for axis, metric in axis_metric.items():
        r = ratings[ratings["axis"] == axis]
        if r.empty:
            continue
        wide = r.pivot_table(index=["track", "editor", "item"], columns="rater", values="score", aggfunc="mean")
        complete = wide.dropna()
        mos = r.groupby(["track", "editor"])["score"].mean()
        pairs = [({e: float(mos[(t, e)]) for e in mos[t].index},
                  {e: float(v.get(metric, np.nan)) for e, v in metrics.get(t, {}).items()})
                 for t in mos.index.get_level_values(0).unique()]
        kappa, n_pairs = metric_human_agreement(pairs)
        out[axis] = {
            "krippendorff_alpha": krippendorff_alpha_ordinal(wide.to_numpy().T),
            "icc_2k": icc_2k(complete.to_numpy()) if complete.shape[0] >= 2 and complete.shape[1] >= 2 else float("nan"),
            "kappa": kappa, "pairs": n_pairs, "units": len(wide), "raters": wide.shape[1],
        }
    return out
