"""The curate DAG at chunk granularity: which chunk of which stage reads what.

The nodes of one clip's per-clip stages (``clip_nodes``) and of one clip x embodiment
(``embodiment_nodes``) are what the two Prefect tasks of ``handedit.tasks.clip`` walk;
the driver never builds nodes.

Stages: ingest -> [estimate_hands] -> registration -> segment -> restore_background (per scope) and, per
embodiment, retarget -> render -> composite -> harmonize -> qc. Every per-hand stage
handles all of a clip's hands in one node (its arrays have a hand axis). A node is one (unit, chunk); its
dependencies name the exact arrays it reads, so its provenance key fingerprints exactly
its inputs. restore_background reads a window of neighbouring chunks.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from handedit.storage.layout import PER_HAND_STAGES, SCOPE_MASK, Unit, chunk_ranges
from handedit.storage.store import dumps

NodeId = tuple[Unit, int]


@dataclass
class Dep:
    unit: Unit
    chunk: int
    arrays: tuple[str, ...]


@dataclass
class Node:
    unit: Unit
    chunk: int
    start: int
    stop: int
    deps: list[Dep] = field(default_factory=list)
    context: dict = field(default_factory=dict)
    fixed_inputs: dict[str, str] = field(default_factory=dict)  # inputs that are not store arrays

    @property
    def id(self) -> NodeId:
        return (self.unit, self.chunk)


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


def node_inputs(node: Node, records: dict[NodeId, dict]) -> dict[str, str]:
    """The input fingerprints of a node: its fixed inputs and the digests of the arrays it
    reads, from its dependencies' records ("absent" where a record is missing)."""
    inputs = dict(node.fixed_inputs)
    for dep in node.deps:
        outputs = (records.get((dep.unit, dep.chunk)) or {}).get("outputs", {})
        for name in dep.arrays:
            inputs[f"{dep.unit.path}#{dep.chunk}/{name}"] = outputs.get(name, "absent")
    return inputs


def _ctx(clip: ClipPlan) -> tuple[dict, dict]:
    base = {"intrinsics": clip.intrinsics, "has_object": clip.has_object, "hands": list(clip.hands),
            "has_arm": clip.has_arm, "has_keypoints": clip.has_keypoints, "keypoints_exact": clip.keypoints_exact,
            "estimated": clip.estimate_hands}
    return base, {"intrinsics": dumps(clip.intrinsics)}


def clip_nodes(clip: ClipPlan, scopes, frames_per_chunk: int, restore_window: int) -> list[Node]:
    """The per-clip stages' nodes: ingest, registration, segment, restore_background per scope."""
    c = clip.clip
    ranges = chunk_ranges(clip.n_frames, frames_per_chunk)
    base_ctx, camera = _ctx(clip)
    ingest, registration, segment = Unit("ingest", c), Unit("registration", c), Unit("segment", c)
    arm = ("arm_keypoints", "arm_valid") if clip.has_arm else ()
    reg_out = ("keypoints", "keypoints_valid", "hand_status", "status")
    nodes: list[Node] = []
    estimate = Unit("estimate_hands", c)
    if clip.estimate_hands:  # one node for the clip: tracking and sides run over the whole sequence
        deps = [Dep(ingest, k, ("frames", "status")) for k in range(len(ranges))]
        ctx = {**base_ctx, "fps": clip.info.get("fps", 30.0),
               "intrinsics_origin": (clip.info.get("meta") or {}).get("intrinsics_origin", "source")}
        nodes.append(Node(estimate, 0, 0, clip.n_frames, deps, ctx, camera))
    for k, (s, e) in enumerate(ranges):
        ingest_ctx = {"source": clip.source_json, "has_object": clip.has_object, "has_gt": clip.has_gt, "has_arm": clip.has_arm,
                      "hands": list(clip.hands), "source_hands": list(clip.info.get("hands", clip.hands))}
        nodes.append(Node(ingest, k, s, e, [], ingest_ctx, {"source": clip.fingerprint}))
        if clip.estimate_hands:
            reg_deps = [Dep(ingest, k, ("frames", "status")),
                        Dep(estimate, 0, ("keypoints", "keypoints_valid", "hand_status", "status"))]
        else:
            reg_deps = [Dep(ingest, k, ("frames", "keypoints", "keypoints_valid", "status", *arm))]
        nodes.append(Node(registration, k, s, e, reg_deps, base_ctx, camera))
        seg_deps = [Dep(ingest, k, ("frames", "status", *arm[1:])), Dep(registration, k, (*reg_out, *arm[:1]))]
        nodes.append(Node(segment, k, s, e, seg_deps, base_ctx, camera))
    for scope in sorted(set(scopes)):
        restore = Unit("restore_background", c, scope=scope)
        for k, (s, e) in enumerate(ranges):
            lo, hi = max(0, s - restore_window), min(clip.n_frames, e + restore_window)
            window = [j for j, (a, b) in enumerate(ranges) if a < hi and b > lo]
            deps = [Dep(ingest, j, ("frames",)) for j in window]
            masks = tuple(dict.fromkeys((SCOPE_MASK[scope], SCOPE_MASK["hand"])))  # + the alignment features' (hand) masks
            deps += [Dep(segment, j, (*masks, "status")) for j in window]
            nodes.append(Node(restore, k, s, e, deps, {"window": [lo, hi]}))
    return nodes


