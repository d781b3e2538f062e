"""The curate flows: source clips -> harmonized robot composites, sharded over a Dask cluster.

    curate (the driver)                 plans shards lazily, skips complete ones, claims the rest
      curate-shard (one flow run each)  per clip: curate_clip -> per embodiment: curate_embodiment

The driver lists the sources one group at a time, cuts shards (``handedit.flows.plan``),
and for each shard reads one manifest: a shard whose last run covered this exact plan and
left every chunk current is skipped. Otherwise it claims the shard (``storage.shards``:
create-if-absent, so two drivers on one store work on disjoint shards) and runs it as a
subflow on the run's Dask cluster, at most ``shards_in_flight`` at a time. A shard flow
submits 1 + E Prefect tasks per clip (``handedit.tasks.clip``: each walks its chunks), then
writes the shard's index and ledger partitions, its run log and its manifest.

Failures: a chunk that fails is recorded in its unit (``STAGE_ERROR``) and the rest goes
on; a clip whose source cannot be opened is one clip-level row (``SOURCE_UNREADABLE``); a
shard with failures stays incomplete, so the next run retries exactly what failed.
"""

from __future__ import annotations

import contextvars
import json
import logging
import os
import subprocess
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

from distributed import span
from prefect import flow, get_run_logger
from tqdm import tqdm

import handedit
from handedit.digests import embodiment_digest, model_digests as stage_model_digests
from handedit.embodiments import EmbodimentError, describe_embodiment, get_embodiment, resolve_urdf
from handedit.embodiments.robot_files import robot_dirs_added
from handedit.flows import progress as progress_of
from handedit.flows.api import run_url
from handedit.flows.config import CurateConfig, PreflightError, dashboard_link
from handedit.flows.plan import iter_shards, run_key
from handedit.reasons import Reason
from handedit.storage import Location, create_or_open_store, open_store
from handedit.storage.integrity import chunk_object_count, clips_missing_objects
from handedit.storage.layout import SCHEMA_VERSION
from handedit.storage.ledger import read_ledger, status_counts
from handedit.storage.shards import (INDEX, LEDGER, has_partitions, is_complete, new_holder, read_manifest, release,
                                     renew, try_claim, write_manifest, write_partition, write_run_log)
from handedit.storage.store import CorruptChunk, jsonable, now_iso, store_full
from handedit.storage.summary import index_rows
from handedit.tasks import STAGES as STAGE_DECLARATIONS
from handedit.tasks.clip import ClipJob, EmbodimentJob, curate_clip, curate_embodiment, stage_version_params



def run_links(dashboard: str | None, prefect_run: str | None, local_cluster: bool) -> dict:
    """The run's monitoring links, each with what an operator should know of how long it lives
    (kept in every shard's run log; releases keep only lasting links)."""
    from handedit.flows.api import api_is_temporary

    gone = "gone when this command exits"
    return {"Dask dashboard": {"url": dashboard, "note": f"this run's own cluster: {gone}" if local_cluster and dashboard else ""},
            "Prefect run": {"url": prefect_run, "note": f"a temporary Prefect API: {gone}" if api_is_temporary() and prefect_run
                            else ""}}


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
    robot_digest: str = ""  # content of the resolved (or composed) URDF, every mesh it names, and its robot files


def plan_embodiments(ids: list[str]) -> list[EmbodimentPlan]:
    """Resolve each embodiment's track and joints once per run; missing or broken assets
    reject only that embodiment's frames (ids themselves were validated with the config)."""
    plans = []
    for emb_id in ids:
        track = get_embodiment(emb_id).track
        try:
            _, joints = describe_embodiment(emb_id)
            emb = get_embodiment(emb_id)
            robot = embodiment_digest(resolve_urdf(emb), emb.files)
            plans.append(EmbodimentPlan(emb_id, track, joints, robot_digest=robot))
        except EmbodimentError as exc:
            plans.append(EmbodimentPlan(emb_id, track, [], f"{type(exc).__name__}: {exc}", int(exc.reason)))
    return plans


