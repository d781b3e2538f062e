"""Flow vs bare loop: frames/s of the curate flow against the same stage functions in a loop.

    .venv/bin/python bench/curate_overhead.py [--clips 2 --frames 48 --workers 2]

Both sides run the same chunk nodes (flows.dag) through the same stage bodies
(tasks.STAGE_BODIES: read inputs, call handedit, write the chunk) on the same clips,
each into its own fresh store. The bare loop runs them in order in this process; the
flow runs them as Prefect tasks on a Dask LocalCluster started beforehand (its start-up
and the Prefect server's are printed separately, not counted). Both pay their own
per-process warm-up (renderer, solver, source). The printed ratio is flow/bare frames/s.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "error")
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "180")


def bare_loop(config) -> float:
    """Every node in DAG order, in this process, no orchestration. Returns seconds."""
    from handedit.flows.curate import plan_clips, plan_embodiments, stage_version_params, _create_units
    from handedit.flows.dag import build_nodes
    from handedit.storage import create_or_open_store
    from handedit.tasks import STAGE_BODIES
    from handedit.tasks.common import ChunkJob, execute

    t0 = time.perf_counter()
    root = create_or_open_store(config.out, config.frames_per_chunk, "bench")
    clips, _ = plan_clips(config)
    embs = plan_embodiments(config.embodiments)
    for clip in clips:
        _create_units(root, config, clip, embs)
        scopes = {e.id: e.scope for e in embs}
        for node in build_nodes(clip, scopes, config.frames_per_chunk, config.restore_background.window):
            version, params = stage_version_params(config, node.unit.stage)
            job = ChunkJob(str(config.out), node.unit, node.chunk, node.start, node.stop, "bare", version,
                           params, {}, "bench", node.context)
            execute(job, STAGE_BODIES[node.unit.stage])
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clips", type=int, default=2)
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--frames-per-chunk", type=int, default=16)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--embodiment", default="allegro")
    args = ap.parse_args()

    from distributed import LocalCluster
    from prefect.testing.utilities import prefect_test_harness

    from handedit.flows.config import ClusterConfig, CurateConfig
    from handedit.flows.curate import run_curate
    from handedit.sources.synthetic import make_clip_specs

    tmp = Path(tempfile.mkdtemp(prefix="handedit-bench-"))
    os.environ.setdefault("PREFECT_HOME", str(tmp / "prefect"))
    specs = make_clip_specs(args.clips, n_frames=args.frames, width=args.width, height=args.height)
    n_frames = args.clips * args.frames

    def cfg(name: str, cluster: ClusterConfig) -> CurateConfig:
        return CurateConfig(out=tmp / name / "handedit.zarr", clips=specs, embodiments=[args.embodiment],
                            frames_per_chunk=args.frames_per_chunk, cluster=cluster)

    bare_s = bare_loop(cfg("bare", ClusterConfig()))

    t0 = time.perf_counter()
    with prefect_test_harness(server_startup_timeout=120):
        server_s = time.perf_counter() - t0
        t1 = time.perf_counter()
        with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                          dashboard_address="127.0.0.1:0") as cluster:
            cluster_s = time.perf_counter() - t1
            t2 = time.perf_counter()
            summary = run_curate(cfg("flow", ClusterConfig(address=cluster.scheduler_address)))
            flow_s = time.perf_counter() - t2
    shutil.rmtree(tmp, ignore_errors=True)

    chunks = sum(c["ran"] for c in summary["stages"].values())
    print(f"clips x frames: {args.clips} x {args.frames} at {args.width}x{args.height}, "
          f"{args.frames_per_chunk} frames/chunk, {chunks} chunk tasks, embodiment {args.embodiment}")
    print(f"bare loop (1 process):      {bare_s:7.1f} s  {n_frames / bare_s:6.2f} frames/s")
    print(f"flow ({args.workers} Dask workers):       {flow_s:7.1f} s  {n_frames / flow_s:6.2f} frames/s")
    print(f"  not counted: Prefect server start {server_s:.1f} s, Dask cluster start {cluster_s:.1f} s")
    print(f"ratio flow/bare frames/s:   {bare_s / flow_s:.2f}  (goal >= 0.9)")


if __name__ == "__main__":
    main()
