"""A clip's plan: what the walk knows about a clip before reading a frame (typed; it
replaces the string-keyed context the stage bodies used to receive).

The clip task makes it from the source's metadata (``clip_plan``) and stores it on the
ingest unit, where each embodiment task reads it back (``stored_plan``). Its ``facts`` are
declared by every stage (``tasks.stage``), so they are in every chunk's provenance key;
the source's content enters through ingest alone (``fingerprint``), and the source spec's
paths not at all: a moved dataset is the same data.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field

from handedit.storage import Unit
from handedit.storage.store import jsonable


@dataclass(frozen=True)
class ClipPlan:
    clip: str
    n_frames: int
    height: int
    width: int
    intrinsics: dict
    source_json: str
    fingerprint: str
    has_object: bool
    has_gt: bool
    info: dict = field(default_factory=dict, compare=False)  # the source's ClipInfo, JSON-safe
    hands: tuple[str, ...] = ("right",)
    has_arm: bool = False
    has_keypoints: bool = True
    world: dict | None = field(default=None, compare=False)
    keypoints_exact: bool = False
    estimate_hands: bool = False  # the keypoints come from the estimate_hands stage, not the source

    @property
    def fps(self) -> float:
        return float(self.info.get("fps", 30.0))

    @property
    def source_hands(self) -> tuple[str, ...]:
        """The hands as the source orders them (ingest maps them onto ``hands``)."""
        return tuple(self.info.get("hands", self.hands))

    @property
    def intrinsics_origin(self) -> str:
        return (self.info.get("meta") or {}).get("intrinsics_origin", "source")

    def facts(self) -> dict:
        """What the stage bodies use of the plan, as it enters their keys."""
        return jsonable({"n_frames": self.n_frames, "height": self.height, "width": self.width,
                         "intrinsics": self.intrinsics, "has_object": self.has_object, "has_gt": self.has_gt,
                         "hands": list(self.hands), "source_hands": list(self.source_hands), "has_arm": self.has_arm,
                         "has_keypoints": self.has_keypoints, "world": self.world, "keypoints_exact": self.keypoints_exact,
                         "estimate_hands": self.estimate_hands, "fps": self.fps,
                         "intrinsics_origin": self.intrinsics_origin})


def clip_plan(spec, estimate: str = "auto") -> ClipPlan:
    """A clip's plan from its source (opens it: metadata only); raises SourceError.
    ``estimate`` (EstimateHandsConfig.mode): whether its hands are estimated from the
    pixels; such a clip tracks both sides, whatever the source says."""
    from handedit.keypoints import SIDES
    from handedit.sources import open_source

    info = open_source(spec).info()
    estimated = estimate == "always" or (estimate == "auto" and not info.has_keypoints)
    return ClipPlan(
        clip=info.clip_id, n_frames=info.n_frames, height=info.height, width=info.width,
        intrinsics=info.intrinsics.to_dict(), source_json=json.dumps(spec.model_dump(mode="json"), sort_keys=True,
                                                                     separators=(",", ":")),
        fingerprint=info.fingerprint, has_object=info.has_object, has_gt=bool(info.ground_truth),
        info=jsonable({**vars(info), "intrinsics": info.intrinsics.to_dict()}),  # the source's own (its hands too)
        hands=SIDES if estimated else tuple(info.hands), has_arm=info.has_arm and not estimated,
        has_keypoints=info.has_keypoints or estimated, world=info.world,
        keypoints_exact=info.keypoints_exact or estimated,  # estimated joints are read off the pixels
        estimate_hands=estimated,
    )


def plan_json(plan: ClipPlan) -> dict:
    return jsonable(asdict(plan))


def stored_plan(root, clip: str) -> ClipPlan | None:
    """The clip's plan as its clip task stored it (None when the clip was never ingested)."""
    unit = Unit("ingest", clip)
    if unit.path not in root or "plan" not in root[unit.path].attrs:
        return None
    d = dict(root[unit.path].attrs["plan"])
    d["hands"] = tuple(d["hands"])
    return ClipPlan(**d)