def model_digests(config: CurateConfig) -> dict[str, str]:
    """Content of each stage's model file (new weights at the same path change the run key)."""
    out = {}
    for stage in (s.name for s in STAGE_DECLARATIONS):
        for name, d in stage_model_digests(config.stage_config(stage)).items():
            out[stage if name == "model" else f"{stage}:{name}"] = d
    return out


def the_run_key(config: CurateConfig, embs: list[EmbodimentPlan]) -> str:
    params = {s.name: stage_version_params(config, s.name) for s in STAGE_DECLARATIONS}
    versions = {s.name: s.versions(config.stage_config(s.name)) for s in STAGE_DECLARATIONS}
    return run_key(config.frames_per_chunk, {"params": params, "versions": versions, "models": model_digests(config)},
                   [{"id": e.id, "scope": e.scope, "robot": e.robot_digest, "error": e.error} for e in embs], SCHEMA_VERSION)


# ----------------------------------------------------------------------------- one shard


def _merge(into: dict, stages: dict) -> None:
    for stage, c in stages.items():
        t = into.setdefault(stage, {"ran": 0, "skipped": 0, "failed": 0})
        for k in t:
            t[k] += c.get(k, 0)


@flow(name="curate-shard", flow_run_name="shard-{shard_id}")
def curate_shard(config_json: str, shard_id: str, specs_json: list[str], embodiments: list[dict], run_id: str,
                 digest: str, code: str, links: dict | None = None) -> dict:
    """One shard: 1 + E tasks per clip on the run's cluster, then the shard's bookkeeping."""
    from handedit.sources import parse_spec

    config = CurateConfig.model_validate_json(config_json)
    loc = Location(config.out)
    started = now_iso()
    scopes = tuple(sorted({e["scope"] for e in embodiments}))
    clips = [parse_spec(json.loads(s)).id for s in specs_json]
    clip_futures, emb_futures = [], []
    for spec_json, clip_id in zip(specs_json, clips):
        with span("curate", "clip"):  # Dask spans: the dashboard groups time per embodiment and stage
            fc = curate_clip.submit(ClipJob(loc.store_url, spec_json, config_json, scopes, code), clip_id=clip_id)
        clip_futures.append(fc)
        for emb in embodiments:
            with span("curate", emb["id"]):
                emb_futures.append(curate_embodiment.submit(EmbodimentJob(loc.store_url, clip_id, emb, config_json, code),
                                                            emb_id=emb["id"], wait_for=[fc]))
    stages: dict = {}
    errors, source_errors, task_failures, recovered, recomputed = [], {}, [], [], Counter()
    n_clip_tasks = len(clip_futures)
    for i, fut in enumerate([*clip_futures, *emb_futures]):
        try:
            res = fut.result(raise_on_failure=False)
        except Exception as exc:  # noqa: BLE001 - e.g. never run because its clip task failed
            res = exc
        progress_of.report(run_id, res, embodiment=i >= n_clip_tasks)
        if not isinstance(res, dict):
            task_failures.append(f"{fut.task_run_id}: {res!r}")
            continue
        _merge(stages, res["stages"])
        errors += res["errors"]
        recovered += res.get("recovered", [])
        recomputed.update(res.get("recomputed", {}))
        if res.get("source_error") and res["clip"] not in source_errors and "could not be ingested" not in res["source_error"]:
            source_errors[res["clip"]] = res["source_error"]
    root = open_store(loc)
    ok_clips = [c for c in clips if c not in source_errors]
    written = time.time()
    try:
        index = index_rows(root, ok_clips, source_errors, {e["id"]: e for e in embodiments})
        index["shard"], index["written"] = shard_id, written
        ledger = read_ledger(root, clips=ok_clips, source_errors=source_errors)
        ledger["shard"], ledger["written"] = shard_id, written
        write_partition(loc, INDEX, shard_id, index)
        write_partition(loc, LEDGER, shard_id, ledger)
    except CorruptChunk as exc:  # bytes of a unit no task of this run rewrote: verify --repair names them
        errors.append(str(exc))
    except OSError as exc:  # a full disk fails the shard (and the run), named
        if (full := store_full(exc, f"the index and ledger of shard {shard_id}")) is None:
            raise
        errors.append(str(full))
    # complete: nothing to retry. Chunks an embodiment without assets rejects are the plan's
    # own outcome (they fail identically until its assets, hence the run key, change).
    complete = not task_failures and not errors
    log = {"run": run_id, "shard": shard_id, "started": started, "finished": now_iso(), "stages": stages,
           "errors": errors[:50], "task_failures": task_failures, "clip_errors": source_errors, "complete": complete,
           "recovered": recovered, "recomputed": dict(recomputed), "links": links or {}}
    _shard_artifact(shard_id, log)
    try:
        write_run_log(loc, shard_id, run_id, log)
        write_manifest(loc, shard_id, {"shard": shard_id, "clips": clips, "digest": digest, "complete": complete,
                                       "embodiments": embodiments, "updated": now_iso(), "run": run_id, "stages": stages,
                                       "objects": {c: chunk_object_count(loc, c) for c in ok_clips} if complete else {}})
    except OSError as exc:
        if (full := store_full(exc, f"the run log and manifest of shard {shard_id}")) is None:
            raise
        log["errors"].append(str(full))
        log["complete"] = False
    return log


