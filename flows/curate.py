"""The curate flow: source clips -> harmonized robot composites, on a Dask cluster.

    ingest -> segment -> restore_background (per scope: hand | hand_arm)
           -> per embodiment: retarget -> render -> composite -> harmonize -> qc

The flow driver plans clips x embodiments, creates every array (it is the only process
that creates arrays or writes attributes), then schedules chunk tasks on the Dask task
runner as their inputs complete, skipping chunks whose provenance is current, and
records each chunk's provenance and rejections as results arrive.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import subprocess
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from prefect import flow, get_run_logger
from prefect.context import get_run_context
from tqdm import tqdm

import handedit
from handedit.flows.config import CurateConfig
from handedit.flows.dag import ClipPlan, Node, NodeId, build_nodes
from handedit.flows.scheduler import DagResult, Prepared, run_dag
from handedit.embodiments import EmbodimentError, describe_embodiment, get_embodiment, resolve_urdf
from handedit.reasons import Reason
from handedit.sources import SourceError, open_source
from handedit.storage import Unit, create_or_open_store, create_unit, read_records, write_ledger_table, write_records
from handedit.storage.ledger import read_ledger, status_counts
from handedit.storage.provenance import ChunkRecord
from handedit.storage.store import create_previews, dumps, jsonable, now_iso, set_attrs
from handedit.tasks import STAGE_TASKS
from handedit.tasks.common import RETRIES, ChunkJob, failure_record, is_transient


def code_version() -> str:
    """Package version plus the git commit when running from a checkout."""
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).parent, capture_output=True, text=True, timeout=5
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        sha = ""
    return f"{handedit.__version__}+{sha}" if sha else handedit.__version__


@dataclass
class EmbodimentPlan:
    id: str
    scope: str
    joint_names: list[str]
    error: str | None = None
    reason: int = int(Reason.OK)
    urdf_digest: str = ""  # content of the resolved (or composed) URDF


def plan_clips(config: CurateConfig) -> tuple[list[ClipPlan], dict[str, str]]:
    """Open each source on the driver (metadata only); a bad source is a clip-level rejection."""
    plans, errors = [], {}
    for spec in config.all_clips():
        try:
            info = open_source(spec).info()
        except SourceError as exc:
            errors[spec.id] = str(exc)
            continue
        plans.append(
            ClipPlan(
                clip=info.clip_id,
                n_frames=info.n_frames,
                height=info.height,
                width=info.width,
                intrinsics=info.intrinsics.to_dict(),
                source_json=dumps(spec.model_dump(mode="json")),
                fingerprint=info.fingerprint,
                has_object=info.has_object,
                has_gt=bool(info.ground_truth),
                info=jsonable({**vars(info), "intrinsics": info.intrinsics.to_dict()}),
                hands=tuple(info.hands),
                has_arm=info.has_arm,
                has_keypoints=info.has_keypoints,
                world=info.world,
                keypoints_exact=info.keypoints_exact,
            )
        )
    ids = [p.clip for p in plans]
    if len(set(ids)) != len(ids):
        raise ValueError(f"clip ids must be unique, got {ids}")
    return plans, errors


def plan_embodiments(ids: list[str]) -> list[EmbodimentPlan]:
    """Resolve each embodiment's track and joints; missing or broken assets reject only
    that embodiment's frames (ids themselves were validated with the config)."""
    plans = []
    for emb_id in ids:
        track = get_embodiment(emb_id).track
        try:
            _, joints = describe_embodiment(emb_id)
            urdf = file_digest(resolve_urdf(get_embodiment(emb_id)))
            plans.append(EmbodimentPlan(emb_id, track, joints, urdf_digest=urdf))
        except EmbodimentError as exc:
            plans.append(EmbodimentPlan(emb_id, track, [], f"{type(exc).__name__}: {exc}", int(exc.reason)))
    return plans


def _create_units(root, config: CurateConfig, clip: ClipPlan, embs: list[EmbodimentPlan]) -> None:
    f, sizes = config.frames_per_chunk, {"H": clip.height, "W": clip.width, "S": len(clip.hands)}
    hands = {"hands": list(clip.hands)}
    create_unit(root, Unit("ingest", clip.clip), clip.n_frames, sizes, f, clip.has_object, clip.has_gt,
                attrs={"info": clip.info, **hands}, has_arm=clip.has_arm)
    create_unit(root, Unit("registration", clip.clip), clip.n_frames, sizes, f, attrs=hands, has_arm=clip.has_arm)
    create_unit(root, Unit("segment", clip.clip), clip.n_frames, sizes, f, attrs=hands)
    for scope in sorted({e.scope for e in embs}):
        create_unit(root, Unit("restore_background", clip.clip, scope=scope), clip.n_frames, sizes, f)
    for emb in embs:
        for stage in ("retarget", "render", "composite", "harmonize", "qc"):
            extra = {**hands, **({"joint_names": emb.joint_names} if stage == "retarget" else {})}
            create_unit(root, Unit(stage, clip.clip, embodiment=emb.id), clip.n_frames,
                        {**sizes, "dof": len(emb.joint_names)}, f, attrs=extra)
        if emb.scope == "hand_arm":
            for side in clip.hands:
                create_previews(root, Unit("retarget", clip.clip, embodiment=emb.id), clip.height, clip.width, side)


