"""Paper scale by simulation, and a real small sharded run against a bare loop.

    .venv/bin/python bench/scale.py [--clips 338000] [--embodiments 26] [--frames 266]
                                    [--shard-size 64] [--real-shards 4 --real-clips 2 --workers 2] [--no-real]

1. Plans (without running stages) EgoDex-like clips of ``--frames`` frames x ``--embodiments``
   embodiments the way the driver does (``handedit.flows.plan``: groups -> shards, one
   manifest digest each) and prints shards, flow runs, Prefect task runs, Dask tasks,
   store objects, driver peak memory and planning time per clip; next to the round-1 design
   measured on the same input (every 16-frame chunk of every stage a Prefect task; all
   nodes built up front; a root registry of every clip).
2. Runs a real sharded curate (``--real-shards`` shards x ``--real-clips`` synthetic clips)
   on a ``--workers``-worker LocalCluster and the same per-clip and per-embodiment task
   bodies (``handedit.tasks.clip``) in a bare loop of as many processes, and prints both
   throughputs and their ratio (goal >= 0.9).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import tempfile
import time
import tracemalloc
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "error")
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "180")

EGODEX_TASKS = 194


class SimulatedTree:
    """An EgoDex-like tree listed without touching a disk: ``n_clips`` episodes over tasks of
    ``clips_per_task`` (the last one shorter), one group (task) at a time."""

    kind = "simulated"

    def __init__(self, n_clips: int, clips_per_task: int | None = None, frames: int = 266):
        self.n_clips = n_clips
        self.per_task = clips_per_task or math.ceil(n_clips / EGODEX_TASKS)
        self.frames = frames

    def task_sizes(self) -> list[int]:
        full, rest = divmod(self.n_clips, self.per_task)
        return [self.per_task] * full + ([rest] if rest else [])

    def groups(self):
        from handedit.sources.synthetic import SyntheticSpec

        for t, size in enumerate(self.task_sizes()):
            yield f"task{t:03d}", [SyntheticSpec(clip_id=f"egodex-task{t:03d}-{k}", n_frames=self.frames, seed=k)
                                   for k in range(size)]


def store_objects_per_clip(n_embodiments: int, frames: int, frames_per_chunk: int, hands: int = 2) -> int:
    """Files (objects) a clip adds to the store: every array's zarr.json and one object per
    chunk (image arrays: one shard of F frames; small arrays: F frames per chunk), every group's zarr.json."""
    from handedit.storage.layout import stage_arrays

    chunks = math.ceil(frames / frames_per_chunk)

    def unit(stage: str) -> int:
        specs = [a for a in stage_arrays(stage) if a.when in (None, "arm")]
        return 1 + sum(1 + chunks for _ in specs)

    per_clip = sum(unit(s) for s in ("ingest", "registration", "segment")) + 2 * unit("restore_background") + 4
    per_emb = sum(unit(s) for s in ("retarget", "render", "composite", "harmonize", "qc")) + 1
    return per_clip + n_embodiments * per_emb


def simulate_plan(tree: SimulatedTree, n_embodiments: int, shard_size: int, frames: int, frames_per_chunk: int,
                  shards_in_flight: int = 2) -> dict:
    """What the driver does before any work: list, cut shards, digest each (no stage runs)."""
    from handedit.flows.plan import iter_shards

    t0 = time.perf_counter()
    shards = clips = largest = 0
    for shard in iter_shards([tree], [], shard_size):
        shard.digest("run-key")
        shards += 1
        clips += len(shard.specs)
        largest = max(largest, len(shard.specs))
    seconds = time.perf_counter() - t0
    return {"clips": clips, "shards": shards, "flow_runs": shards + 1,
            "prefect_task_runs": clips * (1 + n_embodiments), "dask_tasks": clips * (1 + n_embodiments),
            "store_objects": clips * store_objects_per_clip(n_embodiments, frames, frames_per_chunk) + 5 * shards,
            "planning_ms_per_clip": 1000 * seconds / max(clips, 1), "driver_held_shards": min(shards, shards_in_flight),
            "largest_bookkeeping_file_clips": largest}