def _objects_missing(loc: Location, manifest: dict, check: bool) -> bool:
    """A complete shard whose clips now hold fewer chunk objects than when it completed (a
    deleted chunk or array): run it again; its walk finds and recomputes exactly those."""
    gone = clips_missing_objects(loc, manifest.get("objects") or {}) if check else []
    for clip, have, n in gone:
        get_run_logger().warning("shard %s: clip %s has %d of its %d chunk objects; recomputing what is missing",
                                 manifest.get("shard"), clip, have, n)
    return bool(gone)


# ----------------------------------------------------------------------------- the driver


class ClusterLost(RuntimeError):
    """The Dask cluster has had no worker for longer than the configured timeout."""


class _Leases:
    """Renews this driver's shard claims while their shards run (a background thread)."""

    def __init__(self, loc: Location, lease_s: float):
        self.loc, self.lease_s = loc, lease_s
        self.claims: dict[str, object] = {}
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(max(1.0, self.lease_s / 3)):
            with self._lock:
                claims = list(self.claims.values())
            for c in claims:
                renew(self.loc, c, self.lease_s)  # False: a newer generation took the shard over (--take-over)

    def add(self, claim) -> None:
        with self._lock:
            self.claims[claim.shard] = claim

    def done(self, shard: str) -> None:
        with self._lock:
            c = self.claims.pop(shard, None)
        if c is not None:
            self._release(c)

    def close(self) -> None:
        self._stop.set()
        with self._lock:
            claims = list(self.claims.values())
        for c in claims:
            self._release(c)

    def _release(self, claim) -> None:
        """Give a claim back; on a full disk it stays, and lapses with its lease (or its driver's
        process) as a claim of a dead driver does."""
        try:
            release(self.loc, claim)
        except OSError as exc:
            if store_full(exc) is None:
                raise
            logging.getLogger(__name__).warning("shard %s: claim not released (%s); it lapses with its lease",
                                                claim.shard, exc.strerror or exc)


def _watch_workers(address: str, timeout_s: float, stop: threading.Event, lost: list) -> None:
    """Fail loudly instead of waiting forever on a cluster that lost every worker."""
    from distributed import Client

    try:
        client = Client(address, timeout=30)
    except Exception:  # noqa: BLE001 - cannot tell; the shard flows will report
        return
    since = None
    try:
        while not stop.wait(5.0):
            try:
                n = len(client.scheduler_info(n_workers=-1)["workers"])
            except Exception:  # noqa: BLE001
                continue
            if n:
                since = None
                continue
            since = since or time.time()
            if time.time() - since >= timeout_s:
                lost.append(ClusterLost(f"the Dask cluster at {address} has had no worker for {time.time() - since:.0f} s; "
                                        f"check the workers' logs, restart them and re-run: finished chunks are kept"))
                return
    finally:
        client.close()


