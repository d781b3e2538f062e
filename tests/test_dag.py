"""The chunk DAG and the driver's scheduler, without Prefect or Dask."""

from __future__ import annotations

from handedit.flows.dag import ClipPlan, build_nodes
from handedit.flows.scheduler import run_dag
from handedit.storage import Unit

CLIP = ClipPlan("c", n_frames=20, height=4, width=4, intrinsics={"fx": 1}, source_json="{}", fingerprint="fp",
                has_object=True, has_gt=False)


class Done:
    """A handle that is already finished (the scheduler only needs add_done_callback)."""

    def __init__(self, value):
        self.value = value

    def add_done_callback(self, fn):
        fn(self)


def test_nodes_and_dependencies():
    nodes = build_nodes(CLIP, {"allegro": "hand", "ur5e_shadow": "hand_arm"}, frames_per_chunk=8, restore_window=3)
    by_id = {n.id: n for n in nodes}
    # 3 chunks x (ingest, registration, segment, 2 scopes, 5 hand stages, 4 hand-arm stages) + 1 sequence-level retarget
    assert len(nodes) == 3 * (3 + 2 + 5 + 4) + 1
    seq = by_id[(Unit("retarget", "c", embodiment="ur5e_shadow"), 0)]
    assert (seq.start, seq.stop) == (0, 20) and {d.chunk for d in seq.deps} == {0, 1, 2}
    assert (Unit("retarget", "c", embodiment="ur5e_shadow"), 1) not in by_id
    render = by_id[(Unit("render", "c", embodiment="ur5e_shadow"), 2)]
    assert [(d.unit.stage, d.chunk) for d in render.deps] == [("retarget", 0)]
    assert {(d.unit.stage, d.chunk) for d in seq.deps} == {(s, k) for s in ("ingest", "registration", "segment") for k in (0, 1, 2)}
    restore = by_id[(Unit("restore_background", "c", scope="hand"), 1)]
    assert restore.context["window"] == [5, 19]
    assert {(d.unit.stage, d.chunk) for d in restore.deps} == {(s, k) for s in ("ingest", "segment") for k in (0, 1, 2)}
    comp = by_id[(Unit("composite", "c", embodiment="ur5e_shadow"), 2)]
    assert {d.unit for d in comp.deps} >= {Unit("restore_background", "c", scope="hand_arm"), Unit("ingest", "c")}
    assert (comp.start, comp.stop) == (16, 20)
    qc = by_id[(Unit("qc", "c", embodiment="allegro"), 0)]
    assert len(qc.deps) == 8 and all(d.arrays[0] == "status" for d in qc.deps)
    assert {d.unit.stage for d in qc.deps if "hand_status" in d.arrays} == {"registration", "segment", "retarget", "render",
                                                                             "composite"}


def run(nodes, stored, params=None, fail=(), prefail_stage=None):
    params = params or {}
    order, written = [], {}

    def submit(prep):
        order.append(prep.node.id)
        failed = prep.node.unit.stage in fail
        return Done(({"key": prep.key, "outcome": "error" if failed else "ok",
                      "outputs": {"status": f"s-{prep.node.unit.stage}-{prep.node.chunk}-{'x' if failed else 'ok'}"}}, failed))

    def prefail(prep):
        if prep.node.unit.stage == prefail_stage:
            return {"key": prep.key, "outcome": "error", "outputs": {"status": "missing"}}
        return None

    result = run_dag(nodes, lambda s: (1, params.get(s, {})), lambda nid: stored.get(nid), submit,
                     lambda prep, h: h.value, prefail, lambda n, r: written.__setitem__(n.id, r))
    return result, order, written


def test_scheduler_runs_in_dependency_order_then_skips_current_chunks():
    nodes = build_nodes(CLIP, {"allegro": "hand"}, 8, 3)
    result, order, written = run(nodes, {})
    assert len(order) == len(nodes) and set(written) == {n.id for n in nodes}
    pos = {nid: i for i, nid in enumerate(order)}
    for n in nodes:
        for d in n.deps:
            assert pos[(d.unit, d.chunk)] < pos[n.id]
    # same inputs and params: nothing runs
    _, again, _ = run(nodes, written)
    assert again == []
    # new harmonize params: only harmonize runs (qc reads status digests, unchanged here)
    _, changed, _ = run(nodes, written, params={"harmonize": {"strength": 0.9}})
    assert {nid[0].stage for nid in changed} == {"harmonize"} and len(changed) == 3
    # an error record is never current: it runs again
    stored = dict(written)
    key = (Unit("segment", "c"), 1)
    stored[key] = {**stored[key], "outcome": "error"}
    _, retried, _ = run(nodes, stored)
    assert retried[0] == key


def test_failures_are_counted_and_do_not_stop_the_dag():
    nodes = build_nodes(CLIP, {"allegro": "hand"}, 8, 3)
    result, order, written = run(nodes, {}, fail=("segment",), prefail_stage="retarget")
    assert result.counts["segment"].failed == 3 and result.counts["retarget"].failed == 3
    assert result.counts["qc"].ran == 3  # downstream still ran (and sees non-OK status)
    assert not any(nid[0].stage == "retarget" for nid in order)  # prefailed: never submitted
    assert len(written) == len(nodes)


class Never:
    """A handle whose task never finishes (a cluster that lost its workers)."""

    def add_done_callback(self, fn):
        pass


def test_idle_driver_asks_the_watchdog_and_can_abort():
    nodes = build_nodes(CLIP, {"allegro": "hand"}, 8, 3)
    calls = []

    def on_idle(idle_s):
        calls.append(idle_s)
        if len(calls) == 3:
            raise RuntimeError("no worker")

    try:
        run_dag(nodes, lambda s: (1, {}), lambda nid: None, lambda prep: Never(), lambda p, h: ({}, False),
                lambda prep: None, lambda n, r: None, on_idle=on_idle, poll_s=0.01)
    except RuntimeError as exc:
        assert "no worker" in str(exc)
    else:
        raise AssertionError("the driver kept waiting")
    assert calls == sorted(calls) and len(calls) == 3