def stage_version_params(config: CurateConfig, stage: str) -> tuple[int, dict]:
    """A stage's code version (its config class's VERSION) and parameters."""
    cfg = config.stage_config(stage)
    return int(getattr(type(cfg), "VERSION", 1)), cfg.model_dump(mode="json")


def add_asset_inputs(config: CurateConfig, nodes: list[Node], embs: list[EmbodimentPlan]) -> None:
    """Files a stage reads besides the store are inputs too, by content: a stage's model
    weights, and the robot's URDF for the stages that load it. New weights or a new robot
    description at the same path change the provenance key and re-run those stages."""
    models: dict[str, str] = {}
    for stage in {n.unit.stage for n in nodes}:
        path = getattr(config.stage_config(stage), "model_path", None)
        if path:
            models[stage] = file_digest(Path(path))
    urdfs = {e.id: e.urdf_digest for e in embs}
    for node in nodes:
        if node.unit.stage in models:
            node.fixed_inputs["model"] = models[node.unit.stage]
        if node.unit.stage in ("retarget", "render") and node.unit.embodiment:
            node.fixed_inputs["urdf"] = urdfs.get(node.unit.embodiment, "")


def file_digest(path: Path) -> str:
    """sha256 of a file, cached by (path, size, mtime)."""
    try:
        st = path.stat()
    except OSError:
        return "missing"
    return _file_digest(str(path), st.st_size, st.st_mtime_ns)