@flow(name="curate")
def curate(config: CurateConfig, progress: bool = False) -> dict:
    """Curate ``config`` (clips and source trees) x ``config.embodiments`` into ``config.out``."""
    from handedit.flows.runner import task_runner

    logger = get_run_logger()
    loc = Location(config.out)
    version, started = code_version(), now_iso()
    create_or_open_store(loc, config.frames_per_chunk, version)
    with robot_dirs_added(config.robots):  # the run's robot folders, for this run only
        embs = plan_embodiments(config.embodiments)
    for e in embs:
        if e.error:
            logger.error("embodiment %s rejected: %s", e.id, e.error)
    key = the_run_key(config, embs)
    emb_dicts = [asdict(e) for e in embs]
    holder = new_holder()
    config_json = config.model_dump_json()
    summary = {"store": loc.store_url, "stages": {}, "errors": [], "clip_errors": {}, "run": holder,
               "shards": {"ran": 0, "skipped": 0, "held": 0, "incomplete": 0}, "held_by_others": {},
               "recovered": [], "recomputed": {}}
    bar = tqdm(desc="curate", unit="pair", disable=not progress, total=None)
    tally = progress_of.start(holder, len(embs))
    progress_of.list_in_background(tally, iter_shards(config.sources, config.clips, config.shard_size))
    artifact = progress_of.ProgressArtifact(tally)

    def show(final: bool = False) -> None:
        """The bar and the Prefect artifact, from the progress the shard flows report."""
        bar.total = tally.planned_pairs()
        bar.n = tally.pairs_done
        bar.set_postfix_str(tally.brief(), refresh=True)
        artifact.update(force=final)

    with config.cluster.connect() as address:
        summary["dashboard"] = link = dashboard_link(address)
        summary["prefect_run"] = ui = run_url()
        summary["links"] = links = run_links(link, ui, local_cluster=not config.cluster.address)
        for name, entry in links.items():  # one link per line: no punctuation joins a URL
            logger.info("%s: %s%s", name, entry["url"] or "(not available)", f"  ({entry['note']})" if entry["note"] else "")
        if progress:
            tqdm.write("\n".join(f"{name + ':':<16}{e['url'] or '(not available)'}{'  (' + e['note'] + ')' if e['note'] else ''}"
                                 for name, e in links.items()))
        from handedit.flows.preflight import check_workers

        # each worker checks the store, the Prefect API and the robots from where it runs
        check_workers(address, loc.store_url, [e.id for e in embs if not e.error], config.cluster.worker_timeout,
                      config.robots)
        leases = _Leases(loc, config.claim_lease_s)
        stop, lost = threading.Event(), []
        watchdog = threading.Thread(target=_watch_workers, args=(address, config.cluster.worker_timeout, stop, lost), daemon=True)
        watchdog.start()
        shard_flow = curate_shard.with_options(task_runner=task_runner(address))
        pool = ThreadPoolExecutor(config.shards_in_flight)
        in_flight: dict = {}

        def collect(block: bool) -> None:
            while in_flight and (block or len(in_flight) >= config.shards_in_flight):
                done = next((s for s, f in in_flight.items() if f.done()), None)
                if done is None:
                    if lost:
                        raise lost[0]
                    show()
                    time.sleep(0.2)
                    continue
                log = in_flight.pop(done).result()
                leases.done(done)
                _merge(summary["stages"], log["stages"])
                summary["errors"] += log["errors"] + log["task_failures"]
                summary["clip_errors"].update(log["clip_errors"])
                summary["recovered"] += log.get("recovered", [])
                for why, n in log.get("recomputed", {}).items():
                    summary["recomputed"][why] = summary["recomputed"].get(why, 0) + n
                summary["shards"]["ran"] += 1
                summary["shards"]["incomplete"] += 0 if log["complete"] else 1
                show()
            if lost:
                raise lost[0]

        try:
            for shard in iter_shards(config.sources, config.clips, config.shard_size):
                digest = shard.digest(key)
                manifest = read_manifest(loc, shard.id)
                if is_complete(manifest, digest) and has_partitions(loc, shard.id) \
                        and not _objects_missing(loc, manifest, config.check_skipped_shards):
                    summary["shards"]["skipped"] += 1
                    show()
                    continue
                collect(block=False)  # wait for a free slot first: claim only what runs now
                claim, other = try_claim(loc, shard.id, holder, config.claim_lease_s, take_over=config.take_over)
                if claim is None:
                    summary["shards"]["held"] += 1
                    summary["held_by_others"][shard.id] = other.describe()
                    logger.warning("shard %s is held by %s; skipped (run again later, or pass --take-over once "
                                   "that driver is gone)", shard.id, other.describe())
                    continue
                fresh = read_manifest(loc, shard.id)
                if fresh != manifest and is_complete(fresh, digest):
                    # another driver finished it while this one waited for a slot: the check under
                    # the claim is the one that counts
                    release(loc, claim)
                    summary["shards"]["skipped"] += 1
                    show()
                    continue
                leases.add(claim)
                args = (config_json, shard.id, [s.model_dump_json() for s in shard.specs], emb_dicts, holder, digest, version,
                        links)
                in_flight[shard.id] = pool.submit(contextvars.copy_context().run, shard_flow, *args)
            collect(block=True)
        except OSError as exc:  # the driver's own bookkeeping on a full disk: a failed run, named, no traceback
            if (full := store_full(exc, "the run's shard bookkeeping")) is None:
                raise
            summary["errors"].append(str(full))
            summary["shards"]["incomplete"] += 1
        finally:
            stop.set()
            pool.shutdown(wait=True)
            leases.close()
            show(final=True)
            progress_of.stop(holder)
            bar.close()
    for clip_id, err in summary["clip_errors"].items():
        logger.error("clip %s rejected: %s", clip_id, err)
    summary = _finish(loc, summary, started)
    summary["outcome"] = outcome(summary, config.fail_below_kept)
    publish_artifacts(summary)
    if summary["outcome"]["failed"]:
        from prefect.states import Failed

        logger.error("curate failed: %s", "; ".join(summary["outcome"]["reasons"]))
        return Failed(message="; ".join(summary["outcome"]["reasons"]), data=summary)
    logger.info("curate finished: %s of %s frame x embodiment pairs kept", summary["outcome"]["kept"],
                summary["outcome"]["pairs"])
    return summary


