"""Target names as the authors' toolkit spells them -> roster embodiments.

The toolkit canonicalises a manifest's ``target_name`` by lower-casing it and dropping
everything but letters and digits, then looking it up in its alias table (its
``handedit_eval/bank.py``); the roster's display names are its canonical names. The
aliases below are the toolkit's (data, not code), so ``inspire`` is RH56DFX, ``brainco``
is RM65 + BrainCo and ``orca`` is OrcaHand, exactly as the toolkit scores them.
"""

from __future__ import annotations

import re
from pathlib import Path

TOOLKIT_ALIASES = {
    "inspire": "RH56DFX", "orca": "OrcaHand", "shadow": "Shadow Hand", "schunksvh": "Schunk SVH",
    "brainco": "RM65 + BrainCo", "rm65brainco": "RM65 + BrainCo", "ur5schunkhand": "UR5 + Schunk Hand",
    "ur5shadowhand": "UR5 + Shadow Hand", "jakazu7dexhand021": "Jaka Zu7 + DexHand021", "kukasharpa": "KUKA + Sharpa",
}


def normalize_name(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "", (text or "").lower())


def resolve_target(name: str, scope: str | None = None):
    """The roster embodiment a toolkit target name means (None when it names none); ``scope``
    (``hand`` | ``hand_arm``) breaks ties the way the toolkit's group inference does."""
    from handedit.embodiments import list_embodiments

    if not name:
        return None
    key = normalize_name(TOOLKIT_ALIASES.get(normalize_name(name), name))
    found = [e for e in list_embodiments() if key in (normalize_name(e.name), normalize_name(e.id))]
    if scope is not None:
        found = [e for e in found if e.track == scope] or found
    return found[0] if found else None


def toolkit_reference_renders(folder) -> dict[str, Path]:
    """{embodiment id: render} of the authors' toolkit reference folder (``hand-only/*.png``,
    ``hand-arm/*.png``, one RViz-style render per target, named as the toolkit names them)."""
    out = {}
    for sub, scope in (("hand-only", "hand"), ("hand-arm", "hand_arm")):
        for p in sorted((Path(folder) / sub).glob("*.png")):
            emb = resolve_target(p.stem, scope)
            if emb is not None:
                out[emb.id] = p
    return out


def compact_descriptor(description: str, max_words: int = 18) -> str:
    """The short form the toolkit conditions on: the first sentence, at most ``max_words`` words."""
    first = (description or "").split(".", 1)[0].strip()
    words = first.split()
    return first if len(words) <= max_words else " ".join(words[:max_words]).rstrip(",;:")


def toolkit_reference_bank(items: list) -> list[tuple[list[list[str]] | None, list[str]]]:
    """Per manifest item, as the toolkit builds them from the manifest alone: (the reference
    views of its target collected over every item, when it has none of its own, else None;
    the judge's distractors: the first view of up to three other targets, the same track's
    first, in the order of the toolkit's "group:target" keys)."""
    from handedit.embodiments import get_embodiment
    from handedit.embodiments.errors import EmbodimentError

    def key(it) -> tuple[str, str]:
        return it.replacement_scope, it.embodiment or it.target_name

    bank: dict[tuple[str, str], list[list[str]]] = {}
    for it in items:
        views = bank.setdefault(key(it), [])
        for ref, mask in zip(it.urdf_ref_paths, it.urdf_mask_paths + [""] * len(it.urdf_ref_paths)):
            if [ref, mask] not in views:
                views.append([ref, mask])
    first = {k: views[0][0] for k, views in bank.items() if views}

    def order(k: tuple[str, str]) -> str:
        try:
            name = get_embodiment(k[1]).name
        except EmbodimentError:  # a target outside the roster keeps its own spelling
            name = k[1]
        return f"{'hand_only' if k[0] == 'hand' else 'hand_arm'}:{name}"

    keys = sorted(first, key=order)
    out = []
    for it in items:
        own = key(it)
        same = [k for k in keys if k != own and k[0] == own[0]]
        other = [k for k in keys if k != own and k[0] != own[0]]
        distractors = [first[k] for k in (same + other if len(same) < 3 else same)[:3]]
        out.append((None if it.urdf_ref_paths else bank.get(own, []), distractors))
    return out