def embodiment_nodes(clip: ClipPlan, emb: str, scope: str, frames_per_chunk: int) -> list[Node]:
    """One embodiment's nodes on one clip: retarget, render, composite, harmonize, qc."""
    c = clip.clip
    ranges = chunk_ranges(clip.n_frames, frames_per_chunk)
    base_ctx, camera = _ctx(clip)
    ingest, registration, segment = Unit("ingest", c), Unit("registration", c), Unit("segment", c)
    restore = Unit("restore_background", c, scope=scope)
    ret, ren, comp, harm, qc = (Unit(st, c, embodiment=emb) for st in ("retarget", "render", "composite", "harmonize", "qc"))
    seq = scope == "hand_arm"  # the virtual base is fixed per sequence: one retarget node per clip
    nodes: list[Node] = []
    if seq:
        nodes.append(Node(ret, 0, 0, clip.n_frames, *_hand_arm_retarget(ingest, registration, segment, ranges, base_ctx, clip)))
    for k, (s, e) in enumerate(ranges):
        rk = 0 if seq else k  # the retarget node a chunk reads
        comp_deps = [Dep(restore, k, ("background", "hole", "status")),
                     Dep(ren, k, ("rgba", "depth", "robot_side", "hand_status", "status")),
                     Dep(segment, k, (SCOPE_MASK[scope], "hand_status")), Dep(ingest, k, ("frames",)),
                     Dep(registration, k, ("keypoints", "keypoints_valid"))]
        comp_ctx = {**base_ctx, "scope": scope}
        if seq and clip.has_arm:  # the tracked arm widens the corridor the off-arm check allows
            comp_deps += [Dep(registration, k, ("arm_keypoints",)), Dep(ingest, k, ("arm_valid",))]
        if clip.has_object:  # the object's mask and depth (occlusion)
            comp_deps.append(Dep(ingest, k, ("object_mask", "object_depth")))
        upstream = [(ingest, k), (registration, k), (segment, k), (restore, k), (ret, rk), (ren, k), (comp, k), (harm, k)]
        if not seq:
            nodes.append(Node(ret, k, s, e, *_hand_retarget(ingest, registration, segment, k, base_ctx, clip)))
        nodes += [
            Node(ren, k, s, e, [Dep(ret, rk, ("qpos", "root_pose", "hand_status", "status"))], base_ctx, camera),
            Node(comp, k, s, e, comp_deps, comp_ctx),
            Node(harm, k, s, e, [Dep(comp, k, ("image", "robot_mask", "status"))], base_ctx),
            Node(qc, k, s, e, [Dep(u, j, ("status", *(("hand_status",) if u.stage in PER_HAND_STAGES else ())))
                               for u, j in upstream],
                 {"hands": list(clip.hands),
                  "upstream": [{"stage": u.stage, "clip": u.clip, "scope": u.scope, "embodiment": u.embodiment}
                               for u, _ in upstream]}),
        ]
    return nodes


def build_nodes(clip: ClipPlan, embodiments: dict[str, str], frames_per_chunk: int, restore_window: int) -> list[Node]:
    """All nodes for one clip; ``embodiments`` maps embodiment id -> scope (its track)."""
    nodes = clip_nodes(clip, embodiments.values(), frames_per_chunk, restore_window)
    for emb, scope in embodiments.items():
        nodes += embodiment_nodes(clip, emb, scope, frames_per_chunk)
    return nodes


_REG = ("keypoints", "keypoints_valid", "hand_status", "status")


def _hand_retarget(ingest: Unit, registration: Unit, segment: Unit, k: int, ctx: dict, clip: ClipPlan) -> tuple[list[Dep], dict]:
    """Hand-only: one node per chunk on the chunk's registered keypoints; with an object,
    its pose (and the source, for its mesh) feed the contact/penetration QC."""
    obj = ("object_pose",) if clip.has_object else ()
    ctx = {**ctx, "source": clip.source_json} if clip.has_object else ctx
    deps = [Dep(ingest, k, ("status", *obj)), Dep(registration, k, _REG), Dep(segment, k, ("hand_status",))]
    return deps, ctx


def _hand_arm_retarget(ingest: Unit, registration: Unit, segment: Unit, ranges: list[tuple[int, int]], ctx: dict,
                       clip: ClipPlan) -> tuple[list[Dep], dict]:
    """Hand-arm: one node for the whole clip. The virtual-base search scores every
    candidate over the sequence, so it runs once and writes all of the unit's frames (the
    unit's only writer); render chunks then read their frames of it."""
    obj = ("object_pose",) if clip.has_object else ()
    arm = ("arm_valid",) if clip.has_arm else ()
    ctx = {**ctx, "source": clip.source_json} if clip.has_object else ctx
    deps = []
    for j in range(len(ranges)):
        deps += [Dep(ingest, j, ("world_from_camera", "status", *obj, *arm)),
                 Dep(registration, j, (*_REG, *(("arm_keypoints",) if clip.has_arm else ()))), Dep(segment, j, ("hand_status",))]
    return deps, {**ctx, "track": "hand_arm", "clip_frames": [0, ranges[-1][1]], "world": clip.world}