def _shard_artifact(shard_id: str, log: dict) -> None:
    """One shard's outcome in Prefect's UI (its flow run's Artifacts tab): chunks per stage."""
    import re

    from prefect.artifacts import create_table_artifact

    rows = [{"stage": stage, **counts} for stage, counts in log["stages"].items()]
    key = "shard-" + re.sub(r"[^a-z0-9-]+", "-", shard_id.lower()).strip("-")
    verdict = "complete" if log["complete"] else f"incomplete ({len(log['errors']) + len(log['task_failures'])} error(s))"
    create_table_artifact(rows, key=key[:100], description=f"shard {shard_id}: chunks ran/skipped/failed per stage; {verdict}")


def publish_artifacts(summary: dict) -> None:
    """The run's outcome in Prefect's UI (the flow run's Artifacts tab): frames per stage and
    status, rejections per stage and reason, and a note with the verdict, the store and the
    links (a LocalCluster's dashboard and a temporary API are gone when the command exits)."""
    from prefect.artifacts import create_markdown_artifact, create_table_artifact

    create_table_artifact([{k: r[k] for k in ("stage", "status", "frames")} for r in summary.get("status", [])],
                          key="curate-frames", description="frames per stage and status (the store's clips)")
    rejections = [{"stage": k.split(":", 1)[0], "reason": k.split(":", 1)[1], "frames": n}
                  for k, n in sorted(summary.get("rejections", {}).items())]
    if rejections:
        create_table_artifact(rejections, key="curate-rejections", description="rejected frames per stage and reason")
    res = summary["outcome"]
    verdict = "**Failed**: " + "; ".join(res["reasons"]) if res["failed"] else "**Completed**"
    lines = [f"# curate: {verdict}", "",
             f"- kept: {res['kept']} of {res['pairs']} frame x embodiment pairs ({res['kept_share']:.1%})",
             f"- store: `{summary.get('store')}`",
             f"- shards: {summary.get('shards')}",
             *(f"- {name}: {e['url'] or '(none)'}" + (f" ({e['note']})" if e["note"] else "")
               for name, e in summary.get("links", {}).items()),
             f"- QA page: `handedit dashboard {summary.get('store')}`"]
    create_markdown_artifact("\n".join(lines), key="curate-outcome", description="the run's verdict, store and links")


