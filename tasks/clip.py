"""The card's task granularity: one Prefect task per clip, one per clip x embodiment.

``curate_clip`` runs a clip's per-clip stages (ingest, estimate_hands where the hands
come from the pixels, registration, segment,
restore_background per scope) and ``curate_embodiment`` one embodiment's stages (retarget,
render, composite, harmonize, qc) of one clip. Each walks its chunks itself, in dependency
order and streaming (chunk k is ingested, registered and segmented before chunk k-1 is
restored, so a clip is never held in memory), through the same chunk bodies as before
(``handedit.tasks.<stage>.body``), keeping per-chunk provenance, skip-if-current and
rejection records. So a clip costs 1 + E Prefect task runs, whatever its length.

Each task is the only writer of its units (their arrays and attributes): it creates them,
writes their chunks and, right after each chunk, that chunk's provenance record (the
commit marker: a chunk whose record is missing or does not match is recomputed). The
chunk DAG (``handedit.flows.dag``) says what each chunk reads; records of units another
task owns (the clip's, for an embodiment task) are read from the store.

Retries: a transient error (I/O, connection, memory) of a chunk is retried here, twice,
after 1 and 5 s; any other error rejects that chunk's frames with ``STAGE_ERROR`` and the
message, its dependents mark them ``UPSTREAM``, and the walk goes on. Prefect retries a
task that died (a lost worker): its finished chunks are then skipped.
"""

from __future__ import annotations

import fnmatch
import heapq
import json
import time
from collections import Counter
from dataclasses import dataclass, field

from prefect import task

from handedit.reasons import Reason
from handedit.storage import Unit, create_unit, read_records, write_records
from handedit.storage.integrity import missing_objects, stored_objects
from handedit.storage.handoff import Handoff, handing_over
from handedit.storage.layout import STAGES
from handedit.storage.location import location_of
from handedit.storage.provenance import ChunkRecord, drop_records, is_current, provenance_key
from handedit.storage.store import CorruptChunk, create_previews, jsonable
from handedit.tasks.common import RETRIES, RETRY_DELAYS, ChunkJob, execute, failure_record, is_transient, open_root

CLIP_STAGES = ("ingest", "estimate_hands", "registration", "segment", "restore_background")
EMBODIMENT_STAGES = ("retarget", "render", "composite", "harmonize", "qc")


@dataclass(frozen=True)
class ClipJob:
    """Small and picklable: the store's URL, the clip's spec, the run's configuration."""

    store: str
    spec_json: str
    config_json: str  # CurateConfig
    scopes: tuple[str, ...]  # restore scopes the run's embodiments need
    code_version: str


@dataclass(frozen=True)
class EmbodimentJob:
    store: str
    clip: str
    embodiment: dict  # flows.curate.EmbodimentPlan as a dict
    config_json: str
    code_version: str


@dataclass
class WalkResult:
    clip: str
    stages: dict = field(default_factory=dict)  # stage -> {ran, skipped, failed}
    errors: list = field(default_factory=list)
    recovered: list = field(default_factory=list)  # chunks recomputed because their data was gone or corrupt
    source_error: str | None = None
    seconds: float = 0.0

    def count(self, stage: str, what: str) -> None:
        self.stages.setdefault(stage, {"ran": 0, "skipped": 0, "failed": 0})[what] += 1


def _config(job):
    from handedit.flows.config import CurateConfig

    return CurateConfig.model_validate_json(job.config_json)


def stage_version_params(config, stage: str) -> tuple[int, dict]:
    """A stage's code version (its config class's VERSION) and parameters."""
    cfg = config.stage_config(stage)
    return int(getattr(type(cfg), "VERSION", 1)), cfg.model_dump(mode="json")


