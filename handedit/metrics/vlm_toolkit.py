"""The VLM judge under the toolkit's protocol (``--judge-protocol toolkit``).

Same two calls as the paper's judge (``handedit.metrics.vlm``: SC, then PQ), built the way the
authors' toolkit builds them:

- inputs are labelled JPEG images (quality 95), each preceded by a text label: the full source
  and edited images, a zoom of the edited ROI (human | robot masks, bbox + 24 px, at least
  96 px, shifted into the image), source and edited object-contact crops (the object mask
  grown by a 17 px max filter, bbox + 32 px, at least 96 px; without an object mask the ROI
  zoom stands in for the edited one), reference A (the target's render) and up to three
  distractor references B, C, D (other targets of the same track first);
- the SC answer adds identity fields: the chosen reference, whether it is A, the alignment to
  A and to the nearest distractor, and the margin between them; when the judge picks a
  distractor, ``target_embodiment_match`` is capped at 3;
- answers are read leniently as the toolkit reads them (any JSON object in the reply; each
  score rounded and clamped to 1..5, a missing one stays empty and empties its aspect);
  SC and PQ are the aspect minima mapped by (s - 1) / 4, VLM = sqrt(SC * PQ).

The prompt wording is this project's (the paper's prompts extended with the crops and the
identity fields), not a copy of the toolkit's. The answer cache key includes the protocol.
"""

from __future__ import annotations

import base64
import io
import json
import math
import re
from dataclasses import dataclass, field

import numpy as np
from PIL import Image, ImageFilter

from handedit.metrics.vlm import PQ_FIELDS, SC_FIELDS, MalformedAnswer

ID_FIELDS = ("correct_ref_alignment", "nearest_wrong_ref_alignment", "identity_margin")
ROI_PAD, CONTACT_PAD, MIN_CROP = 24, 32, 96
COLUMNS = {"SC": "VLM-SC", "PQ": "VLM-PQ", "VLM": "VLM", **{f: f"VLM-{f}" for f in SC_FIELDS + PQ_FIELDS + ID_FIELDS},
           "target_choice_correct": "VLM-target_choice_correct"}


@dataclass
class JudgeInputs:
    """One item for the toolkit judge: uint8 RGB images, bool masks (None: absent)."""

    src: np.ndarray
    pred: np.ndarray
    instruction: str
    human_mask: np.ndarray | None = None
    robot_mask: np.ndarray | None = None
    object_mask: np.ndarray | None = None
    reference: np.ndarray | None = None
    distractors: list[np.ndarray] = field(default_factory=list)


# ---------------------------------------------------------------------------------------
# crops

def _fit(mask: np.ndarray, size: tuple[int, int]) -> Image.Image:
    m = Image.fromarray((np.asarray(mask) > 0).astype(np.uint8) * 255)
    return m if m.size == size else m.resize(size, Image.NEAREST)


def grow_to_min(box: tuple[int, int, int, int], size: tuple[int, int], min_size: int) -> tuple[int, int, int, int]:
    """A (x0, y0, x1, y1) box widened about its centre to ``min_size``, then moved inside the image."""
    x0, y0, x1, y1 = box
    w, h = size
    tw, th = max(x1 - x0, min_size), max(y1 - y0, min_size)
    cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
    x0, x1 = int(round(cx - tw / 2.0)), int(round(cx + tw / 2.0))
    y0, y1 = int(round(cy - th / 2.0)), int(round(cy + th / 2.0))
    if x0 < 0:
        x1, x0 = x1 - x0, 0
    if y0 < 0:
        y1, y0 = y1 - y0, 0
    if x1 > w:
        x0, x1 = x0 - (x1 - w), w
    if y1 > h:
        y0, y1 = y0 - (y1 - h), h
    x0, y0 = max(0, x0), max(0, y0)
    return x0, y0, min(w, max(x0 + 1, x1)), min(h, max(y0 + 1, y1))


def crop_by_masks(image: np.ndarray, masks: list[np.ndarray | None], pad: int, min_size: int = MIN_CROP,
                  grow_px: int = 0) -> Image.Image | None:
    """The image cropped to the union of ``masks`` (bbox + ``pad``, at least ``min_size``); None without a mask."""
    im = Image.fromarray(np.ascontiguousarray(image))
    valid = [m for m in masks if m is not None]
    if not valid:
        return None
    merged = np.zeros((im.size[1], im.size[0]), bool)
    for m in valid:
        merged |= np.asarray(_fit(m, im.size)) > 127
    mask = Image.fromarray(merged.astype(np.uint8) * 255)
    if grow_px > 0:
        k = max(3, int(grow_px) * 2 + 1)
        mask = mask.filter(ImageFilter.MaxFilter(k + (k % 2 == 0)))
    box = mask.getbbox()
    if box is None:
        return None
    x0, y0, x1, y1 = box
    box = (max(0, x0 - pad), max(0, y0 - pad), min(im.size[0], x1 + pad), min(im.size[1], y1 + pad))
    return im.crop(grow_to_min(box, im.size, min_size))


