"""Reports laid out like the paper's tables: per track, generic similarity and
embodiment-aware + VLM, best **bold** and second underlined per column; plus a radar
chart per track (OpenCV, no matplotlib) with lower-is-better metrics inverted (*).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from handedit.markdown import md
from handedit.metrics.suite import METRICS

# (group title, [(column label, metric)]) per table, in the paper's order
GENERIC = [
    ("PSNR", [("Full", "psnr_full"), ("BG", "psnr_bg"), ("ROI", "psnr_roi")]),
    ("SSIM", [("Full", "ssim_full"), ("BG", "ssim_bg"), ("ROI", "ssim_roi")]),
    ("LPIPS", [("Full", "lpips_full"), ("BG", "lpips_bg"), ("ROI", "lpips_roi")]),
    ("FID", [("Full", "fid_full"), ("ROI", "fid_roi")]),
]
EMBODIED = [
    ("Embodied Task Metrics", [("Removal", "removal"), ("Struct Fidelity", "struct_fidelity"),
                               ("ID Fidelity", "id_fidelity"), ("Interaction", "interaction")]),
    ("VLM Judge", [("SC", "vlm_sc"), ("PQ", "vlm_pq"), ("VLM", "vlm")]),
]
TABLES = {"generic": ("Generic Similarity", GENERIC), "embodied_vlm": ("Embodiment-Aware Metrics and VLM Judgment", EMBODIED)}
# Rows shown for reference, like the paper's grey Pseudo-GT row: never bold/underlined.
REFERENCE_ROWS = ("Pseudo-GT",)
RADAR_METRICS = ["psnr_full", "ssim_full", "lpips_full", "fid_full", "removal", "struct_fidelity",
                 "id_fidelity", "interaction", "vlm"]
SHORT = {"psnr_full": "PSNR", "ssim_full": "SSIM", "lpips_full": "LPIPS", "fid_full": "FID", "removal": "Removal",
         "struct_fidelity": "Struct", "id_fidelity": "ID", "interaction": "Interact", "vlm": "VLM"}


def _fmt(metric: str, v: float) -> str:
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v:.2f}" if metric.startswith(("psnr", "fid")) else f"{v:.3f}"


def ranks(values: dict[str, float], metric: str) -> dict[str, int]:
    """editor -> 1 (best) / 2 (second) for one column; ties share a rank; NaN unranked."""
    hib = METRICS[metric][0]
    finite = sorted({round(v, 6) for v in values.values() if v is not None and math.isfinite(v)}, reverse=hib)
    out = {}
    for e, v in values.items():
        if v is not None and math.isfinite(v) and round(v, 6) in finite[:2]:
            out[e] = finite.index(round(v, 6)) + 1
    return out


@dataclass
class TrackTable:
    track: str  # Hand-only / Hand-Arm
    title: str
    groups: list
    rows: dict[str, dict[str, float]]  # editor -> metric -> value

    def columns(self) -> list[tuple[str, str, str]]:
        return [(g, label, m) for g, cols in self.groups for label, m in cols]

    def styled(self) -> dict[str, dict[str, tuple[str, int]]]:
        """editor -> metric -> (text, rank); reference rows (Pseudo-GT) are unranked and last."""
        cols = self.columns()
        ranked = {e: row for e, row in self.rows.items() if e not in REFERENCE_ROWS}
        r = {m: ranks({e: row.get(m, float("nan")) for e, row in ranked.items()}, m) for _, _, m in cols}
        order = [*ranked, *(e for e in self.rows if e in REFERENCE_ROWS)]
        return {e: {m: (_fmt(m, self.rows[e].get(m, float("nan"))), r[m].get(e, 0)) for _, _, m in cols} for e in order}

    def markdown(self) -> str:
        cols = self.columns()
        arrow = lambda m: "↑" if METRICS[m][0] else "↓"  # noqa: E731
        # generic columns read "PSNR Full"; the embodied/VLM labels stand alone
        name = lambda g, label: f"{g} {label}" if g in ("PSNR", "SSIM", "LPIPS", "FID") else label  # noqa: E731
        head = "| Model | " + " | ".join(f"{name(g, label)}{arrow(m)}" for g, label, m in cols) + " |"
        lines = [f"**{self.track} {self.title}** (best **bold**, second <u>underlined</u>)", "", head,
                 "|" + "---|" * (len(cols) + 1)]
        for e, cells in self.styled().items():
            vals = [f"**{s}**" if k == 1 else f"<u>{s}</u>" if k == 2 else s for s, k in (cells[m] for _, _, m in cols)]
            lines.append(f"| {'*' + md(e) + '* (reference)' if e in REFERENCE_ROWS else md(e)} | " + " | ".join(vals) + " |")
        return "\n".join(lines) + "\n"

    def latex(self) -> str:
        cols = self.columns()
        spec = "l|" + "|".join("c" * len(c) for _, c in self.groups)
        heads = [r"\multirow{2}{*}{\textbf{Model}}"]
        for i, (g, c) in enumerate(self.groups):
            bar = "|" if i < len(self.groups) - 1 else ""
            arrow = r"\uparrow" if METRICS[c[0][1]][0] else r"\downarrow"
            heads.append(rf"\multicolumn{{{len(c)}}}{{c{bar}}}{{\textbf{{{g}}}${arrow}$}}")
        head1 = " & ".join(heads) + r" \\"
        head2 = " & " + " & ".join(label for _, label, _ in cols) + r" \\"
        body = []
        for e, cells in self.styled().items():
            vals = [rf"\textbf{{{s}}}" if k == 1 else rf"\underline{{{s}}}" if k == 2 else s for s, k in (cells[m] for _, _, m in cols)]
            if e in REFERENCE_ROWS:  # the paper's grey reference row
                vals = [rf"\textcolor{{gray!50}}{{{v}}}" for v in vals]
                body.append(r"\rowcolor{gray!20} \textcolor{gray!50}{" + _tex_escape(e) + "} & " + " & ".join(vals) + r" \\")
                continue
            body.append(_tex_escape(e) + " & " + " & ".join(vals) + r" \\")
        return "\n".join([r"\begin{table*}[t]", r"\centering",
                          rf"\caption{{\textbf{{{self.track} {self.title}.}} Best and second-best model scores are bolded and underlined, respectively.}}",
                          rf"\begin{{tabular}}{{{spec}}}", r"\toprule", head1, head2, r"\midrule", *body,
                          r"\bottomrule", r"\end{tabular}", r"\end{table*}"]) + "\n"

    def csv(self) -> str:
        cols = self.columns()
        lines = ["model," + ",".join(m for _, _, m in cols)]
        for e, row in self.rows.items():
            lines.append(_csv_cell(e) + "," + ",".join("" if not math.isfinite(row.get(m, float("nan"))) else repr(float(row[m])) for _, _, m in cols))
        return "\n".join(lines) + "\n"


def _tex_escape(s: str) -> str:
    return "".join("\\" + c if c in "&%$#_{}" else c for c in s)


def _csv_cell(s: str) -> str:
    return f'"{s}"' if any(c in s for c in ',"\n') else s


def track_tables(track: str, rows: dict[str, dict[str, float]]) -> dict[str, TrackTable]:
    return {key: TrackTable(track, title, groups, rows) for key, (title, groups) in TABLES.items()}


def radar_scores(rows: dict[str, dict[str, float]], metrics: list[str] = RADAR_METRICS) -> tuple[list[str], dict[str, list[float]]]:
    """Per-axis min-max scores in [0.2, 1] (lower-is-better inverted); axes all-NaN are dropped."""
    axes = [m for m in metrics if any(math.isfinite(r.get(m, float("nan"))) for r in rows.values())]
    out = {e: [] for e in rows}
    for m in axes:
        sign = 1.0 if METRICS[m][0] else -1.0
        vals = {e: sign * r.get(m, float("nan")) for e, r in rows.items()}
        fin = [v for v in vals.values() if math.isfinite(v)]
        lo, hi = min(fin), max(fin)
        for e, v in vals.items():
            out[e].append(0.0 if not math.isfinite(v) else 1.0 if hi == lo else 0.2 + 0.8 * (v - lo) / (hi - lo))
    labels = [SHORT.get(m, m) + ("" if METRICS[m][0] else "*") for m in axes]
    return labels, out


PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
           (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207), (0, 0, 0)]


def radar_png(title: str, rows: dict[str, dict[str, float]], size: int = 640) -> np.ndarray:
    """(H,W,3) uint8 RGB radar chart; '*' marks an inverted (lower-is-better) axis."""
    labels, scores = radar_scores(rows)
    legend_w = 220
    img = np.full((size, size + legend_w, 3), 255, np.uint8)
    c = np.array([size / 2, size / 2 + 10])
    r = size * 0.34
    n = len(labels)
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(img, title, (12, 26), font, 0.7, (0, 0, 0), 2, cv2.LINE_AA)
    if n < 3:
        cv2.putText(img, "need >= 3 metrics for a radar", (12, 60), font, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
        return img
    ang = [-math.pi / 2 + 2 * math.pi * i / n for i in range(n)]
    pt = lambda a, s: (int(round(c[0] + s * r * math.cos(a))), int(round(c[1] + s * r * math.sin(a))))  # noqa: E731
    for ring in (0.25, 0.5, 0.75, 1.0):
        cv2.polylines(img, [np.array([pt(a, ring) for a in ang], np.int32)], True, (210, 210, 210), 1, cv2.LINE_AA)
    for a, label in zip(ang, labels):
        cv2.line(img, pt(a, 0), pt(a, 1), (190, 190, 190), 1, cv2.LINE_AA)
        x, y = pt(a, 1.16)
        (tw, th), _ = cv2.getTextSize(label, font, 0.5, 1)
        cv2.putText(img, label, (x - tw // 2, y + th // 2), font, 0.5, (40, 40, 40), 1, cv2.LINE_AA)
    for i, (e, s) in enumerate(scores.items()):
        color = PALETTE[i % len(PALETTE)]
        poly = np.array([pt(a, v) for a, v in zip(ang, s)], np.int32)
        overlay = img.copy()
        cv2.fillPoly(overlay, [poly], color)
        img = cv2.addWeighted(overlay, 0.12, img, 0.88, 0)
        cv2.polylines(img, [poly], True, color, 2, cv2.LINE_AA)
        y = 60 + 24 * i
        cv2.rectangle(img, (size + 10, y - 12), (size + 26, y + 2), color, -1)
        cv2.putText(img, e[:24], (size + 32, y), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "* lower is better (inverted)", (size + 10, size - 16), font, 0.42, (80, 80, 80), 1, cv2.LINE_AA)
    return img
