"""Test-set items: which source frames x embodiments, and the instruction each editor gets.

A track is the set of embodiments of one replacement scope (hand-only: ``hand``,
hand-arm: ``hand_arm``). An item is one source frame edited into one embodiment of
that track; the paper uses N = 1K source frames x 13 embodiments per track. A frame
is eligible for an embodiment when that embodiment's QC kept it (a pseudo-GT exists).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

TRACK_NAMES = {"hand": "Hand-only", "hand_arm": "Hand-Arm"}
TEMPLATE = ("Replace the human {region} region with the robot shown in the reference render: {name}, "
            "described as {description} Preserve the original hand-object interaction, object state, "
            "and surrounding scene structure.")


def instruction(scope: str, name: str, description: str) -> str:
    """The paper's URDF-reference-conditioned template (appendix "Benchmark Execution Details")."""
    region = {"hand": "hand", "hand_arm": "hand-arm"}[scope]
    desc = description.strip()
    if desc and desc[-1] not in ".!?":
        desc += "."
    if desc.split(" ", 1)[0] in ("A", "An"):  # "described as a white robotic hand ..."
        desc = desc[0].lower() + desc[1:]
    return TEMPLATE.format(region=region, name=name, description=desc)


@dataclass(frozen=True)
class SourceFrame:
    clip: str
    frame: int


@dataclass
class TestItem:
    """One benchmark item; image payloads live in the benchmark folder, not here."""

    id: str
    scope: str
    clip: str
    frame: int
    embodiment: str
    target_name: str
    description: str
    instruction: str
    n_refs: int = 0
    extra: dict = field(default_factory=dict)


def item_id(scope: str, clip: str, frame: int, embodiment: str) -> str:
    return f"{scope}-{clip}-f{frame:06d}-{embodiment}"


def select_frames(kept: dict[str, dict[str, np.ndarray]], n_sources: int, seed: int = 0) -> list[SourceFrame]:
    """Pick up to ``n_sources`` source frames of one track, spread over clips.

    ``kept[clip][embodiment]`` is a bool per frame (QC kept it). Frames kept for the
    most embodiments come first (so each source yields as many items as possible);
    within that, a seeded shuffle spreads the pick over clips and time.
    """
    rng = np.random.default_rng(seed)
    cands: list[tuple[int, float, SourceFrame]] = []
    for clip in sorted(kept):
        per_emb = list(kept[clip].values())
        if not per_emb:
            continue
        count = np.sum(per_emb, axis=0)
        for f in np.flatnonzero(count > 0):
            cands.append((-int(count[f]), float(rng.random()), SourceFrame(clip, int(f))))
    cands.sort(key=lambda c: (c[0], c[1]))
    return sorted((c[2] for c in cands[:n_sources]), key=lambda s: (s.clip, s.frame))


def instruction_for_target(scope: str, target_name: str) -> str:
    """The instruction for a toolkit item that carries only ``target_name`` (roster lookup
    by display name or id); empty when the target is not in the roster."""
    from handedit.embodiments import list_embodiments

    key = target_name.strip().lower()
    for e in list_embodiments():
        if key in (e.id.lower(), e.name.lower()):
            return instruction(scope, e.name, e.description)
    return ""
