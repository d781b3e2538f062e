"""The paper's human evaluation of editors (Appendix E), from raters' scores.

Each edited output is rated by several raters on a five-point scale along three axes:
target-robot correctness (``target``), scene-and-interaction preservation
(``scene_interaction``) and realism with physical plausibility (``realism``). The statistics
are ``handedit.metrics.human``'s: Krippendorff's alpha and ICC(2,k) among raters, and the
metric-human Fleiss' kappa over editor pairs (ID Fidelity, Interaction and the VLM judge
against the three axes' mean opinion scores), pooled over the tracks.
"""

from __future__ import annotations

import math

import pandas as pd

from handedit.metrics.human import AXIS_METRIC, agreement_table

AXES = tuple(AXIS_METRIC)  # target, scene_interaction, realism
AXIS_TITLES = {"target": "Target-robot correctness", "scene_interaction": "Scene-and-interaction preservation",
               "realism": "Realism with physical plausibility"}
# the paper's rating guide (Table: anchors of scores 1, 3 and 5) and the instruction shown to annotators
GUIDE = {
    "target": {1: "The requested robot is missing, mostly human-like, or clearly the wrong embodiment.",
               3: "Robot cues are visible, but key morphology, material, or color details are wrong.",
               5: "The requested robot is clearly recognizable, with correct hand or hand-arm appearance."},
    "scene_interaction": {1: "The object, contact, occlusion, or scene layout is heavily changed.",
                          3: "The main interaction is partly preserved, but visible contact or object-state errors remain.",
                          5: "The original object state and hand-object interaction are well preserved."},
    "realism": {1: "Severe artifacts, broken geometry, or implausible scale/contact are present.",
                3: "The image is understandable, but artifacts or physical inconsistencies remain.",
                5: "The edit looks coherent, physically plausible, and visually natural."},
}
INSTRUCTION = ("You are evaluating an edited image for an egocentric human-to-robot hand editing benchmark. For each "
               "example, you will see a source image, a text instruction, a reference render of the target robot, and "
               "one edited image. The reference render shows which robot should appear in the edited image. It does not "
               "show the exact interaction pose. Please rate the edited image on three separate axes: whether the "
               "requested target robot is correctly shown; whether the original object, scene, and hand-object "
               "interaction are preserved; whether the final image looks realistic and physically plausible. Judge the "
               "edited image directly. Do not compare it to a hidden ground-truth image. Focus on whether the requested "
               "edit is successful and whether the final image remains coherent.")


def parse_rating(obj: dict, tracks: dict[str, str], editors: set[str]) -> list[dict]:
    """One output's ratings, checked: ``{"item", "editor", "rater", "target", "scene_interaction",
    "realism"}`` with integer scores 1-5 (an axis may be left out). ``tracks``: item -> track.
    Returns long rows (track, editor, item, rater, axis, score); raises ValueError saying what is wrong."""
    unknown = set(obj) - {"item", "editor", "rater", *AXES}
    if unknown:
        raise ValueError(f"unknown field(s) {sorted(unknown)}")
    if obj.get("item") not in tracks:
        raise ValueError(f"item {obj.get('item')!r} is not in the test set")
    if obj.get("editor") not in editors:
        raise ValueError(f"editor {obj.get('editor')!r} has no predictions in this benchmark")
    rater = obj.get("rater")
    if not isinstance(rater, str) or not rater.strip():
        raise ValueError("rater: a non-empty name is required")
    rows = []
    for axis in AXES:
        if axis not in obj:
            continue
        score = obj[axis]
        if isinstance(score, bool) or not isinstance(score, int) or not 1 <= score <= 5:
            raise ValueError(f"{axis}: {score!r} is not an integer from 1 to 5")
        rows.append({"track": tracks[obj["item"]], "editor": obj["editor"], "item": obj["item"], "rater": rater.strip(),
                     "axis": axis, "score": score})
    if not rows:
        raise ValueError(f"no score: give one or more of {list(AXES)}")
    return rows


def human_report(ratings: pd.DataFrame, metrics: dict[str, dict[str, dict[str, float]]]) -> dict:
    """Per axis: mean opinion score per (track, editor), Krippendorff's alpha, ICC(2,k), and the
    metric-human Fleiss' kappa with the number of editor pairs (``agreement_table``)."""
    table = agreement_table(ratings, metrics)
    mos = ratings.groupby(["axis", "track", "editor"])["score"].mean()
    out = {"raters": int(ratings["rater"].nunique()), "outputs": int(ratings[["editor", "item"]].drop_duplicates().shape[0]),
           "ratings": int(len(ratings)), "axes": {}}
    for axis in AXES:
        if axis not in table:
            continue
        row = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in table[axis].items()}
        row["metric"] = AXIS_METRIC[axis]
        row["mos"] = {t: {e: float(mos[(axis, t, e)]) for e in mos[axis][t].index} for t in mos[axis].index.get_level_values(0).unique()}
        out["axes"][axis] = row
    return out


def markdown(rep: dict) -> str:
    """The paper's human-evaluation tables: agreement among raters and with the metrics, then
    the mean opinion scores per track and editor."""
    def num(v) -> str:
        return "-" if v is None else f"{v:.3f}"

    axes = [a for a in AXES if a in rep["axes"]]
    out = [f"## Human evaluation ({rep['outputs']} outputs, {rep['raters']} raters, {rep['ratings']} ratings)", "",
           "| | " + " | ".join(AXIS_TITLES[a] for a in axes) + " |", "|---|" + "---:|" * len(axes)]
    out.append("| Krippendorff's alpha among raters | " + " | ".join(num(rep["axes"][a]["krippendorff_alpha"]) for a in axes) + " |")
    out.append("| ICC(2,k) among raters | " + " | ".join(num(rep["axes"][a]["icc_2k"]) for a in axes) + " |")
    out.append("| Metric-human Fleiss' kappa | " + " | ".join(
        f"{num(rep['axes'][a]['kappa'])} ({rep['axes'][a]['metric']}, {rep['axes'][a]['pairs']} pairs)" for a in axes) + " |")
    for axis in axes:
        out += ["", f"Mean opinion score, {AXIS_TITLES[axis]}:", "", "| track | editor | MOS |", "|---|---|---:|"]
        for track, editors in sorted(rep["axes"][axis]["mos"].items()):
            out += [f"| {track} | {e} | {m:.2f} |" for e, m in sorted(editors.items(), key=lambda kv: -kv[1])]
    return "\n".join(out) + "\n"


__all__ = ["AXES", "AXIS_TITLES", "GUIDE", "INSTRUCTION", "human_report", "markdown", "parse_rating"]