def jpeg_data_url(image: Image.Image | np.ndarray) -> str:
    im = image if isinstance(image, Image.Image) else Image.fromarray(np.ascontiguousarray(image))
    buf = io.BytesIO()
    im.convert("RGB").save(buf, format="JPEG", quality=95)
    return "data:image/jpeg;base64," + base64.b64encode(buf.getvalue()).decode()


# ---------------------------------------------------------------------------------------
# prompts (this project's wording)

def sc_prompt(instruction: str, has_ref: bool, n_distractors: int, has_roi: bool, has_contact: bool) -> str:
    refs = ("(4) a URDF reference render of the target robot embodiment, labelled A"
            + (f", and {n_distractors} render(s) of other robots of the same kind, labelled B onwards." if n_distractors else ".")
            if has_ref else "(4) no reference render: judge the target from the text instruction alone.")
    crops = [
        "A zoom of the edited region is included: use it for the robot's identity, any remaining human skin, and local shape."
        if has_roi else "No zoom of the edited region is available: judge from the full images.",
        "Crops of the object-contact region in the source and the edited image are included: use them for interaction preservation."
        if has_contact else "No object-contact crops are available.",
    ]
    ident = ("Decide which reference the edited robot resembles most (its arm links, wrist and hand shape) and report it."
             if n_distractors else "Only the target reference is given: compare the edited robot with it alone.")
    return f"""You are evaluating an image editing result for a benchmark on egocentric hand-to-dexterous-robot image editing.

You are given:
(1) a source image showing a human hand or hand-arm interacting with an object;
(2) an edited image;
(3) a text instruction describing the target robot embodiment;
{refs}
{crops[0]}
{crops[1]}
{ident}

Please assign four 1--5 sub-scores:
Robotness: Whether the edited region is clearly robotic rather than human-like.
Target-embodiment match: Whether the robot matches the requested target embodiment, judged first on the zoom and the reference renders.
Interaction preservation: Whether the original object state, contact relationship, and hand-object interaction remain recognizable.
Scene preservation: Whether the surrounding scene structure is preserved without unnecessary global changes.

And the identity fields:
chosen_reference: the letter of the reference the edited robot matches best, or "unknown";
target_choice_correct: true if that letter is A, else false;
correct_ref_alignment: 1--5, how closely the edited robot matches reference A;
nearest_wrong_ref_alignment: 1--5, how closely it matches the most similar other reference (1 if there is none);
identity_margin: 1--5, how clearly A is the closer one (1: another reference is clearly closer, 3: unclear, 5: clearly A).

Use the following scale for each sub-score: 1 = failure, 2 = largely incorrect, 3 = partially correct, 4 = mostly correct, and 5 = clearly successful.

Respond with a single JSON object with the fields robotness, target_embodiment_match, interaction_preservation, scene_preservation, chosen_reference, target_choice_correct, correct_ref_alignment, nearest_wrong_ref_alignment, identity_margin, reasoning.

Text instruction: {instruction}"""


def pq_prompt(has_roi: bool, has_contact: bool) -> str:
    lines = [
        "A zoom of the edited region is included: look there for broken robot parts, remaining human texture and boundary errors."
        if has_roi else "No zoom of the edited region is available: inspect the full image.",
        "A crop of the edit boundary or the robot-object contact is included: base local coherence on it."
        if has_contact else "No contact crop is available: base local coherence on the visible edit boundaries.",
    ]
    return f"""You are evaluating the perceptual quality of an edited image.

You are given the edited image and zoomed crops of it. Judge only visual quality, not whether the requested robot is correct.
{lines[0]}
{lines[1]}

Please assign three 1--5 sub-scores:
Naturalness: Whether the edited image looks visually plausible as a single image.
Artifact absence: Whether the image avoids visible artifacts such as duplicated fingers, broken geometry, halos, blur, or distorted robot parts.
Local coherence: Whether boundaries, texture, lighting, and occlusion near the edited region are consistent with the surrounding scene.

Use the following scale for each sub-score: 1 = very poor, 2 = poor, 3 = acceptable, 4 = good, and 5 = high perceptual quality.

Respond with a single JSON object with the fields naturalness, artifact_absence, local_coherence, reasoning."""


# ---------------------------------------------------------------------------------------
# requests and answers

