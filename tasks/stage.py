"""A stage, declared once: its name, level, config class, what it reads, and its body.

Each ``tasks/<stage>.py`` ends with one ``STAGE = Stage(...)``; ``tasks.STAGES`` lists them
in pipeline order, and that list is all the walker (``tasks.clip``) knows of stages.
``reads(at)`` names every input of one chunk:

- ``Arrays``: arrays of one chunk of a unit in the store (their digests, from the records);
- ``Value``: anything else the body uses, by content: the clip's facts, the source's
  fingerprint, a content digest of the robot's URDF and meshes or of a model file;
- ``Attr``: operator data kept on a unit in the store (review decisions), read fresh by
  the walker.

The walker hashes exactly these into the chunk's provenance key (with the stage's
parameters and the VERSION of its config and of every config nested in it) and hands the
body an ``Inputs`` that serves exactly these: reading an array that was not declared
raises ``UndeclaredRead``, so a key cannot miss an input. Adding a stage is one tasks
module, its domain code, and one line in ``tasks.STAGES``.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Literal

import numpy as np
from pydantic import BaseModel

from handedit.storage import Unit, chunk_ranges, read_chunk
from handedit.storage.layout import ArraySpec
from handedit.storage.store import dumps
from handedit.tasks.plan import ClipPlan

if TYPE_CHECKING:
    from handedit.tasks.common import ChunkJob, StageOutput


@dataclass(frozen=True)
class Arrays:
    """Named arrays of one chunk of a unit."""

    unit: Unit
    chunk: int
    arrays: tuple[str, ...]


@dataclass(frozen=True)
class Value:
    """A value the body uses (JSON-safe; a string is taken as a digest as is)."""

    name: str
    value: Any


@dataclass(frozen=True)
class Attr:
    """An attribute of a unit in the store (operator data), read when the chunk is keyed."""

    unit: Unit
    name: str


Input = Arrays | Value | Attr


@dataclass(frozen=True)
class Robot:
    """The embodiment an embodiment-level unit renders: its track and the content of its
    URDF and every mesh it references (``robot_digest``)."""

    id: str
    track: str  # "hand" or "hand_arm"
    digest: str = ""


@dataclass(frozen=True)
class At:
    """Where a chunk sits: what ``reads`` is given."""

    plan: ClipPlan
    unit: Unit
    chunk: int
    start: int
    stop: int
    ranges: tuple[tuple[int, int], ...]  # every chunk of the clip
    config: BaseModel  # the stage's own
    robot: Robot | None = None  # embodiment stages
    whole: Callable[[Unit], bool] = field(default=lambda unit: False, compare=False)  # units with one whole-clip node

    @property
    def track(self) -> str:
        """The mask the unit works with: the restore scope, or the robot's track."""
        return self.unit.scope or (self.robot.track if self.robot else "hand")

    def each(self, unit: Unit, names) -> list[Arrays]:
        """``names`` of every chunk of ``unit`` this chunk's frames span."""
        if self.whole(unit):
            return [Arrays(unit, 0, tuple(names))]
        return [Arrays(unit, k, tuple(names)) for k, (a, b) in enumerate(self.ranges) if a < self.stop and b > self.start]


def _never(plan: ClipPlan, at_track: str) -> bool:
    return False


def _always(plan: ClipPlan) -> bool:
    return True


@dataclass(frozen=True)
class Stage:
    name: str
    level: Literal["clip", "scope", "embodiment"]
    config: type[BaseModel]
    reads: Callable[[At], list]
    body: Callable[["Inputs", "ChunkJob"], "StageOutput"]
    whole_clip: Callable[[ClipPlan, str], bool] = _never  # (plan, track): one node covers every frame
    applies: Callable[[ClipPlan], bool] = _always  # whether the clip has this stage at all
    uses: tuple[type, ...] = ()  # config classes the body derives from its config (their VERSION is keyed too)
    writes: tuple[ArraySpec, ...] = ()  # the unit's arrays; the store places them (``storage.layout``)

    def versions(self, cfg: BaseModel) -> dict[str, int]:
        """VERSION of every config class this stage runs: its own, those nested in it, those it derives."""
        versions = {**config_versions(cfg), **{c.__name__: int(getattr(c, "VERSION", 1)) for c in self.uses}}
        return dict(sorted(versions.items()))


@dataclass
class Node:
    unit: Unit
    chunk: int
    start: int
    stop: int
    inputs: list = field(default_factory=list)  # [Input]
    robot: Robot | None = None
    spans: dict = field(default_factory=dict)  # (unit, chunk) of each Arrays input -> its frames [a, b)

    @property
    def id(self) -> tuple[Unit, int]:
        return (self.unit, self.chunk)

    @property
    def deps(self) -> list[Arrays]:
        return [i for i in self.inputs if isinstance(i, Arrays)]


