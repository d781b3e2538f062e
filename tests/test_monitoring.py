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
    # an existing cluster's dashboard outlives the command; the test session's Prefect server too
    assert summary["links"]["Dask dashboard"] == {"url": summary["dashboard"], "note": ""}
    assert summary["links"]["Prefect run"]["note"] == ""
    from handedit.storage import Location
    from handedit.storage.shards import run_logs, shard_ids

    loc = Location(tmp_path / "run")
    assert run_logs(loc, shard_ids(loc)[0])[-1]["links"] == summary["links"]  # the run log keeps them

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


def test_a_local_cluster_and_a_temporary_api_are_labelled_as_gone_with_the_command():
    from unittest import mock

    from handedit.flows.curate import run_links

    with mock.patch("handedit.flows.api._TEMPORARY", ["http://127.0.0.1:1/api"]):
        links = run_links("http://127.0.0.1:8787/status", "http://127.0.0.1:1/runs/flow-run/x", local_cluster=True)
    assert "gone when this command exits" in links["Dask dashboard"]["note"]
    assert "temporary Prefect API" in links["Prefect run"]["note"]
    assert run_links("http://d/status", "http://p/x", local_cluster=False) == {
        "Dask dashboard": {"url": "http://d/status", "note": ""}, "Prefect run": {"url": "http://p/x", "note": ""}}