def outcome(summary: dict, fail_below_kept: float) -> dict:
    """Whether a run failed, and why: chunks that failed after their retries, shards left
    incomplete, or a kept share (QC-passed frame x embodiment pairs over all of them) at or
    below ``fail_below_kept`` (0: nothing kept). Partial success is a success with its share."""
    qc = [r for r in summary.get("status", []) if r["stage"] == "qc"]
    pairs = sum(int(r["frames"]) for r in qc)
    kept = sum(int(r["frames"]) for r in qc if r["status"] == "OK")
    share = kept / pairs if pairs else 0.0
    reasons = []
    failed_chunks = sum(int(v.get("failed", 0)) for v in summary.get("stages", {}).values())
    if failed_chunks:
        reasons.append(f"{failed_chunks} chunk(s) failed after their retries (see the errors above; re-run to retry them)")
    if summary.get("shards", {}).get("incomplete"):
        reasons.append(f"{summary['shards']['incomplete']} shard(s) left incomplete")
    if share <= fail_below_kept:
        reasons.append(f"kept {kept} of {pairs} frame x embodiment pairs ({share:.1%}), at or below fail_below_kept "
                       f"{fail_below_kept:.1%}" if pairs else "no frame reached QC")
    return {"failed": bool(reasons), "reasons": reasons, "kept": kept, "pairs": pairs, "kept_share": round(share, 4)}


def _finish(loc: Location, summary: dict, started: str) -> dict:
    from handedit.storage.summary import read_index

    root = open_store(loc)
    index = read_index(loc)
    failed = index["error"].astype(str) != "" if index is not None else None
    every = sorted(set(index["clip"])) if index is not None else []
    clips = sorted(set(index.loc[~failed, "clip"])) if index is not None else []
    unreadable = dict(zip(index.loc[failed, "clip"], index.loc[failed, "error"])) if index is not None else {}
    summary["clips"] = {"curated": len(clips), "unreadable": len(every) - len(clips)}
    summary["status"], summary["rejections"] = [], {}
    try:
        summary["status"] = status_counts(root, clips=clips).to_dict(orient="records")
        ledger = read_ledger(root, clips=every, source_errors=unreadable)  # with the unreadable clips' rows
        by_reason = ledger.groupby(["stage", "reason_name"]).size().to_dict() if len(ledger) else {}
        summary["rejections"] = {f"{s}:{r}": int(n) for (s, r), n in by_reason.items()}
    except CorruptChunk as exc:  # a chunk no task of this run touched: named, with what to run
        summary["errors"].append(str(exc))
    summary["started"], summary["finished"] = started, now_iso()
    return jsonable(summary)


