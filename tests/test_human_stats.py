"""Human-evaluation statistics against textbook values and independent implementations."""

from __future__ import annotations

from itertools import permutations

import numpy as np
import pytest

from handedit.metrics.human import agreement_table, fleiss_kappa, icc_2k, krippendorff_alpha_ordinal, metric_human_agreement, pairwise_choices

NAN = np.nan
# Krippendorff (2011), "Computing Krippendorff's Alpha-Reliability": 4 coders x 12 units
KRIPP = np.array([
    [1, 2, 3, 3, 2, 1, 4, 1, 2, NAN, NAN, NAN],
    [1, 2, 3, 3, 2, 2, 4, 1, 2, 5, NAN, 3],
    [NAN, 3, 3, 3, 2, 3, 4, 2, 2, 5, 1, NAN],
    [1, 2, 3, 3, 2, 4, 4, 1, 2, 5, 1, NAN],
])
# Shrout & Fleiss (1979), Table 2: 6 targets x 4 judges; ICC(2,1) = .29, ICC(2,4) = .62
SHROUT = np.array([[9, 2, 5, 8], [6, 1, 3, 2], [8, 4, 6, 8], [7, 1, 2, 6], [10, 5, 6, 9], [6, 2, 4, 7]], float)
# Fleiss (1971) as reproduced on Wikipedia: 10 subjects, 14 raters, 5 categories; kappa = 0.210
FLEISS = np.array([[0, 0, 0, 0, 14], [0, 2, 6, 4, 2], [0, 0, 3, 5, 6], [0, 3, 9, 2, 0], [2, 2, 8, 1, 1],
                   [7, 7, 0, 0, 0], [3, 2, 6, 3, 0], [2, 5, 3, 2, 2], [6, 5, 2, 1, 0], [0, 2, 2, 3, 7]])


def naive_alpha_ordinal(r: np.ndarray) -> float:
    """alpha = 1 - D_o / D_e from explicit pairs of values (no coincidence matrix)."""
    units = [col[np.isfinite(col)] for col in r.T]
    units = [u for u in units if len(u) >= 2]
    pooled = np.concatenate(units)
    vals = np.unique(pooled)
    n_v = {v: (pooled == v).sum() for v in vals}

    def d2(a, b):  # ordinal: (sum of frequencies from a to b - (n_a + n_b)/2)^2
        lo, hi = min(a, b), max(a, b)
        return (sum(n_v[v] for v in vals if lo <= v <= hi) - (n_v[a] + n_v[b]) / 2) ** 2

    n = len(pooled)
    d_o = sum(sum(d2(u[i], u[j]) for i, j in permutations(range(len(u)), 2)) / (len(u) - 1) for u in units) / n
    d_e = sum(d2(a, b) for a in pooled for b in pooled) / (n * (n - 1))
    return 1 - d_o / d_e


def test_krippendorff_alpha_ordinal():
    assert krippendorff_alpha_ordinal(KRIPP) == pytest.approx(0.815, abs=5e-4)
    r = np.random.default_rng(0)
    for _ in range(3):
        truth = r.integers(1, 6, 30)
        data = np.clip(truth + r.integers(-1, 2, (5, 30)), 1, 5).astype(float)
        data[r.random(data.shape) < 0.15] = NAN
        assert krippendorff_alpha_ordinal(data) == pytest.approx(naive_alpha_ordinal(data), abs=1e-10)
    perfect = np.tile(np.arange(1, 6, dtype=float), (3, 1))
    assert krippendorff_alpha_ordinal(perfect) == pytest.approx(1.0)