def _order(nodes) -> list:
    """Dependency order, earliest chunk first (streaming; see module doc)."""
    by_id = {n.id: n for n in nodes}
    waiting = {n.id: len({(d.unit, d.chunk) for d in n.deps if (d.unit, d.chunk) in by_id}) for n in nodes}
    children: dict = {}
    for n in nodes:
        for d in n.deps:
            if (d.unit, d.chunk) in by_id:
                children.setdefault((d.unit, d.chunk), set()).add(n.id)
    rank = {s: i for i, s in enumerate(STAGES)}
    heap = [((n.chunk, rank[n.unit.stage], n.unit), n.id) for n in nodes if waiting[n.id] == 0]
    heapq.heapify(heap)
    out = []
    while heap:
        _, nid = heapq.heappop(heap)
        out.append(by_id[nid])
        for c in sorted(children.get(nid, ())):
            waiting[c] -= 1
            if waiting[c] == 0:
                n = by_id[c]
                heapq.heappush(heap, ((n.chunk, rank[n.unit.stage], n.unit), c))
    return out


def _faulty(config, unit: Unit) -> bool:
    names = [f"{unit.stage}:{unit.clip}", f"{unit.stage}:{unit.clip}:{unit.embodiment or unit.scope or ''}"]
    return any(fnmatch.fnmatchcase(n, pat) for pat in config.inject_faults for n in names)


def walk(nodes, stage_params, records: dict, run_node, on_record, result: WalkResult, faulty=lambda unit: False,
         prefail=None, missing=None, finished=lambda node: None) -> WalkResult:
    """Run chunk nodes in streaming dependency order, skipping current ones (pure: no store).

    ``stage_params(stage) -> (version, params)``; ``records``: (unit, chunk) -> record of
    every chunk already stored (this task's units and the units it reads), updated as it
    goes; ``run_node(node, key, inputs, version, params, fault) -> record`` runs one chunk
    (a record with ``outcome="error"`` counts as failed); ``prefail(node, ...)`` may return
    a failure record instead of running it; ``on_record(node, record)`` persists a new record;
    ``missing(node, record) -> [object keys]`` names stored outputs a current record vouches
    for that are gone: such a chunk is recomputed, and noted in ``result.recovered``;
    ``finished(node)`` follows every node, run or skipped.
    """
    from handedit.flows.dag import node_inputs

    for node in _order(nodes):
        version, p = stage_params(node.unit.stage)
        inputs = node_inputs(node, records)
        key = provenance_key(node.unit.stage, version, p, inputs)
        note = None
        if is_current(records.get(node.id), key):
            gone = missing(node, records[node.id]) if missing is not None else []
            if not gone:
                result.count(node.unit.stage, "skipped")
                finished(node)
                continue
            note = f"{node.unit.label}#{node.chunk}: recomputed, its stored data was missing ({', '.join(gone[:3])})"
            result.recovered.append(note)
        record = prefail(node, key, inputs, version, p) if prefail is not None else None
        if record is None:
            record = run_node(node, key, inputs, version, p, faulty(node.unit))
            if record.get("outcome") == "error":  # to retry next run (prefailed chunks are the plan's own)
                result.errors.append(f"{node.unit.label}#{node.chunk}: {record.get('error')}")
        if note:
            record.setdefault("extra", {})["recovered"] = note
        result.count(node.unit.stage, "failed" if record.get("outcome") == "error" else "ran")
        on_record(node, record)
        records[node.id] = record
        finished(node)
    return result


