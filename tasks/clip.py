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
commit marker: a chunk whose record is missing or does not match is recomputed). Each
stage's declaration (``tasks.stage``, ``tasks.STAGES``) says what each chunk reads; records
of units another task owns (the clip's, for an embodiment task) are read from the store.

Retries: a transient error (I/O, connection, memory) of a chunk is retried here, twice,
after 1 and 5 s; a full (or read-only) device fails the task, naming the file
(``StoreFull``: the run fails, no frame is rejected for it); any other error rejects that
chunk's frames with ``STAGE_ERROR`` and the message, its dependents mark them ``UPSTREAM``,
and the walk goes on. Prefect retries a
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
from pydantic import BaseModel, ConfigDict, Field

from handedit.reasons import Reason
from handedit.storage import Unit, create_unit, open_store, read_records, write_records
from handedit.storage.integrity import missing_objects, stored_objects
from handedit.storage.handoff import Handoff, handing_over
from handedit.storage.location import location_of
from handedit.storage.provenance import ChunkRecord, changed_inputs, drop_records, is_current, provenance_key
from handedit.storage.store import CorruptChunk, create_previews, drop_previews
from handedit.tasks import STAGES
from handedit.storage.store import StoreFull, store_full
from handedit.tasks.common import RETRIES, RETRY_DELAYS, ChunkJob, execute, failure_record, is_transient, open_root
from handedit.tasks.plan import ClipPlan, clip_plan, plan_json, stored_plan
from handedit.tasks.stage import Inputs, Robot, key_inputs, nodes as stage_nodes

STAGE = {s.name: s for s in STAGES}
CLIP_STAGES = tuple(s.name for s in STAGES if s.level != "embodiment")
EMBODIMENT_STAGES = tuple(s.name for s in STAGES if s.level == "embodiment")


@dataclass(frozen=True)
class ClipJob:
    """Small and picklable: the store's URL, the clip's spec, the run's configuration."""

    store: str
    spec_json: str
    config_json: str  # the run's configuration (flows.config.CurateConfig), read as ``WalkConfig``
    scopes: tuple[str, ...]  # restore scopes the run's embodiments need
    code_version: str


@dataclass(frozen=True)
class EmbodimentJob:
    store: str
    clip: str
    embodiment: dict  # flows.curate.EmbodimentPlan as a dict
    config_json: str
    code_version: str


class WalkConfig(BaseModel):
    """What a walk reads of the run's configuration: each stage's parameters (validated by
    the stage's own config class) and the walk's settings."""

    model_config = ConfigDict(extra="ignore")

    frames_per_chunk: int = 16
    robots: list[str] = []  # the run's robot-file folders (``CurateConfig.robots``)
    handoff_mib: int = Field(512, ge=0)
    reuse_mib: int = Field(512, ge=0)
    inject_faults: list[str] = []
    stages: dict[str, BaseModel] = {}

    @classmethod
    def from_json(cls, text: str) -> "WalkConfig":
        data = json.loads(text)
        stages = {s.name: s.config.model_validate(data.get(s.name) or {}) for s in STAGES}
        return cls.model_validate({**data, "stages": stages})

    def stage_config(self, stage: str) -> BaseModel:
        return self.stages[stage]


@dataclass
class WalkResult:
    clip: str
    stages: dict = field(default_factory=dict)  # stage -> {ran, skipped, failed}
    errors: list = field(default_factory=list)
    recovered: list = field(default_factory=list)  # chunks recomputed because their data was gone or corrupt
    recomputed: dict = field(default_factory=dict)  # "stage[embodiment]: what changed" -> chunks
    source_error: str | None = None
    seconds: float = 0.0
    frames: int = 0  # the clip's frames (what the run's progress counts)

    def count(self, stage: str, what: str) -> None:
        self.stages.setdefault(stage, {"ran": 0, "skipped": 0, "failed": 0})[what] += 1

    def recompute(self, unit: Unit, why: str) -> None:
        label = f"{unit.stage}[{unit.embodiment or unit.scope}]" if unit.embodiment or unit.scope else unit.stage
        key = f"{label}: {why}"
        self.recomputed[key] = self.recomputed.get(key, 0) + 1


def _config(job) -> WalkConfig:
    return WalkConfig.from_json(job.config_json)


def stage_version_params(config, stage: str) -> tuple[int, dict]:
    """A stage's code version (its config class's VERSION; nested configs' versions are
    inputs, ``tasks.stage.config_versions``) and parameters."""
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
    rank = {s.name: i for i, s in enumerate(STAGES)}
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
         prefail=None, missing=None, finished=lambda node: None, attrs=lambda unit, name: None) -> WalkResult:
    """Run chunk nodes in streaming dependency order, skipping current ones (pure: no store).

    ``stage_params(stage) -> (version, params)``; ``records``: (unit, chunk) -> record of
    every chunk already stored (this task's units and the units it reads), updated as it
    goes; ``run_node(node, key, inputs, version, params, fault) -> record`` runs one chunk
    (a record with ``outcome="error"`` counts as failed); ``prefail(node, ...)`` may return
    a failure record instead of running it; ``on_record(node, record)`` persists a new record;
    ``missing(node, record) -> [object keys]`` names stored outputs a current record vouches
    for that are gone: such a chunk is recomputed, and noted in ``result.recovered``;
    ``finished(node)`` follows every node, run or skipped; ``attrs(unit, name)`` reads the
    store attributes nodes declare. A chunk recomputed because an input changed is counted
    in ``result.recomputed`` by what changed.
    """
    for node in _order(nodes):
        version, p = stage_params(node.unit.stage)
        inputs = key_inputs(node, records, attrs)
        key = provenance_key(node.unit.stage, version, p, inputs)
        note = None
        old = records.get(node.id)
        if old is not None and old.get("key") != key:
            result.recompute(node.unit, changed_inputs(old, version, p, inputs))
        if is_current(old, key):
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


