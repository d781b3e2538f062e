"""A run's outcome: failed chunks or a kept share at or below ``fail_below_kept`` fail the
run (exit status 1, Prefect state Failed, the reasons in the message); partial success passes."""

from __future__ import annotations

import asyncio

import pytest

from handedit.flows.cli import main
from handedit.flows.curate import outcome


def _summary(ok: int, other: int, failed: int = 0) -> dict:
    return {"status": [{"stage": "qc", "status": "OK", "frames": ok}, {"stage": "qc", "status": "UPSTREAM", "frames": other},
                       {"stage": "segment", "status": "OK", "frames": ok + other}],
            "stages": {"retarget": {"ran": 2, "skipped": 0, "failed": failed}}, "shards": {"incomplete": 0}}


def test_outcome_rules():
    assert outcome(_summary(3, 13), 0.0) == {"failed": False, "reasons": [], "kept": 3, "pairs": 16, "kept_share": 0.1875}
    nothing = outcome(_summary(0, 16), 0.0)
    assert nothing["failed"] and "kept 0 of 16" in nothing["reasons"][0]
    floor = outcome(_summary(3, 13), 0.25)
    assert floor["failed"] and "at or below fail_below_kept 25.0%" in floor["reasons"][0]
    broken = outcome(_summary(16, 0, failed=1), 0.0)
    assert broken["failed"] and broken["reasons"] == ["1 chunk(s) failed after their retries (see the errors above; re-run "
                                                      "to retry them)"]


def test_a_run_that_keeps_nothing_fails_in_prefect_and_exits_1(tmp_path, capsys, prefect_api, dask_cluster, monkeypatch):
    """The operator's case: an embodiment whose assets are missing rejects every frame; the run
    exits 1 and its Prefect flow run is Failed, with the reasons in its message."""
    from prefect.client.orchestration import get_client

    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(tmp_path / "no-robots"))
    monkeypatch.setenv("HANDEDIT_CACHE_DIR", str(tmp_path / "cache"))
    code = main(["curate", "--demo", "--out", str(tmp_path / "run"), "--clips", "1", "--frames", "8", "--width", "160",
                 "--height", "120", "--frames-per-chunk", "8", "--embodiment", "rh5dg2",
                 "--address", dask_cluster.scheduler_address, "--no-progress"])
    captured = capsys.readouterr()
    assert code == 1 and "the run failed" in captured.err and "kept 0 of 8" in captured.err
    run_id = next(line.split("/flow-run/")[1].split()[0] for line in captured.out.splitlines() if "/flow-run/" in line)

    async def state():
        from prefect.client.schemas.filters import (ArtifactFilter, ArtifactFilterFlowRunId, ArtifactFilterKey,
                                                    FlowRunFilter, FlowRunFilterParentFlowRunId)

        async with get_client() as client:
            run = await client.read_flow_run(run_id)
            arts = await client.read_artifacts(artifact_filter=ArtifactFilter(flow_run_id=ArtifactFilterFlowRunId(any_=[run.id])))
            # this run's shard flow runs only: other tests on the same server publish the same key
            shards = await client.read_flow_runs(flow_run_filter=FlowRunFilter(
                parent_flow_run_id=FlowRunFilterParentFlowRunId(any_=[run.id])))
            shard = await client.read_artifacts(artifact_filter=ArtifactFilter(
                key=ArtifactFilterKey(any_=["shard-clips-00000"]),
                flow_run_id=ArtifactFilterFlowRunId(any_=[r.id for r in shards])))
            return run.state, {a.key: a for a in arts}, shard

    st, arts, shard = asyncio.run(state())
    # each shard's flow run publishes its chunks per stage
    assert len(shard) == 1 and "retarget" in str(shard[0].data) and "chunks ran/skipped/failed" in shard[0].description
    assert st.is_failed() and "kept 0 of 8" in st.message
    # the outcome in the flow run's Artifacts: frames and rejections per stage, the verdict with the store
    assert {"curate-frames", "curate-rejections", "curate-outcome", "curate-progress"} <= set(arts)
    assert arts["curate-progress"].data == 100.0  # every planned pair was made (and rejected)
    assert "ASSETS_MISSING" in str(arts["curate-rejections"].data) and "Failed" in str(arts["curate-outcome"].data)
    assert str(tmp_path / "run") in str(arts["curate-outcome"].data)


@pytest.mark.parametrize("floor, code", [(0.0, 0), (1.0, 1)])
def test_partial_success_and_a_floor(tmp_path, capsys, prefect_api, dask_cluster, floor, code):
    rc = main(["curate", "--demo", "--out", str(tmp_path / "run"), "--clips", "1", "--frames", "8", "--width", "160",
               "--height", "120", "--frames-per-chunk", "8", "--fail-below-kept", str(floor),
               "--address", dask_cluster.scheduler_address, "--no-progress"])
    assert rc == code, capsys.readouterr().err