def _walk_store(root, store: str, nodes, config, code_version: str, result: WalkResult, prefail=None) -> WalkResult:
    """``walk`` on the store: stage bodies run through ``execute``, records go to the units."""
    from handedit.tasks import STAGE_BODIES

    records: dict = {}
    for unit in {n.unit for n in nodes} | {d.unit for n in nodes for d in n.deps}:
        for k, rec in read_records(root, unit).items():
            records[(unit, k)] = rec.to_json()
    params = {s: stage_version_params(config, s) for s in {n.unit.stage for n in nodes}}

    def job_of(node, key, inputs, version, p, fault=False) -> ChunkJob:
        return ChunkJob(store, node.unit, node.chunk, node.start, node.stop, key, version, p, inputs, code_version,
                        node.context, fault=fault)

    def run_node(node, key, inputs, version, p, fault) -> dict:
        return _run(root, job_of(node, key, inputs, version, p, fault), STAGE_BODIES[node.unit.stage])

    def pre(node, key, inputs, version, p):
        return None if prefail is None else prefail(root, job_of(node, key, inputs, version, p))

    own = {n.unit for n in nodes}
    present: dict = {}  # unit -> its stored objects: listed once, only when a skip needs it
    corrupt: set = set()  # (unit, chunk) of this task's own units whose stored bytes failed to decode

    def missing(node, record) -> list[str]:
        if node.unit not in present:
            present[node.unit] = stored_objects(location_of(root), node.unit.path)
        return missing_objects(root, node.unit, record, present[node.unit])

    def run_noting(node, key, inputs, version, p, fault) -> dict:
        record = run_node(node, key, inputs, version, p, fault)
        if record.get("corrupt"):
            corrupt.update(_owned_chunk(record["corrupt"], own, config.frames_per_chunk))
        return record

    starts = {n.id: n.start for n in nodes}  # the chunks this walk writes

    def run(into: WalkResult) -> WalkResult:
        kept = _handoff(root, nodes, starts, records, config.handoff_mib, config.reuse_mib)

        def finished(node) -> None:
            if kept is not None:
                kept.done(_own_reads(node, starts))

        with handing_over(kept):
            return walk(nodes, params.__getitem__, records, run_noting,
                        lambda n, r: write_records(root, n.unit, [ChunkRecord.from_json(r)]), into,
                        faulty=lambda u: _faulty(config, u), prefail=pre, missing=missing, finished=finished)

    run(result)
    if corrupt:  # a corrupt chunk this task owns: recompute it, then the chunks that failed reading it
        for unit, chunk in sorted(corrupt):
            records.pop((unit, chunk), None)
            drop_records(root, unit, [chunk])
            result.recovered.append(f"{unit.label}#{chunk}: recomputed, its stored bytes were corrupt")
        present.clear()  # list again: the first pass wrote objects
        again = run(WalkResult(result.clip))
        for stage, c in again.stages.items():  # the second pass replaces those chunks' first outcome
            n, mine = c["ran"] + c["failed"], result.stages[stage]
            took = min(n, mine["failed"])
            mine["failed"] -= took
            mine["skipped"] -= n - took
            mine["ran"] += c["ran"]
            mine["failed"] += c["failed"]
        result.errors = [e for e in result.errors if "CorruptChunk" not in e] + again.errors
        result.recovered += again.recovered
    return result


def _own_reads(node, starts: dict) -> list[tuple[str, int, tuple[str, ...]]]:
    """(unit path, start frame, arrays) of each chunk ``node`` reads that its own walk writes."""
    return [(d.unit.path, starts[(d.unit, d.chunk)], d.arrays) for d in node.deps if (d.unit, d.chunk) in starts]


def _handoff(root, nodes, starts: dict, records: dict, budget_mib: int, reuse_mib: int) -> Handoff | None:
    """The walk's hand-over (``storage.handoff``): which of its chunks its nodes read, and
    which arrays of them; and the digests of the other tasks' chunks they read (from the
    records), by which this worker reuses what it decoded of them."""
    if not (budget_mib or reuse_mib):  # (CurateConfig: both >= 0)
        return None
    readers: Counter = Counter()
    names: dict = {}  # (path, start) -> Counter of the arrays read
    digests: dict = {}
    for n in nodes:
        for d in n.deps:
            if (d.unit, d.chunk) in starts:
                key = (d.unit.path, starts[(d.unit, d.chunk)])
                readers[key] += 1
                names.setdefault(key, Counter()).update(d.arrays)
            elif (rec := records.get((d.unit, d.chunk))) is not None and rec.get("outcome") == "ok":
                digests[(d.unit.path, rec["start"], rec["stop"])] = rec.get("outputs", {})
    return Handoff(root.store, readers, names, budget_mib << 20, digests, reuse_mib << 20)