def _walk_store(root, store: str, plan: ClipPlan, nodes, config: WalkConfig, code_version: str, result: WalkResult,
                prefail=None) -> WalkResult:
    """``walk`` on the store: each node's body gets its declared ``Inputs`` and runs through
    ``execute``; records go to the units."""
    from handedit.storage import chunk_ranges

    records: dict = {}
    for unit in {n.unit for n in nodes} | {d.unit for n in nodes for d in n.deps}:
        for k, rec in read_records(root, unit).items():
            records[(unit, k)] = rec.to_json()
    params = {s: stage_version_params(config, s) for s in {n.unit.stage for n in nodes}}
    ranges = tuple(chunk_ranges(plan.n_frames, config.frames_per_chunk))
    fresh: list = []  # the store opened anew, once: operators' attributes may postdate the worker's cached handle

    def attrs(unit: Unit, name: str):
        if not fresh:
            fresh.append(open_store(store))
        return fresh[0][unit.path].attrs.get(name) if unit.path in fresh[0] else None

    def job_of(node, key, inputs, version, p, fault=False) -> ChunkJob:
        track = node.unit.scope or (node.robot.track if node.robot else None)
        return ChunkJob(store, node.unit, node.chunk, node.start, node.stop, key, version, p, inputs, code_version,
                        plan, track, fault=fault)

    def run_node(node, key, inputs, version, p, fault) -> dict:
        return _run(root, job_of(node, key, inputs, version, p, fault), STAGE[node.unit.stage].body,
                    lambda: Inputs(root, node, ranges, attrs))

    def pre(node, key, inputs, version, p):
        return None if prefail is None else prefail(root, job_of(node, key, inputs, version, p))

    present: dict = {}  # unit -> its stored objects: listed once, only when a skip needs it
    corrupt: set = set()  # (unit, chunk) of this task's own units whose stored bytes failed to decode

    def missing(node, record) -> list[str]:
        if node.unit not in present:
            present[node.unit] = stored_objects(location_of(root), node.unit.path)
        return missing_objects(root, node.unit, record, present[node.unit])

    def run_noting(node, key, inputs, version, p, fault) -> dict:
        record = run_node(node, key, inputs, version, p, fault)
        if record.get("corrupt"):
            corrupt.update(_owned_chunk(record["corrupt"], nodes))
        return record

    starts = {n.id: n.start for n in nodes}  # the chunks this walk writes

    def save(node, record: dict) -> None:
        try:
            write_records(root, node.unit, [ChunkRecord.from_json(record)])
        except OSError as exc:
            raise (store_full(exc, f"the record of {node.unit.path} chunk {node.chunk}") or exc) from None

    def run(into: WalkResult) -> WalkResult:
        kept = _handoff(root, nodes, starts, records, config.handoff_mib, config.reuse_mib)

        def finished(node) -> None:
            if kept is not None:
                kept.done(_own_reads(node, starts))

        with handing_over(kept):
            return walk(nodes, params.__getitem__, records, run_noting, save, into,
                        faulty=lambda u: _faulty(config, u), prefail=pre, missing=missing, finished=finished, attrs=attrs)

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