def round1(n_clips: int, n_embodiments: int, frames: int, frames_per_chunk: int, sample: int = 20) -> dict:
    """Round 1's design on the same input: build_nodes for every clip up front (timed on a
    sample, extrapolated), one Prefect task per node, a root registry of every clip."""
    from handedit.embodiments.roster import list_embodiments
    from handedit.flows.config import CurateConfig
    from handedit.tasks.clip import WalkConfig, clip_nodes, embodiment_nodes
    from handedit.tasks.plan import ClipPlan
    from handedit.tasks.stage import Robot

    embs = {e.id: e.track for e in list_embodiments()[:n_embodiments]}
    plan = ClipPlan("c", frames, 1080, 1920, {"fx": 1.0}, "{}", "fp", False, False, hands=("left", "right"))
    cfg = WalkConfig.from_json(CurateConfig(out="x", frames_per_chunk=frames_per_chunk,
                                            restore_background={"window": 12}).model_dump_json())
    t0 = time.perf_counter()
    for _ in range(sample):
        nodes = clip_nodes(plan, embs.values(), cfg)
        for emb, track in embs.items():
            nodes += embodiment_nodes(plan, Robot(emb, track), cfg)
    per_clip = (time.perf_counter() - t0) / sample
    registry_entry = len(json.dumps({"egodex-task000-1234": {"source": {"kind": "egodex", "root": "/data/egodex",
                                     "task": "task000", "episode": "1234"}, "n_frames": frames, "fingerprint": "f" * 64}}))
    return {"prefect_task_runs": n_clips * len(nodes), "planning_ms_per_clip": 1000 * per_clip,
            "largest_file_bytes": n_clips * registry_entry, "nodes_per_clip": len(nodes)}


# ----------------------------------------------------------------------------- the real run


def _bare_worker(jobs: list) -> float:
    from handedit.tasks.clip import run_clip, run_embodiment

    t0 = time.perf_counter()
    for clip_job, emb_jobs in jobs:
        run_clip(clip_job)
        for j in emb_jobs:
            run_embodiment(j)
    return time.perf_counter() - t0


def real_run(n_shards: int, per_shard: int, workers: int, frames: int, size: tuple[int, int], emb: str) -> dict:
    import multiprocessing as mp
    from dataclasses import asdict

    from distributed import LocalCluster
    from prefect.testing.utilities import prefect_test_harness

    from handedit.flows.config import ClusterConfig, CurateConfig
    from handedit.flows.curate import code_version, plan_embodiments, run_curate
    from handedit.sources.synthetic import make_clip_specs
    from handedit.storage import Location, create_or_open_store
    from handedit.tasks.clip import ClipJob, EmbodimentJob

    tmp = Path(tempfile.mkdtemp(prefix="handedit-scale-"))
    os.environ.setdefault("PREFECT_HOME", str(tmp / "prefect"))
    specs = make_clip_specs(n_shards * per_shard, n_frames=frames, width=size[0], height=size[1])
    n_frames = len(specs) * frames

    def config(name: str, cluster=ClusterConfig()) -> CurateConfig:
        return CurateConfig(out=str(tmp / name), clips=specs, embodiments=[emb], shard_size=per_shard,
                            shards_in_flight=workers + 1, cluster=cluster)

    # bare loop: the same task bodies, clips dealt round-robin to as many processes as workers
    cfg = config("bare")
    loc = Location(cfg.out)
    create_or_open_store(loc, cfg.frames_per_chunk, "bench")
    embs = [asdict(e) for e in plan_embodiments(cfg.embodiments)]
    scopes = tuple(sorted({e["scope"] for e in embs}))
    jobs = [(ClipJob(loc.store_url, s.model_dump_json(), cfg.model_dump_json(), scopes, code_version()),
             [EmbodimentJob(loc.store_url, s.id, e, cfg.model_dump_json(), code_version()) for e in embs]) for s in specs]
    t0 = time.perf_counter()
    with mp.get_context("spawn").Pool(workers) as pool:
        pool.map(_bare_worker, [jobs[i::workers] for i in range(workers)])
    bare_s = time.perf_counter() - t0

    t0 = time.perf_counter()
    with prefect_test_harness(server_startup_timeout=180):
        server_s = time.perf_counter() - t0
        t1 = time.perf_counter()
        import dask

        from handedit.flows.config import LOCAL_WORKER_CONFIG

        with dask.config.set(LOCAL_WORKER_CONFIG), \
                LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                             dashboard_address="127.0.0.1:0") as cluster:
            cluster_s = time.perf_counter() - t1
            t2 = time.perf_counter()
            summary = run_curate(config("flow", ClusterConfig(address=cluster.scheduler_address)))
            flow_s = time.perf_counter() - t2
    work = {name: _chunk_seconds(tmp / name) for name in ("bare", "flow")}
    shutil.rmtree(tmp, ignore_errors=True)
    return {"frames": n_frames, "bare_s": bare_s, "flow_s": flow_s, "server_s": server_s, "cluster_s": cluster_s,
            "shards": summary["shards"], "workers": workers, "work": work}