def _owned_chunk(corrupt: dict, units, f: int) -> list:
    """[(unit, chunk)] a CorruptChunk's array path and frames point to, if one of ``units``."""
    unit_path = corrupt["array"].rsplit("/", 1)[0]
    return [(u, int(corrupt["start"]) // f) for u in units if u.path == unit_path]


def _run(root, job: ChunkJob, body) -> dict:
    """One chunk, with the transient-error retries (see module doc)."""
    for attempt in range(RETRIES + 1):
        try:
            record = execute(job, body)
            record["attempts"] = attempt + 1
            return record
        except Exception as exc:  # noqa: BLE001 - a chunk's failure is recorded, not raised
            if is_transient(exc) and attempt < RETRIES:
                time.sleep(RETRY_DELAYS[attempt])
                continue
            reason = Reason(int(getattr(exc, "reason", Reason.STAGE_ERROR)))
            record = failure_record(job, root, reason, f"{type(exc).__name__}: {exc}", attempt + 1)
            if isinstance(exc, CorruptChunk):
                record["corrupt"] = {"array": exc.array_path, "start": exc.start, "stop": exc.stop}
            return record
    raise AssertionError("unreachable")


# ----------------------------------------------------------------------------- units


def clip_plan(spec, estimate: str = "auto"):
    """A clip's plan from its source (opens it: metadata only); raises SourceError.
    ``estimate`` (EstimateHandsConfig.mode): whether its hands are estimated from the
    pixels; such a clip tracks both sides, whatever the source says."""
    from handedit.flows.dag import ClipPlan
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


def _plan_json(plan) -> dict:
    from dataclasses import asdict

    return jsonable(asdict(plan))


def stored_plan(root, clip: str):
    """The clip's plan as its clip task stored it (None when the clip was never ingested)."""
    from handedit.flows.dag import ClipPlan

    unit = Unit("ingest", clip)
    if unit.path not in root or "plan" not in root[unit.path].attrs:
        return None
    d = dict(root[unit.path].attrs["plan"])
    d["hands"] = tuple(d["hands"])
    return ClipPlan(**d)


def create_clip_units(root, config, plan, scopes) -> None:
    f, sizes = config.frames_per_chunk, {"H": plan.height, "W": plan.width, "S": len(plan.hands)}
    hands = {"hands": list(plan.hands)}
    create_unit(root, Unit("ingest", plan.clip), plan.n_frames, sizes, f, plan.has_object, plan.has_gt,
                attrs={"info": plan.info, "plan": _plan_json(plan), **hands}, has_arm=plan.has_arm)
    if plan.estimate_hands:
        create_unit(root, Unit("estimate_hands", plan.clip), plan.n_frames, sizes, f, attrs=hands)
    create_unit(root, Unit("registration", plan.clip), plan.n_frames, sizes, f, attrs=hands, has_arm=plan.has_arm)
    create_unit(root, Unit("segment", plan.clip), plan.n_frames, sizes, f, attrs=hands)
    for scope in sorted(scopes):
        create_unit(root, Unit("restore_background", plan.clip, scope=scope), plan.n_frames, sizes, f)


def create_embodiment_units(root, config, plan, emb: dict) -> None:
    f = config.frames_per_chunk
    sizes = {"H": plan.height, "W": plan.width, "S": len(plan.hands), "dof": len(emb["joint_names"])}
    hands = {"hands": list(plan.hands)}
    for stage in EMBODIMENT_STAGES:
        extra = {**hands, "stage": stage, **({"joint_names": emb["joint_names"]} if stage == "retarget" else {})}
        create_unit(root, Unit(stage, plan.clip, embodiment=emb["id"]), plan.n_frames, sizes, f, attrs=extra)
    if emb["scope"] == "hand_arm":
        for side in plan.hands:
            create_previews(root, Unit("retarget", plan.clip, embodiment=emb["id"]), plan.height, plan.width, side)


def _asset_inputs(config, nodes, emb: dict | None = None) -> None:
    """Files a stage reads besides the store are inputs too, by content: a stage's model
    weights, and the robot's URDF for the stages that load it."""
    from handedit.digests import model_digests

    for node in nodes:
        node.fixed_inputs.update(model_digests(config.stage_config(node.unit.stage)))
        if emb is not None and node.unit.stage in ("retarget", "render"):
            node.fixed_inputs["urdf"] = emb.get("urdf_digest", "")


# ----------------------------------------------------------------------------- tasks


def run_clip(job: ClipJob) -> dict:
    """The body of ``curate_clip`` (also what a bare loop calls)."""
    from handedit.flows.dag import clip_nodes
    from handedit.sources import SourceError, parse_spec
    from handedit.storage import set_attrs

    t0 = time.perf_counter()
    config = _config(job)
    spec = parse_spec(json.loads(job.spec_json))
    result = WalkResult(spec.id)
    try:
        plan = clip_plan(spec, config.estimate_hands.mode)
    except SourceError as exc:
        result.source_error = str(exc)
        return vars(result)
    root = open_root(job.store)
    create_clip_units(root, config, plan, job.scopes)
    for stage in CLIP_STAGES:
        if stage == "estimate_hands" and not plan.estimate_hands:
            continue
        for scope in (job.scopes if stage == "restore_background" else (None,)):
            unit = Unit(stage, plan.clip, scope=scope)
            v, p = stage_version_params(config, stage)
            set_attrs(root, unit.path, {"stage": stage, "version": v, "params": p})
    nodes = clip_nodes(plan, job.scopes, config.frames_per_chunk, config.restore_background.window)
    _asset_inputs(config, nodes)
    _walk_store(root, job.store, nodes, config, job.code_version, result)
    result.seconds = time.perf_counter() - t0
    return vars(result)


def run_embodiment(job: EmbodimentJob) -> dict:
    """The body of ``curate_embodiment``."""
    from handedit.flows.dag import embodiment_nodes
    from handedit.storage import set_attrs

    t0 = time.perf_counter()
    config = _config(job)
    result = WalkResult(job.clip)
    root = open_root(job.store)
    plan = stored_plan(root, job.clip)
    emb = job.embodiment
    if plan is None:
        result.source_error = "the clip could not be ingested (see its clip-level rejection)"
        return vars(result)
    create_embodiment_units(root, config, plan, emb)
    for stage in EMBODIMENT_STAGES:
        v, p = stage_version_params(config, stage)
        set_attrs(root, Unit(stage, plan.clip, embodiment=emb["id"]).path, {"version": v, "params": p})
    nodes = embodiment_nodes(plan, emb["id"], emb["scope"], config.frames_per_chunk)
    _asset_inputs(config, nodes, emb)

    def prefail(root_, cj: ChunkJob) -> dict | None:
        if not emb.get("error") or cj.unit.stage != "retarget":
            return None
        return failure_record(cj, root_, Reason(int(emb["reason"])), emb["error"], 0)

    _walk_store(root, job.store, nodes, config, job.code_version, result, prefail=prefail)
    result.seconds = time.perf_counter() - t0
    return vars(result)


_OPTIONS = {"retries": 1, "retry_delay_seconds": [5.0], "persist_result": False}


def _no_cache():
    from prefect.cache_policies import NO_CACHE

    return NO_CACHE


@task(name="curate-clip", task_run_name="clip[{clip_id}]", cache_policy=_no_cache(), **_OPTIONS)
def curate_clip(job: ClipJob, clip_id: str = "") -> dict:
    return run_clip(job)


@task(name="curate-embodiment", task_run_name="embodiment[{job.clip}|{emb_id}]", cache_policy=_no_cache(), **_OPTIONS)
def curate_embodiment(job: EmbodimentJob, emb_id: str = "") -> dict:
    return run_embodiment(job)