def _owned_chunk(corrupt: dict, nodes) -> list:
    """[(unit, chunk)] a CorruptChunk's array path and frames point to, if one of the walk's nodes."""
    unit_path, start = corrupt["array"].rsplit("/", 1)[0], int(corrupt["start"])
    return [n.id for n in nodes if n.unit.path == unit_path and n.start <= start < n.stop]


def _run(root, job: ChunkJob, body, inputs) -> dict:
    """One chunk, with the transient-error retries (see module doc); ``inputs()`` makes the
    body's ``Inputs`` (reading operators' attributes: inside the retried block)."""
    for attempt in range(RETRIES + 1):
        try:
            record = execute(job, body, inputs())
            record["attempts"] = attempt + 1
            return record
        except Exception as exc:  # noqa: BLE001 - a chunk's failure is recorded, not raised
            if (full := store_full(exc, f"{job.unit.path} frames {job.start}-{job.stop - 1}")) is not None:
                # the run fails; no frame is rejected for it
                raise full from None
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


def create_clip_units(root, config, plan, scopes) -> None:
    f, sizes = config.frames_per_chunk, {"H": plan.height, "W": plan.width, "S": len(plan.hands)}
    hands = {"hands": list(plan.hands)}
    create_unit(root, Unit("ingest", plan.clip), plan.n_frames, sizes, f, plan.has_object, plan.has_gt,
                attrs={"info": plan.info, "plan": plan_json(plan), **hands}, has_arm=plan.has_arm)
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
        vb = config.stage_config("retarget").virtual_base
        n = min(vb.preview_frames(), plan.n_frames)
        unit = Unit("retarget", plan.clip, embodiment=emb["id"])
        for side in plan.hands:
            if vb.wants_previews():
                create_previews(root, unit, plan.height, plan.width, side, n)
            else:
                drop_previews(root, unit, side)


# ----------------------------------------------------------------------------- tasks


def _units(plan: ClipPlan, scopes=(), embodiment: str | None = None) -> list[Unit]:
    """The units one task walks: the clip's (its restore scopes too), or one embodiment's."""
    if embodiment is not None:
        return [Unit(s, plan.clip, embodiment=embodiment) for s in EMBODIMENT_STAGES]
    out = []
    for st in STAGES:
        if st.level == "clip" and st.applies(plan):
            out.append(Unit(st.name, plan.clip))
        elif st.level == "scope":
            out += [Unit(st.name, plan.clip, scope=scope) for scope in sorted(set(scopes))]
    return out


def _label_units(root, config: WalkConfig, units) -> None:
    from handedit.storage import set_attrs

    for unit in units:
        v, p = stage_version_params(config, unit.stage)
        set_attrs(root, unit.path, {"stage": unit.stage, "version": v, "params": p})