def requests(x: JudgeInputs) -> tuple[list[tuple[str, str | None]], list[tuple[str, str | None]], dict]:
    """(SC content, PQ content, flags): each content a list of (text, image data URL or None)."""
    roi = crop_by_masks(x.pred, [x.human_mask, x.robot_mask], ROI_PAD)
    src_contact = crop_by_masks(x.src, [x.object_mask], CONTACT_PAD, grow_px=max(1, CONTACT_PAD // 4))
    pred_contact = crop_by_masks(x.pred, [x.object_mask], CONTACT_PAD, grow_px=max(1, CONTACT_PAD // 4))
    if pred_contact is None and roi is not None:
        pred_contact = roi
    has_ref = x.reference is not None
    distractors = x.distractors if has_ref else []
    flags = {"vlm_has_urdf_ref": has_ref, "vlm_num_distractors": len(distractors), "vlm_has_roi_crop": roi is not None,
             "vlm_has_contact_crop": pred_contact is not None}
    sc = [(sc_prompt(x.instruction, has_ref, len(distractors), roi is not None,
                     src_contact is not None and pred_contact is not None), None)]
    for label, im in (("Source image:", x.src), ("Edited image:", x.pred), ("Edited region (zoom):", roi),
                      ("Source object-contact region:", src_contact), ("Edited object-contact region:", pred_contact),
                      ("Reference A (the target robot):", x.reference)):
        if im is not None:
            sc.append((label, jpeg_data_url(im)))
    for k, d in enumerate(distractors):
        sc.append((f"Reference {chr(ord('B') + k)} (another robot):", jpeg_data_url(d)))
    pq = [(pq_prompt(roi is not None, pred_contact is not None), None)]
    for label, im in (("Edited image:", x.pred), ("Edited region (zoom):", roi), ("Edited boundary or contact region:", pred_contact)):
        if im is not None:
            pq.append((label, jpeg_data_url(im)))
    return sc, pq, flags


def score_1_to_5(value) -> int | None:
    try:
        v = int(round(float(value)))
    except (TypeError, ValueError):
        return None
    return max(1, min(5, v))


def as_binary(value) -> int | None:
    if isinstance(value, bool):
        return int(value)
    if value is None:
        return None
    t = str(value).strip().lower()
    if t in {"true", "yes", "y", "1", "correct", "target", "a"}:
        return 1
    if t in {"false", "no", "n", "0", "incorrect"}:
        return 0
    try:
        return int(float(t) > 0.5)
    except ValueError:
        return None


def lenient_json(text: str) -> dict:
    """Any JSON object in the reply; MalformedAnswer when there is none (so the call is retried)."""
    text = (text or "").strip()
    for candidate in (text, (re.search(r"\{.*\}", text, flags=re.S) or [None])[0]):
        if candidate:
            try:
                obj = json.loads(candidate)
            except ValueError:
                continue
            if isinstance(obj, dict):
                return obj
    raise MalformedAnswer(f"no JSON object in the reply: {text[:120]!r}")


def combine(sc: dict, pq: dict, flags: dict) -> dict:
    """The toolkit's row from the two answers: clamped scores, the target-match cap, SC/PQ/VLM."""
    row: dict = dict(flags)
    for f in SC_FIELDS + ID_FIELDS:
        row[f] = score_1_to_5(sc.get(f))
    for f in PQ_FIELDS:
        row[f] = score_1_to_5(pq.get(f))
    row["chosen_reference"] = str(sc.get("chosen_reference", ""))
    row["target_choice_correct"] = as_binary(sc.get("target_choice_correct"))
    row["reasoning_sc"], row["reasoning_pq"] = str(sc.get("reasoning", "")), str(pq.get("reasoning", ""))
    if row["target_choice_correct"] == 0 and row["target_embodiment_match"] is not None:
        row["target_embodiment_match"] = min(row["target_embodiment_match"], 3)  # a distractor was chosen
    for name, fields in (("SC", SC_FIELDS), ("PQ", PQ_FIELDS)):
        values = [row[f] for f in fields if row[f] is not None]
        row[name] = (min(values) - 1.0) / 4.0 if len(values) == len(fields) else float("nan")
    sc_v, pq_v = row["SC"], row["PQ"]
    row["VLM"] = math.sqrt(max(sc_v, 0.0) * max(pq_v, 0.0)) if math.isfinite(sc_v) and math.isfinite(pq_v) else float("nan")
    return row


def columns(row: dict) -> dict:
    """The toolkit's per-sample columns of a judged row (``VLM-SC``, ``VLM-robotness``, ...)."""
    out = {dst: (float("nan") if row.get(src) is None else row[src]) for src, dst in COLUMNS.items()}
    out.update({f"VLM-{k}": row[k] for k in ("chosen_reference", "vlm_has_urdf_ref", "vlm_num_distractors",
                                             "vlm_has_roi_crop", "vlm_has_contact_crop") if k in row})
    return out
