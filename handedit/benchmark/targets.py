"""Target names as the authors' toolkit spells them -> roster embodiments.

The toolkit canonicalises a manifest's ``target_name`` by lower-casing it and dropping
everything but letters and digits, then looking it up in its alias table (its
``handedit_eval/bank.py``); the roster's display names are its canonical names. The
aliases below are the toolkit's (data, not code), so ``inspire`` is RH56DFX, ``brainco``
is RM65 + BrainCo and ``orca`` is OrcaHand, exactly as the toolkit scores them.
"""

from __future__ import annotations

import re

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


def toolkit_reference_renders(folder) -> dict[str, "Path"]:
    """{embodiment id: render} of the authors' toolkit reference folder (``hand-only/*.png``,
    ``hand-arm/*.png``, one RViz-style render per target, named as the toolkit names them)."""
    from pathlib import Path

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
