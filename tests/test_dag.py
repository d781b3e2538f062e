"""The chunk DAG of one clip and the walk a task makes over it, without Prefect or a store."""

from __future__ import annotations

from handedit.flows.dag import ClipPlan, build_nodes, clip_nodes, embodiment_nodes
from handedit.storage import Unit
from handedit.tasks.clip import CLIP_STAGES, EMBODIMENT_STAGES, WalkResult, _order, walk

CLIP = ClipPlan("c", n_frames=20, height=4, width=4, intrinsics={"fx": 1}, source_json="{}", fingerprint="fp",
                has_object=True, has_gt=False)


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
    # what the two tasks of a clip walk: clip stages, and one embodiment's
    assert {n.unit.stage for n in clip_nodes(CLIP, ["hand"], 8, 3)} == set(CLIP_STAGES) - {"estimate_hands"}
    assert {n.unit.stage for n in embodiment_nodes(CLIP, "allegro", "hand", 8)} == set(EMBODIMENT_STAGES)


def test_estimated_hands_are_one_node_per_clip_that_registration_reads():
    from dataclasses import replace

    clip = replace(CLIP, estimate_hands=True, has_object=False, hands=("left", "right"))
    nodes = clip_nodes(clip, ["hand"], 8, 3)
    by_id = {n.id: n for n in nodes}
    est = [n for n in nodes if n.unit.stage == "estimate_hands"]
    assert len(est) == 1 and (est[0].start, est[0].stop) == (0, 20)
    assert {(d.unit.stage, d.chunk) for d in est[0].deps} == {("ingest", k) for k in (0, 1, 2)}
    reg = by_id[(Unit("registration", "c"), 2)]
    assert [(d.unit.stage, d.chunk) for d in reg.deps] == [("ingest", 2), ("estimate_hands", 0)]
    assert "keypoints" not in reg.deps[0].arrays and "keypoints" in reg.deps[1].arrays  # the estimate's, not the source's
    assert reg.context["estimated"] is True
    order = [(n.unit.stage, n.chunk) for n in _order(nodes)]
    assert order.index(("estimate_hands", 0)) > order.index(("ingest", 2))
    assert order.index(("estimate_hands", 0)) < order.index(("registration", 0))


def test_walk_streams_chunks_in_dependency_order():
    nodes = clip_nodes(CLIP, ["hand"], 8, 3)
    order = [(n.unit.stage, n.chunk) for n in _order(nodes)]
    pos = {nid: i for i, nid in enumerate(order)}
    for n in nodes:
        for d in n.deps:
            assert pos[(d.unit.stage, d.chunk)] < pos[(n.unit.stage, n.chunk)]
    # streaming: chunk 0 is restored before chunk 2 is even ingested (it needs chunks 0-1 only)
    assert pos[("restore_background", 0)] < pos[("ingest", 2)]


def run(nodes, records, params=None, fail=(), prefail_stage=None):
    params = params or {}
    ran, written = [], {}

    def run_node(node, key, inputs, version, p, fault):
        ran.append(node.id)
        failed = node.unit.stage in fail
        return {"key": key, "outcome": "error" if failed else "ok", "error": "boom" if failed else None,
                "outputs": {"status": f"s-{node.unit.stage}-{node.chunk}-{'x' if failed else 'ok'}"}}

    def prefail(node, key, inputs, version, p):
        if node.unit.stage == prefail_stage:
            return {"key": key, "outcome": "error", "outputs": {"status": "missing"}}
        return None

    result = walk(nodes, lambda s: (1, params.get(s, {})), records, run_node, lambda n, r: written.__setitem__(n.id, r),
                  WalkResult("c"), prefail=prefail)
    return result, ran, written


def test_walk_skips_current_chunks_and_reruns_what_changed():
    nodes = build_nodes(CLIP, {"allegro": "hand"}, 8, 3)
    result, ran, written = run(nodes, {})
    assert len(ran) == len(nodes) and set(written) == {n.id for n in nodes}
    # same inputs and params: nothing runs
    _, again, _ = run(nodes, dict(written))
    assert again == []
    # new harmonize params: only harmonize runs (qc reads status digests, unchanged here)
    _, changed, _ = run(nodes, dict(written), params={"harmonize": {"strength": 0.9}})
    assert {nid[0].stage for nid in changed} == {"harmonize"} and len(changed) == 3
    # an error record is never current: it runs again
    stored = dict(written)
    key = (Unit("segment", "c"), 1)
    stored[key] = {**stored[key], "outcome": "error"}
    _, retried, _ = run(nodes, stored)
    assert retried[0] == key


def test_failures_are_counted_and_do_not_stop_the_walk():
    nodes = build_nodes(CLIP, {"allegro": "hand"}, 8, 3)
    result, ran, written = run(nodes, {}, fail=("segment",), prefail_stage="retarget")
    assert result.stages["segment"]["failed"] == 3 and result.stages["retarget"]["failed"] == 3
    assert result.stages["qc"]["ran"] == 3  # downstream still ran (and sees non-OK status)
    assert not any(nid[0].stage == "retarget" for nid in ran)  # prefailed: never run
    assert len(written) == len(nodes)
    assert len(result.errors) == 3  # the segment failures, to retry; prefailed chunks are the plan's own