def clip_nodes(plan: ClipPlan, scopes, config: WalkConfig) -> list:
    """The chunk nodes of a clip's own stages."""
    return stage_nodes(STAGES, plan, _units(plan, scopes), config.stages, config.frames_per_chunk)


def embodiment_nodes(plan: ClipPlan, robot: Robot, config: WalkConfig) -> list:
    """The chunk nodes of one embodiment's stages on a clip."""
    return stage_nodes(STAGES, plan, _units(plan, embodiment=robot.id), config.stages, config.frames_per_chunk, robot)


def run_clip(job: ClipJob) -> dict:
    """The body of ``curate_clip`` (also what a bare loop calls)."""
    from handedit.sources import SourceError, parse_spec

    t0 = time.perf_counter()
    config = _config(job)
    spec = parse_spec(json.loads(job.spec_json))
    result = WalkResult(spec.id)
    try:
        plan = clip_plan(spec, config.stages["estimate_hands"].mode)
    except SourceError as exc:
        result.source_error = str(exc)
        return vars(result)
    result.frames = plan.n_frames
    root = open_root(job.store)
    create_clip_units(root, config, plan, job.scopes)
    nodes = clip_nodes(plan, job.scopes, config)
    _label_units(root, config, sorted({n.unit for n in nodes}, key=lambda u: u.path))
    _walk_store(root, job.store, plan, nodes, config, job.code_version, result)
    result.seconds = time.perf_counter() - t0
    return vars(result)


def run_embodiment(job: EmbodimentJob) -> dict:
    """The body of ``curate_embodiment``."""
    from handedit.embodiments.robot_files import robot_dirs_added

    config = _config(job)
    with robot_dirs_added(config.robots):  # this worker may not have started with the run's robot folders
        return _run_embodiment(job, config)


def _run_embodiment(job: EmbodimentJob, config: WalkConfig) -> dict:
    t0 = time.perf_counter()
    result = WalkResult(job.clip)
    root = open_root(job.store)
    plan = stored_plan(root, job.clip)
    emb = job.embodiment
    if plan is None:
        result.source_error = "the clip could not be ingested (see its clip-level rejection)"
        return vars(result)
    result.frames = plan.n_frames
    create_embodiment_units(root, config, plan, emb)
    robot = Robot(emb["id"], emb["scope"], emb.get("robot_digest", ""))
    nodes = embodiment_nodes(plan, robot, config)
    _label_units(root, config, _units(plan, embodiment=robot.id))

    def prefail(root_, cj: ChunkJob) -> dict | None:
        if not emb.get("error") or cj.unit.stage != "retarget":
            return None
        return failure_record(cj, root_, Reason(int(emb["reason"])), emb["error"], 0)

    _walk_store(root, job.store, plan, nodes, config, job.code_version, result, prefail=prefail)
    result.seconds = time.perf_counter() - t0
    return vars(result)


def _retry_unless_full(task, task_run, state) -> bool:
    """Prefect retries a task that died (a lost worker), not one that found the store full."""
    exc = state.data if isinstance(state.data, BaseException) else None
    return not isinstance(exc, StoreFull)


_OPTIONS = {"retries": 1, "retry_delay_seconds": [5.0], "retry_condition_fn": _retry_unless_full, "persist_result": False}


def _no_cache():
    from prefect.cache_policies import NO_CACHE

    return NO_CACHE


@task(name="curate-clip", task_run_name="clip[{clip_id}]", cache_policy=_no_cache(), **_OPTIONS)
def curate_clip(job: ClipJob, clip_id: str = "") -> dict:
    return run_clip(job)


@task(name="curate-embodiment", task_run_name="embodiment[{job.clip}|{emb_id}]", cache_policy=_no_cache(), **_OPTIONS)
def curate_embodiment(job: EmbodimentJob, emb_id: str = "") -> dict:
    return run_embodiment(job)