def nodes(stages, plan: ClipPlan, units: list[Unit], configs: dict[str, BaseModel], frames_per_chunk: int,
          robot: Robot | None = None) -> list[Node]:
    """Every chunk node of ``units`` (each unit's stage from ``stages``), with its declared
    inputs; every node also declares the clip's facts, its config's nested VERSIONs and the
    content of the model files its config names."""
    from handedit.digests import model_digests

    by_name = {s.name: s for s in stages}
    ranges = tuple(chunk_ranges(plan.n_frames, frames_per_chunk))

    def whole(unit: Unit) -> bool:
        track = unit.scope or (robot.track if unit.embodiment and robot else "hand")
        return by_name[unit.stage].whole_clip(plan, track)

    out = []
    for unit in units:
        stage, cfg = by_name[unit.stage], configs[unit.stage]
        common = [Value("clip", plan.facts()), Value("versions", stage.versions(cfg)),
                  *(Value(f"model:{k}", d) for k, d in sorted(model_digests(cfg).items()))]
        for k, (s, e) in ([(0, (0, plan.n_frames))] if whole(unit) else list(enumerate(ranges))):
            inputs = [*common, *stage.reads(At(plan, unit, k, s, e, ranges, cfg, robot, whole))]
            spans = {(i.unit, i.chunk): ((0, plan.n_frames) if whole(i.unit) else ranges[i.chunk])
                     for i in inputs if isinstance(i, Arrays)}
            out.append(Node(unit, k, s, e, inputs, robot, spans))
    return out


def _digest(value: Any) -> str:
    return value if isinstance(value, str) else hashlib.blake2b(dumps(value).encode(), digest_size=16).hexdigest()


def key_inputs(node: Node, records: dict, attrs: Callable[[Unit, str], Any]) -> dict[str, str]:
    """The fingerprints of a node's declared inputs: array digests from their chunks'
    records ("absent" where a record is missing), values by content, attributes as read now."""
    out: dict[str, str] = {}
    for i in node.inputs:
        if isinstance(i, Arrays):
            outputs = (records.get((i.unit, i.chunk)) or {}).get("outputs", {})
            for name in i.arrays:
                out[f"{i.unit.path}#{i.chunk}/{name}"] = outputs.get(name, "absent")
        elif isinstance(i, Value):
            out[i.name] = _digest(i.value)
        else:
            out[f"{i.unit.path}@{i.name}"] = _digest(attrs(i.unit, i.name))
    return out


def config_versions(config: BaseModel) -> dict[str, int]:
    """VERSION of a config class and of every config nested in it, by class name: bumping
    any of them changes the key of the stage that runs it."""
    out: dict[str, int] = {}

    def visit(cfg: BaseModel) -> None:
        out[type(cfg).__name__] = int(getattr(type(cfg), "VERSION", 1))
        for name in type(cfg).model_fields:
            v = getattr(cfg, name)
            for item in (v if isinstance(v, (list, tuple)) else [v]):
                if isinstance(item, BaseModel):
                    visit(item)

    visit(config)
    return dict(sorted(out.items()))


class UndeclaredRead(RuntimeError):
    """A stage body read something its ``reads`` did not declare (a bug in the stage module)."""


class Inputs:
    """What a body may read: exactly its node's declared inputs."""

    def __init__(self, root, node: Node, ranges: tuple[tuple[int, int], ...], attrs: Callable[[Unit, str], Any]):
        self._root, self._node, self.ranges = root, node, ranges  # ranges: every chunk of the clip
        self._arrays: dict[tuple[Unit, int], set[str]] = {}
        self._values: dict[str, Any] = {}
        self._attrs: dict[tuple[Unit, str], Any] = {}
        for i in node.inputs:
            if isinstance(i, Arrays):
                self._arrays.setdefault((i.unit, i.chunk), set()).update(i.arrays)
            elif isinstance(i, Value):
                self._values[i.name] = i.value
            else:
                self._attrs[(i.unit, i.name)] = attrs(i.unit, i.name)

    def read(self, unit: Unit, names, start: int | None = None, stop: int | None = None) -> dict[str, np.ndarray]:
        """Frames [start, stop) (default: the node's) of declared arrays of ``unit``."""
        start = self._node.start if start is None else start
        stop = self._node.stop if stop is None else stop
        names = list(names)
        covered = np.zeros(max(stop - start, 0), bool)
        for (u, k), declared in self._arrays.items():
            if u == unit and set(names) <= declared:
                a, b = self._node.spans[(u, k)]
                covered[max(a - start, 0):max(b - start, 0)] = True
        if not covered.all():
            raise UndeclaredRead(f"{self._node.unit.label}: reads {names} of {unit.label} frames {start}:{stop} "
                                 f"without declaring them in its stage's reads()")
        return read_chunk(self._root, unit, names, start, stop)

    def value(self, name: str) -> Any:
        if name not in self._values:
            raise UndeclaredRead(f"{self._node.unit.label}: uses {name!r} without declaring it in its stage's reads()")
        return self._values[name]

    def attr(self, unit: Unit, name: str) -> Any:
        if (unit, name) not in self._attrs:
            raise UndeclaredRead(f"{self._node.unit.label}: reads attribute {name!r} of {unit.label} without declaring it")
        return self._attrs[(unit, name)]

    def write_previews(self, *args, **kwargs):
        """Side outputs of the node's own unit (the hand-arm search's candidate previews)."""
        from handedit.storage.store import write_previews

        return write_previews(self._root, self._node.unit, *args, **kwargs)