def test_icc_2k():
    assert icc_2k(SHROUT) == pytest.approx(0.62, abs=0.005)
    # independent: ICC(2,1) from explicit mean squares, stepped up by Spearman-Brown
    r = np.random.default_rng(1)
    x = r.integers(1, 6, (40, 1)) + r.normal(0, 0.8, (40, 5)) + r.normal(0, 0.3, 5)
    n, k = x.shape
    rows, cols = x.mean(1), x.mean(0)
    msr = k * sum((m - x.mean()) ** 2 for m in rows) / (n - 1)
    msc = n * sum((m - x.mean()) ** 2 for m in cols) / (k - 1)
    mse = sum((x[i, j] - rows[i] - cols[j] + x.mean()) ** 2 for i in range(n) for j in range(k)) / ((n - 1) * (k - 1))
    icc21 = (msr - mse) / (msr + (k - 1) * mse + k * (msc - mse) / n)
    assert icc_2k(x) == pytest.approx(k * icc21 / (1 + (k - 1) * icc21), rel=1e-9)
    with pytest.raises(ValueError):
        icc_2k(np.array([[1.0, NAN], [2.0, 3.0]]))


def test_fleiss_kappa_and_pairwise_agreement():
    assert fleiss_kappa(FLEISS) == pytest.approx(0.210, abs=5e-4)
    # two raters who always agree on binary choices (both categories used) -> kappa 1
    assert fleiss_kappa(np.array([[2, 0], [0, 2], [2, 0]])) == pytest.approx(1.0)
    human = {"a": 4.2, "b": 3.1, "c": 2.5, "d": 3.9}
    same = {"a": 0.9, "b": 0.5, "c": 0.2, "d": 0.8}
    table = pairwise_choices(human, same)
    assert table.shape == (12, 2) and set(map(tuple, table)) == {(2.0, 0.0), (0.0, 2.0)}
    # metric order a > c > d > b vs human a > d > b > c: pairs (c,d) and (b,c) disagree,
    # so P_bar = 4/6 and P_e = 1/2 (both orders) -> kappa = (4/6 - 1/2) / (1/2) = 1/3
    assert fleiss_kappa(pairwise_choices(human, dict(same, c=0.85))) == pytest.approx(1 / 3)
    kappa, pairs = metric_human_agreement([(human, same), (human, same)])
    assert pairs == 12 and kappa == pytest.approx(1.0)
    # lower-is-better metric (e.g. LPIPS) with the ordering reversed agrees perfectly too
    assert metric_human_agreement([(human, {e: -v for e, v in same.items()})], higher_is_better=False)[0] == pytest.approx(1.0)
    reversed_ = {e: -v for e, v in same.items()}
    assert metric_human_agreement([(human, reversed_)])[0] < 0


def test_agreement_table_from_long_ratings():
    import pandas as pd

    r = np.random.default_rng(3)
    quality = {"A": 4.5, "B": 3.5, "C": 2.0, "D": 1.5}  # editors' true quality
    rows = []
    for track in ("hand", "hand_arm"):
        for editor, q in quality.items():
            for item in range(6):
                truth = np.clip(q + r.normal(0, 0.5), 1, 5)
                for rater in range(5):
                    for axis in ("target", "scene_interaction", "realism"):
                        rows.append((track, editor, item, rater, axis, int(np.clip(round(truth + r.normal(0, 0.4)), 1, 5))))
    df = pd.DataFrame(rows, columns=["track", "editor", "item", "rater", "axis", "score"])
    agree = {t: {e: {"id_fidelity": q, "interaction": q, "vlm": q} for e, q in quality.items()} for t in ("hand", "hand_arm")}
    table = agreement_table(df, agree)
    for axis in ("target", "scene_interaction", "realism"):
        row = table[axis]
        assert row["pairs"] == 12 and row["units"] == 48 and row["raters"] == 5
        assert row["kappa"] == pytest.approx(1.0)
        assert 0.5 < row["krippendorff_alpha"] < 1 and 0.8 < row["icc_2k"] < 1
        sub = df[df["axis"] == axis].pivot_table(index=["track", "editor", "item"], columns="rater", values="score")
        assert row["krippendorff_alpha"] == pytest.approx(naive_alpha_ordinal(sub.to_numpy().T.astype(float)))
    flipped = {t: {e: {"id_fidelity": -q} for e, q in quality.items()} for t in agree}
    assert agreement_table(df, flipped, {"target": "id_fidelity"})["target"]["kappa"] < 0