def _chunk_seconds(out: Path) -> float:
    """Sum of the chunk bodies' own wall time in a store (provenance ``seconds``)."""
    from handedit.storage import open_store
    from handedit.storage.ledger import iter_units
    from handedit.storage.provenance import read_records

    root = open_store(str(out))
    return sum(r.seconds for u in iter_units(root) for r in read_records(root, u).values())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clips", type=int, default=338_000)
    ap.add_argument("--embodiments", type=int, default=26)
    ap.add_argument("--frames", type=int, default=266)
    ap.add_argument("--frames-per-chunk", type=int, default=16)
    ap.add_argument("--shard-size", type=int, default=64)
    ap.add_argument("--real-shards", type=int, default=4)
    ap.add_argument("--real-clips", type=int, default=2, help="clips per shard in the real run")
    ap.add_argument("--real-frames", type=int, default=48)
    ap.add_argument("--real-size", default="640x480")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--no-real", action="store_true")
    args = ap.parse_args()

    tracemalloc.start()
    tree = SimulatedTree(args.clips, frames=args.frames)
    new = simulate_plan(tree, args.embodiments, args.shard_size, args.frames, args.frames_per_chunk)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    old = round1(args.clips, args.embodiments, args.frames, args.frames_per_chunk)
    c = new["clips"]
    print(f"simulated: {c:,} EgoDex-like clips of {args.frames} frames x {args.embodiments} embodiments, "
          f"{len(tree.task_sizes())} tasks, shards of {args.shard_size}")
    print(f"{'':32}{'this design':>18}{'round 1':>18}")
    print(f"{'shards (flow runs)':32}{new['shards']:>18,}{1:>18,}")
    print(f"{'Prefect task runs':32}{new['prefect_task_runs']:>18,}{old['prefect_task_runs']:>18,}")
    print(f"{'Prefect task runs per clip':32}{new['prefect_task_runs'] / c:>18.1f}{old['nodes_per_clip']:>18.1f}"
          f"   (goal <= 27)")
    print(f"{'Dask tasks':32}{new['dask_tasks']:>18,}{old['prefect_task_runs']:>18,}")
    print(f"{'store objects':32}{new['store_objects']:>18,}")
    print(f"{'planning ms per clip':32}{new['planning_ms_per_clip']:>18.3f}{old['planning_ms_per_clip']:>18.1f}   (goal <= 1)")
    print(f"{'driver peak memory (planning)':32}{peak / 2**20:>15.1f} MB{'':>18}   (goal <= 1 GB)")
    print(f"{'largest bookkeeping file':32}{new['largest_bookkeeping_file_clips']:>12} clips"
          f"{old['largest_file_bytes'] / 2**20:>15.1f} MB  (round 1: the root registry, grows with every clip)")
    if args.no_real:
        return
    size = tuple(int(v) for v in args.real_size.split("x"))
    r = real_run(args.real_shards, args.real_clips, args.workers, args.real_frames, size, "allegro")
    n = r["frames"]
    print(f"\nreal: {args.real_shards} shards x {args.real_clips} synthetic clips x {args.real_frames} frames at {args.real_size}, "
          f"allegro, {r['workers']} processes each side")
    print(f"bare loop ({r['workers']} processes):   {r['bare_s']:7.1f} s  {n / r['bare_s']:6.2f} frames/s")
    print(f"sharded flow ({r['workers']} workers): {r['flow_s']:7.1f} s  {n / r['flow_s']:6.2f} frames/s  shards {r['shards']}")
    print(f"  not counted: Prefect server start {r['server_s']:.1f} s, Dask cluster start {r['cluster_s']:.1f} s")
    print(f"  chunk bodies' own time: bare {r['work']['bare']:.1f} s, flow {r['work']['flow']:.1f} s "
          f"(the rest of the flow's wall time is orchestration and idle workers)")
    print(f"parallel efficiency flow/bare: {r['bare_s'] / r['flow_s']:.2f}  (goal >= 0.9)")


if __name__ == "__main__":
    main()
