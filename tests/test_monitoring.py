"""What an operator watches: Dask spans per embodiment with time per stage, and the run's
dashboard and Prefect links in its summary."""

from __future__ import annotations

from distributed import Client

from handedit.flows.config import ClusterConfig, CurateConfig
from handedit.flows.curate import run_curate
from handedit.sources.synthetic import make_clip_specs


def test_spans_per_embodiment_with_time_per_stage(tmp_path, prefect_api, dask_cluster):
    summary = run_curate(CurateConfig(out=str(tmp_path / "run"), clips=make_clip_specs(1, seed=8, n_frames=8, width=96,
                                                                                        height=72),
                                      embodiments=["allegro"], frames_per_chunk=8,
                                      cluster=ClusterConfig(address=dask_cluster.scheduler_address)))
    assert summary["dashboard"].startswith("http://127.0.0.1") and "/flow-run/" in (summary["prefect_run"] or "")

    def spans(dask_scheduler):
        out = {}
        for s in dask_scheduler.extensions["spans"].spans.values():
            labels = {k[2] for k in s.cumulative_worker_metrics if len(k) > 2}
            out.setdefault(tuple(s.name), set()).update(labels)
        return out

    with Client(dask_cluster.scheduler_address) as client:
        found = client.run_on_scheduler(spans)
    assert {"ingest", "registration", "segment", "restore_background"} <= found[("curate", "clip")]
    assert {"retarget", "render", "composite", "harmonize", "qc"} <= found[("curate", "allegro")]