def _source_roots(config: CurateConfig) -> list[Path]:
    """The local folders the run reads its clips from (dataset trees, explicit clips' roots)."""
    roots = [Path(t.root) for t in config.sources if getattr(t, "root", None)]
    for spec in config.clips:
        where = getattr(spec, "root", None) or (Path(spec.path).parent if getattr(spec, "path", None) else None)
        if where is not None:
            roots.append(Path(where))
    return list(dict.fromkeys(roots))


def preflight(config: CurateConfig) -> None:
    """Cheap checks that would otherwise fail after the cluster started, each with the fix."""
    from handedit.storage.layout import safe_name

    for i, spec in enumerate(config.clips):
        try:
            safe_name("clip id", spec.id)
        except ValueError as exc:
            raise PreflightError(f"clips[{i}]: {exc}") from None
    if config.cluster.address:
        config.cluster.check_reachable()
    loc = Location(config.out)
    if loc.is_local:
        run_dir = Path(loc.root)
        for root in _source_roots(config):
            if run_dir.resolve().is_relative_to(root.resolve()):
                logging.getLogger(__name__).warning(
                    "--out %s is inside the source tree %s: the run's files will sit among the dataset's (and a later "
                    "tree scan may meet them); a folder outside it is safer", config.out, root)
        if run_dir.is_file() or (Path(loc.path(loc.store_name)).is_file()):
            raise PreflightError(f"--out {config.out} is a file; give a folder for the run (it holds handedit.zarr)")
        try:
            run_dir.mkdir(parents=True, exist_ok=True)
            probe = run_dir / f".write-test-{os.getpid()}"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            raise PreflightError(f"cannot write to --out {config.out} ({exc.strerror or exc}); give a writable folder "
                                 f"(or fix its permissions / free space)") from None


def run_curate(config: CurateConfig, progress: bool = False) -> dict:
    """Run the driver flow (it starts or connects to the Dask cluster the config names) on
    the run's one Prefect API (``handedit.flows.api``)."""
    from handedit.flows.api import run_api

    preflight(config)
    with run_api() as api:
        _warn_unreachable_api(api, config)
        state = curate(config, progress=progress, return_state=True)
        summary = state.result(raise_on_failure=False)
        if isinstance(summary, BaseException):  # the driver itself raised: not a run outcome
            raise summary
        return summary


def _warn_unreachable_api(api: str, config: CurateConfig) -> None:
    import logging
    from urllib.parse import urlparse

    local = ("127.0.0.1", "localhost", "::1")
    remote = config.cluster.cluster_class or (config.cluster.address and config.cluster.scheduler_host()[0] not in local)
    if remote and urlparse(api).hostname in local:
        logging.getLogger("handedit.curate").warning(
            "the run's Prefect API is %s, which workers on other hosts cannot reach: run `prefect server start` on a "
            "host they can reach and set PREFECT_API_URL on the driver and the workers", api)


__all__ = ["curate", "curate_shard", "run_curate", "CurateConfig", "code_version"]


def load_config(config_path: str | Path, cluster_path: str | Path | None = None, out: str | None = None) -> CurateConfig:
    """A YAML CurateConfig, optionally with the ``cluster:`` section of a deploy/cluster spec."""
    import yaml

    config = CurateConfig.from_yaml(config_path)
    update: dict = {}
    if cluster_path:
        spec = yaml.safe_load(Path(cluster_path).read_text()) or {}
        update["cluster"] = type(config.cluster).model_validate(spec.get("cluster", spec))
    if out:
        update["out"] = str(out)
    return config.model_copy(update=update) if update else config


@flow(name="curate-from-config", log_prints=True)
def curate_from_config(config_path: str, cluster_path: str | None = None, out: str | None = None) -> dict:
    """Deployment entry point (deploy/prefect.yaml): runs ``curate`` as a subflow on the
    Dask cluster the config names, so one deployment serves local, Slurm or Kubernetes."""
    summary = run_curate(load_config(config_path, cluster_path, out))
    if summary.get("outcome", {}).get("failed"):
        from prefect.states import Failed

        return Failed(message="; ".join(summary["outcome"]["reasons"]), data=summary)
    return summary