@lru_cache(maxsize=64)
def _file_digest(path: str, size: int, mtime_ns: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _matches_fault(config: CurateConfig, unit: Unit) -> bool:
    names = [f"{unit.stage}:{unit.clip}", f"{unit.stage}:{unit.clip}:{unit.embodiment or unit.scope or ''}"]
    return any(fnmatch.fnmatchcase(n, pat) for pat in config.inject_faults for n in names)


class ClusterLost(RuntimeError):
    """The Dask cluster has had no worker for longer than the configured timeout."""


def _worker_watchdog(timeout_s: float):
    """An ``on_idle`` callback: fail loudly instead of waiting forever on a dead cluster."""
    since: list[float] = []

    def on_idle(idle_s: float) -> None:
        try:
            n = len(get_run_context().task_runner.client.scheduler_info(n_workers=-1)["workers"])
        except Exception:
            n = -1  # cannot tell; keep waiting
        if n != 0:
            since.clear()
            return
        since.append(idle_s)
        if idle_s - since[0] >= timeout_s:
            raise ClusterLost(
                f"no chunk finished for {idle_s:.0f} s and the Dask cluster has had no worker for "
                f"{idle_s - since[0]:.0f} s; check the workers' logs (the dashboard link above), restart "
                f"them, and re-run: finished chunks are kept and skipped"
            )

    return on_idle


def _dashboard_link() -> str | None:
    try:
        return get_run_context().task_runner.client.dashboard_link
    except Exception:
        return None


@flow(name="curate")
def curate(config: CurateConfig, progress: bool = False) -> dict:
    """Curate ``config.clips`` x ``config.embodiments`` into the store at ``config.out``."""
    logger = get_run_logger()
    version, started = code_version(), now_iso()
    root = create_or_open_store(config.out, config.frames_per_chunk, version)
    clips, clip_errors = plan_clips(config)
    embs = plan_embodiments(config.embodiments)
    registry = dict(root.attrs.get("clips") or {})
    for c in clips:
        registry[c.clip] = {"source": json.loads(c.source_json), "n_frames": c.n_frames, "fingerprint": c.fingerprint}
    for clip_id, err in clip_errors.items():
        registry[clip_id] = {"error": err, "reason": int(Reason.SOURCE_UNREADABLE)}
        logger.error("clip %s rejected: %s", clip_id, err)
    set_attrs(root, "", {"clips": registry, "embodiments": {e.id: {"scope": e.scope, "dof": len(e.joint_names), "error": e.error} for e in embs}})
    for e in embs:
        if e.error:
            logger.error("embodiment %s rejected: %s", e.id, e.error)
    for c in clips:
        _create_units(root, config, c, embs)

    scopes = {e.id: e.scope for e in embs}
    window = config.restore_background.window
    nodes = [n for c in clips for n in build_nodes(c, scopes, config.frames_per_chunk, window)]
    add_asset_inputs(config, nodes, embs)
    units = sorted({n.unit for n in nodes})
    stage_params = {stage: stage_version_params(config, stage) for stage in {u.stage for u in units}}
    for unit in units:
        version_, params = stage_params[unit.stage]
        set_attrs(root, unit.path, {"stage": unit.stage, "version": version_, "params": params})
    stored = {u: read_records(root, u) for u in units}
    failed_embs = {e.id: e for e in embs if e.error}
    jobs: dict[NodeId, ChunkJob] = {}

    def job_for(prep: Prepared) -> ChunkJob:
        n = prep.node
        job = ChunkJob(str(config.out), n.unit, n.chunk, n.start, n.stop, prep.key, prep.version, prep.params,
                       prep.inputs, version, n.context, fault=_matches_fault(config, n.unit))
        jobs[n.id] = job
        return job

    def submit(prep: Prepared):
        return STAGE_TASKS[prep.node.unit.stage].submit(job_for(prep))

    def complete(prep: Prepared, handle) -> tuple[dict, bool]:
        result = handle.result(raise_on_failure=False)
        if isinstance(result, dict):
            return result, False
        exc = result if isinstance(result, BaseException) else RuntimeError(f"task ended without a result: {result!r}")
        reason = Reason(int(getattr(exc, "reason", Reason.STAGE_ERROR)))
        attempts = RETRIES + 1 if is_transient(exc) else 1
        logger.warning("%s chunk %d failed: %s", prep.node.unit.label, prep.node.chunk, exc)
        return failure_record(jobs[prep.node.id], root, reason, f"{type(exc).__name__}: {exc}", attempts), True

    def prefail(prep: Prepared) -> dict | None:
        emb = failed_embs.get(prep.node.unit.embodiment or "")
        if emb is None or prep.node.unit.stage != "retarget":
            return None
        return failure_record(job_for(prep), root, Reason(emb.reason), emb.error or "", 0)

    def on_record(node: Node, record: dict) -> None:
        write_records(root, node.unit, [ChunkRecord.from_json(record)])

    link = _dashboard_link()
    logger.info("Dask dashboard: %s", link)
    if progress:
        tqdm.write(f"Dask dashboard: {link or '(not available)'}")
    bar = tqdm(total=len(nodes), desc="curate", unit="chunk", disable=not progress)
    try:
        result = run_dag(nodes, stage_params.__getitem__, lambda nid: _stored(stored, nid), submit, complete,
                         prefail, on_record, bar.update, on_idle=_worker_watchdog(config.cluster.worker_timeout))
    finally:
        bar.close()
    return _finish(root, config, result, started, link, clip_errors)


def _stored(stored: dict, node_id: NodeId) -> dict | None:
    unit, chunk = node_id
    rec = stored.get(unit, {}).get(chunk)
    return rec.to_json() if rec is not None else None


def _finish(root, config: CurateConfig, result: DagResult, started: str, link: str | None, clip_errors: dict) -> dict:
    n_rejections = write_ledger_table(root)
    counts = {stage: vars(c) for stage, c in result.counts.items()}
    run = {"started": started, "finished": now_iso(), "dashboard": link, "stages": counts, "errors": result.errors[:50],
           "rejections": n_rejections, "clip_errors": clip_errors}
    set_attrs(root, "", {"runs": [*(root.attrs.get("runs") or []), run]})
    status = status_counts(root)
    ledger = read_ledger(root)
    by_reason = ledger.groupby(["stage", "reason_name"]).size().to_dict() if len(ledger) else {}
    return {
        "store": str(config.out),
        "dashboard": link,
        "stages": counts,
        "status": status.to_dict(orient="records"),
        "rejections": {f"{s}:{r}": int(n) for (s, r), n in by_reason.items()},
        "errors": result.errors,
        "clip_errors": clip_errors,
    }


def run_curate(config: CurateConfig, progress: bool = False) -> dict:
    """Run the flow on the configured Dask cluster (LocalCluster unless an address is set)."""
    return curate.with_options(task_runner=config.cluster.task_runner())(config, progress=progress)


__all__ = ["curate", "run_curate", "CurateConfig", "code_version"]


def load_config(config_path: str | Path, cluster_path: str | Path | None = None, out: str | None = None) -> CurateConfig:
    """A YAML CurateConfig, optionally with the ``cluster:`` section of a deploy/cluster spec."""
    import yaml

    config = CurateConfig.from_yaml(config_path)
    update: dict = {}
    if cluster_path:
        spec = yaml.safe_load(Path(cluster_path).read_text()) or {}
        update["cluster"] = type(config.cluster).model_validate(spec.get("cluster", spec))
    if out:
        update["out"] = Path(out)
    return config.model_copy(update=update) if update else config


@flow(name="curate-from-config", log_prints=True)
def curate_from_config(config_path: str, cluster_path: str | None = None, out: str | None = None) -> dict:
    """Deployment entry point (deploy/prefect.yaml): runs ``curate`` as a subflow on the
    Dask cluster the config names, so one deployment serves local, Slurm or Kubernetes."""
    return run_curate(load_config(config_path, cluster_path, out))
