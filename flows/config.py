"""Configuration of a curate run: clips, embodiments, per-stage parameters, cluster.

One pydantic model, loadable from YAML (deployments) or built by the CLI. Each stage's
parameters are that stage's own config class from ``handedit``; their values (and the
class's VERSION) feed the provenance key, so editing one re-runs that stage and only
what reads its output.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, ValidationInfo, field_validator

from handedit.embodiments import get_embodiment
from handedit.qc import QCConfig
from handedit.render.stage import RenderConfig
from handedit.retarget import RetargetConfig
from handedit.sources import SourceSpec, TreeSpec
from handedit.sources.base import IngestConfig
from handedit.vision.registration import RegistrationConfig
from handedit.vision.composite import CompositeConfig
from handedit.vision.estimate_hands import EstimateHandsConfig
from handedit.vision.harmonize import HarmonizeConfig
from handedit.vision.restore_background import RestoreConfig
from handedit.vision.segment import SegmentConfig


class PreflightError(ValueError):
    """Something a run would fail on, found before any server or cluster starts."""


def _models_in(annotation) -> list[type[BaseModel]]:
    """The pydantic models an annotation can hold (through list[...], unions, Optional)."""
    import typing

    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _models_in(arg)]


def explain(exc, model: type[BaseModel]) -> str:
    """A validation error as lines; an unknown key names the closest valid ones
    (``frames_per_chunks`` -> did you mean ``frames_per_chunk``?)."""
    import difflib

    lines = []
    for err in exc.errors():
        where = ".".join(str(p) for p in err["loc"])
        if err["type"] != "extra_forbidden":
            lines.append(f"  {where}: {err['msg']}")
            continue
        models = [model]
        for part in err["loc"][:-1]:
            nxt = [m for c in models if isinstance(part, str) and part in c.model_fields
                   for m in _models_in(c.model_fields[part].annotation)]
            tagged = [c for c in models if "kind" in c.model_fields and c.model_fields["kind"].default == part]
            models = nxt or tagged or models  # a union's tag picks its member; list indices keep the candidates
        valid = sorted({f for c in models for f in c.model_fields})
        close = difflib.get_close_matches(str(err["loc"][-1]), valid, n=3, cutoff=0.6)
        hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else f"; valid keys: {', '.join(valid)}"
        lines.append(f"  {where}: unknown key{hint}")
    return "\n".join(lines)


# Dask's nanny starts workers with OMP/MKL/OPENBLAS_NUM_THREADS=1 and an aggressive
# MALLOC_TRIM_THRESHOLD_ (``distributed.nanny.pre-spawn-environ``). Our chunk bodies are
# OpenCV/numpy/llvmpipe work with serial Python between parallel regions: with one thread
# per library per worker, cores sit idle while the other worker is in Python. Measured on
# this 2-core machine (bench/scale.py): chunk bodies 1.6x slower in such workers than in a
# plain process; with the libraries' own defaults, the same. The profiler's default 10 ms
# stack sampling costs a few percent more; every 100 ms still fills the dashboard's page.
LOCAL_WORKER_CONFIG = {"distributed.nanny.pre-spawn-environ": {}, "distributed.worker.profile.interval": "100ms"}


class ClusterConfig(BaseModel):
    """Where tasks run: a local cluster of worker processes, an existing scheduler, or a
    cluster class (e.g. ``dask_jobqueue.SLURMCluster``, ``dask_kubernetes.operator.KubeCluster``)
    started for the run; see ``deploy/cluster/*.yaml``."""

    model_config = ConfigDict(extra="forbid")

    address: str | None = Field(None, description="tcp://host:8786 of a running Dask scheduler")
    cluster_class: str | None = Field(None, description="qualified name of a Dask cluster class")
    cluster_kwargs: dict = Field(default_factory=dict, description="arguments of cluster_class")
    adapt: dict | None = Field(None, description="e.g. {minimum: 0, maximum: 64} for adaptive clusters")
    n_workers: int = Field(2, ge=1)
    threads_per_worker: int = Field(1, ge=1, description="1: renderers and solvers are per process")
    memory_limit: str = "6GiB"
    dashboard_address: str = "127.0.0.1:0"
    no_worker_timeout_s: float | None = Field(
        None, gt=0, description="abort after this long without any worker (default: 120 s local, 1800 s otherwise)"
    )

    @property
    def worker_timeout(self) -> float:
        """Local workers should always be there; remote or adaptive ones may queue for a while."""
        if self.no_worker_timeout_s is not None:
            return self.no_worker_timeout_s
        return 1800.0 if (self.address or self.cluster_class) else 120.0

    def scheduler_host(self) -> tuple[str | None, int]:
        """(host, port) of ``address`` (``tcp://host:port`` or ``host:port``; port 8786 by default)."""
        from urllib.parse import urlparse

        u = urlparse(self.address if "://" in self.address else f"tcp://{self.address}")
        return u.hostname, u.port or 8786

    def check_reachable(self, timeout_s: float = 10.0) -> None:
        """An unreachable scheduler address is one message now, not a traceback after a
        long connect timeout."""
        import socket

        try:
            with socket.create_connection(self.scheduler_host(), timeout=timeout_s):
                pass
        except (OSError, ValueError) as exc:
            raise PreflightError(f"cannot reach the Dask scheduler at {self.address} ({exc}); start it "
                             f"(`dask scheduler`) or fix --address / cluster.address") from None

    @contextmanager
    def connect(self):
        """The scheduler address for the run: the given one, or a cluster started for the
        run (``cluster_class``, else a LocalCluster of ``n_workers`` processes on 127.0.0.1),
        closed at the end. Shard flows reach it through ``DaskTaskRunner(address=...)``."""
        if self.address:
            yield self.address
            return
        if self.cluster_class:
            import importlib

            mod, _, name = self.cluster_class.rpartition(".")
            cluster = getattr(importlib.import_module(mod), name)(**self.cluster_kwargs)
            if self.adapt:
                cluster.adapt(**self.adapt)
            elif not getattr(cluster, "workers", None):  # a job-queue cluster starts with none: n_workers jobs
                cluster.scale(self.n_workers)
        else:
            import dask
            from distributed import LocalCluster

            with dask.config.set(LOCAL_WORKER_CONFIG):
                cluster = LocalCluster(n_workers=self.n_workers, threads_per_worker=self.threads_per_worker,
                                       processes=True, host="127.0.0.1", dashboard_address=self.dashboard_address,
                                       memory_limit=self.memory_limit)
        with cluster:
            yield cluster.scheduler_address


def dashboard_link(address: str) -> str | None:
    """The Dask dashboard URL of the scheduler at ``address`` (None when it has none)."""
    try:
        from distributed import Client

        with Client(address, timeout=30) as c:
            return c.dashboard_link
    except Exception:  # noqa: BLE001 - a link, never a reason to fail
        return None


Url = Annotated[str, BeforeValidator(lambda v: str(v))]


class CurateConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    out: Url = Field(description="the run folder or its store: runs/demo, runs/demo/handedit.zarr, s3://bucket/prefix")
    clips: list[SourceSpec] = Field(default_factory=list, description="explicit clips")
    sources: list[TreeSpec] = Field(default_factory=list, description="dataset trees, e.g. {kind: egodex, root: DIR}")
    robots: list[str] = Field(default_factory=list, description="folders of robot files (one YAML file per hand, arm or "
                              "hand-arm; see handedit.embodiments.robot_files) joining the roster for this run and its "
                              "workers, like $HANDEDIT_ROBOT_DIRS")
    embodiments: list[str] = ["allegro"]
    frames_per_chunk: int = Field(16, ge=1, description="frames per chunk; fixed per store")
    shard_size: int = Field(64, ge=1, description="clips per shard: a shard is one flow run and one claim")
    shards_in_flight: int = Field(2, ge=1, description="shard flow runs at a time (the driver holds only these)")
    claim_lease_s: float = Field(600.0, gt=0, description="a shard claim lapses this long after its last renewal")
    take_over: bool = Field(False, description="claim shards even when another driver's claim looks live")
    check_skipped_shards: bool = Field(True, description="before skipping a complete shard, list its clips' chunk "
                                       "objects (one listing per clip) and re-run it if any is missing")
    handoff_mib: int = Field(512, ge=0, description="chunks a task wrote, kept in memory (up to this many MiB per task) "
                             "for its own later stages that read them (storage.handoff); 0: every read decodes the store")
    reuse_mib: int = Field(512, ge=0, description="other tasks' chunks a worker decoded (a clip's background, frames, masks), "
                           "kept (up to this many MiB per worker process) for its next embodiment task of the clip; 0: off")
    fail_below_kept: float = Field(0.0, ge=0, le=1, description="the run fails (exit status 1, Prefect state Failed) when the "
                                   "share of frame x embodiment pairs kept is at or below this (0: when nothing is kept); a "
                                   "run with failed chunks fails too")
    estimate_hands: EstimateHandsConfig = EstimateHandsConfig()
    registration: RegistrationConfig = RegistrationConfig()
    segment: SegmentConfig = SegmentConfig()
    restore_background: RestoreConfig = RestoreConfig()
    retarget: RetargetConfig = RetargetConfig()
    render: RenderConfig = RenderConfig()
    # The source's object mask shows the object where it was in front of the hand, so by
    # default it occludes the robot there too (object depth, when known, refines this).
    composite: CompositeConfig = CompositeConfig(occluder_in_front_without_depth=True)
    harmonize: HarmonizeConfig = HarmonizeConfig()
    qc: QCConfig = QCConfig()
    cluster: ClusterConfig = ClusterConfig()
    inject_faults: list[str] = Field(
        default_factory=list,
        description="drills/tests: 'stage:clip[:embodiment]' globs whose chunks raise InjectedFault",
    )

    @field_validator("robots")
    @classmethod
    def _robot_dirs(cls, dirs: list[str]) -> list[str]:
        """Absolute, so that workers started elsewhere find the same folders."""
        return [str(Path(d).expanduser().resolve()) for d in dirs]

    @field_validator("embodiments")
    @classmethod
    def _known_embodiments(cls, ids: list[str], info: ValidationInfo) -> list[str]:
        """A typo fails before any work starts; missing assets are per-embodiment rejections.
        Keys may be in the run's ``robots`` folders, looked up for this check only: the process
        that validates a run (a Prefect worker serving many) keeps no folder of it."""
        from handedit.embodiments.robot_files import RobotFileError, robot_dirs_added

        try:
            with robot_dirs_added(info.data.get("robots", [])):
                for emb_id in ids:
                    get_embodiment(emb_id)  # raises with the list of known ids
        except RobotFileError as exc:
            raise ValueError(f"robots: {exc}") from None
        if len(set(ids)) != len(ids):
            raise ValueError(f"embodiments listed twice: {ids}")
        return ids

    def all_clips(self) -> list:
        """Explicit clips, then every clip of every source tree, in listing order."""
        return [*self.clips, *(c for tree in self.sources for c in tree.clips())]

    def stage_config(self, stage: str) -> BaseModel:
        return IngestConfig() if stage == "ingest" else getattr(self, stage)

    @classmethod
    def from_yaml(cls, path: str | Path) -> "CurateConfig":
        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError) as exc:
            raise ValueError(f"cannot read curate config {path}: {exc}") from None
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise ValueError(f"{path}: invalid curate config:\n{explain(exc, cls)}") from None
