"""The chunk DAG of one clip, from the stages' declarations, and the walk a task makes over
it, without Prefect or a store."""

from __future__ import annotations

import pytest

from handedit.flows.config import CurateConfig
from handedit.storage import Unit
from handedit.tasks.clip import (CLIP_STAGES, EMBODIMENT_STAGES, WalkConfig, WalkResult, _order, clip_nodes,
                                 embodiment_nodes, walk)
from handedit.tasks.plan import ClipPlan
from handedit.tasks.stage import Arrays, Inputs, Robot, UndeclaredRead, Value, config_versions

CLIP = ClipPlan("c", n_frames=20, height=4, width=4, intrinsics={"fx": 1}, source_json="{}", fingerprint="fp",
                has_object=True, has_gt=False)


def config(frames_per_chunk: int = 8, window: int = 3, clip_sources: int = 8) -> WalkConfig:
    cfg = CurateConfig(out="x", frames_per_chunk=frames_per_chunk,
                       restore_background={"window": window, "clip_sources": clip_sources})
    return WalkConfig.from_json(cfg.model_dump_json())


def build_nodes(clip: ClipPlan, embodiments: dict[str, str], frames_per_chunk: int = 8, window: int = 3) -> list:
    cfg = config(frames_per_chunk, window)
    out = clip_nodes(clip, embodiments.values(), cfg)
    for emb, track in embodiments.items():
        out += embodiment_nodes(clip, Robot(emb, track, f"robot-{emb}"), cfg)
    return out


def test_nodes_and_dependencies():
    nodes = build_nodes(CLIP, {"allegro": "hand", "ur5e_shadow": "hand_arm"}, frames_per_chunk=8, window=3)
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
    assert {(d.unit.stage, d.chunk) for d in restore.deps} == {(s, k) for s in ("ingest", "segment") for k in (0, 1, 2)}
    comp = by_id[(Unit("composite", "c", embodiment="ur5e_shadow"), 2)]
    assert {d.unit for d in comp.deps} >= {Unit("restore_background", "c", scope="hand_arm"), Unit("ingest", "c")}
    assert (comp.start, comp.stop) == (16, 20)
    qc = by_id[(Unit("qc", "c", embodiment="allegro"), 0)]
    assert len(qc.deps) == 8 and all(d.arrays[0] == "status" for d in qc.deps)
    # every node declares the clip's facts and its config's versions; the robot's content, the stages that load it
    assert all({"clip", "versions"} <= {i.name for i in n.inputs if isinstance(i, Value)} for n in nodes)
    assert {n.unit.stage for n in nodes if Value("robot", "robot-allegro") in n.inputs} == {"retarget", "render"}
    assert {d.unit.stage for d in qc.deps if "hand_status" in d.arrays} == {"registration", "segment", "retarget", "render",
                                                                             "composite"}
    # what the two tasks of a clip walk: clip stages, and one embodiment's
    assert {n.unit.stage for n in clip_nodes(CLIP, ["hand"], config())} == set(CLIP_STAGES) - {"estimate_hands"}
    assert {n.unit.stage for n in embodiment_nodes(CLIP, Robot("allegro", "hand"), config())} == set(EMBODIMENT_STAGES)


def test_estimated_hands_are_one_node_per_clip_that_registration_reads():
    from dataclasses import replace

    clip = replace(CLIP, estimate_hands=True, has_object=False, hands=("left", "right"))
    nodes = clip_nodes(clip, ["hand"], config())
    by_id = {n.id: n for n in nodes}
    est = [n for n in nodes if n.unit.stage == "estimate_hands"]
    assert len(est) == 1 and (est[0].start, est[0].stop) == (0, 20)
    assert {(d.unit.stage, d.chunk) for d in est[0].deps} == {("ingest", k) for k in (0, 1, 2)}
    reg = by_id[(Unit("registration", "c"), 2)]
    assert [(d.unit.stage, d.chunk) for d in reg.deps] == [("ingest", 2), ("estimate_hands", 0)]
    assert "keypoints" not in reg.deps[0].arrays and "keypoints" in reg.deps[1].arrays  # the estimate's, not the source's
    order = [(n.unit.stage, n.chunk) for n in _order(nodes)]
    assert order.index(("estimate_hands", 0)) > order.index(("ingest", 2))
    assert order.index(("estimate_hands", 0)) < order.index(("registration", 0))


def test_walk_streams_chunks_in_dependency_order():
    for sources in (0, 8):
        nodes = clip_nodes(CLIP, ["hand"], config(clip_sources=sources))
        order = [(n.unit.stage, n.chunk) for n in _order(nodes)]
        pos = {nid: i for i, nid in enumerate(order)}
        for n in nodes:
            for d in n.deps:
                assert pos[(d.unit.stage, d.chunk)] < pos[(n.unit.stage, n.chunk)]
    # streaming: chunk 0 is restored before chunk 2 is even ingested (it needs chunks 0-1 only), unless it
    # takes what its window never saw from the rest of the clip (frames 14-19, more than twice the window away)
    assert pos[("restore_background", 0)] > pos[("segment", 2)]
    nodes = clip_nodes(CLIP, ["hand"], config(clip_sources=0))
    pos = {nid: i for i, nid in enumerate((n.unit.stage, n.chunk) for n in _order(nodes))}
    assert pos[("restore_background", 0)] < pos[("ingest", 2)]


def run(nodes, records, params=None, fail=(), prefail_stage=None):
    params = params or {}
    ran, written = [], {}

    def run_node(node, key, inputs, version, p, fault):
        ran.append(node.id)
        failed = node.unit.stage in fail
        return {"key": key, "outcome": "error" if failed else "ok", "error": "boom" if failed else None, "inputs": inputs,
                "outputs": {"status": f"s-{node.unit.stage}-{node.chunk}-{'x' if failed else 'ok'}"}}

    def prefail(node, key, inputs, version, p):
        if node.unit.stage == prefail_stage:
            return {"key": key, "outcome": "error", "outputs": {"status": "missing"}, "inputs": inputs}
        return None

    def record(node, r):
        written[node.id] = {**r, "version": 1, "params": params.get(node.unit.stage, {}), "inputs": r["inputs"]}

    result = walk(nodes, lambda s: (1, params.get(s, {})), records, run_node, record, WalkResult("c"), prefail=prefail)
    return result, ran, written


def test_walk_skips_current_chunks_and_reruns_what_changed():
    nodes = build_nodes(CLIP, {"allegro": "hand"}, 8, 3)
    result, ran, written = run(nodes, {})
    assert len(ran) == len(nodes) and set(written) == {n.id for n in nodes} and not result.recomputed
    # same inputs and params: nothing runs
    _, again, _ = run(nodes, dict(written))
    assert again == []
    # new harmonize params: only harmonize runs (qc reads status digests, unchanged here)
    result, changed, _ = run(nodes, dict(written), params={"harmonize": {"strength": 0.9}})
    assert {nid[0].stage for nid in changed} == {"harmonize"} and len(changed) == 3
    assert result.recomputed == {"harmonize[allegro]: parameters strength": 3}  # the summary says why
    # the robot's content changed (a mesh edited in place): the stages that load it, and only those
    moved = build_nodes(CLIP, {"allegro": "hand"}, 8, 3)
    for n in moved:
        n.inputs = [Value("robot", "new") if i == Value("robot", "robot-allegro") else i for i in n.inputs]
    result, changed, _ = run(moved, dict(written))
    assert {nid[0].stage for nid in changed} == {"retarget", "render"}
    assert set(result.recomputed) == {"retarget[allegro]: robot URDF or meshes changed",
                                      "render[allegro]: robot URDF or meshes changed"}
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


def test_a_nested_config_version_is_in_every_key_that_runs_it():
    from handedit.retarget.config import VirtualBaseConfig

    cfg = config()
    before = config_versions(cfg.stages["retarget"])
    assert before["VirtualBaseConfig"] == VirtualBaseConfig.VERSION and "RetargetConfig" in before
    nodes = build_nodes(CLIP, {"ur5e_shadow": "hand_arm"})
    _, _, written = run(nodes, {})
    old = VirtualBaseConfig.VERSION
    try:
        VirtualBaseConfig.VERSION = old + 1
        result, changed, _ = run(build_nodes(CLIP, {"ur5e_shadow": "hand_arm"}), dict(written))
    finally:
        VirtualBaseConfig.VERSION = old
    assert {nid[0].stage for nid in changed} == {"retarget"}
    assert result.recomputed == {"retarget[ur5e_shadow]: config versions changed": 1}


def test_a_body_reads_only_what_its_stage_declared():
    nodes = {n.id: n for n in build_nodes(CLIP, {"allegro": "hand"})}
    render = nodes[(Unit("render", "c", embodiment="allegro"), 1)]
    inp = Inputs(None, render, ((0, 8), (8, 16), (16, 20)), lambda unit, name: None)
    with pytest.raises(UndeclaredRead, match="frames"):  # the source frames: not a render input
        inp.read(Unit("ingest", "c"), ["frames"])
    with pytest.raises(UndeclaredRead):  # its declared array, but of another chunk
        inp.read(Unit("retarget", "c", embodiment="allegro"), ["qpos"], 0, 8)
    with pytest.raises(UndeclaredRead):
        inp.value("source")
    assert inp.value("robot") == "robot-allegro"
    assert Arrays(Unit("retarget", "c", embodiment="allegro"), 1, ("qpos", "root_pose", "hand_status", "status")) in render.inputs


def test_a_review_decision_and_new_model_weights_rerun_their_stages(tmp_path):
    """Operator data in the store (``handedit review``) and a model file's content are inputs."""
    hand_arm = {"ur5e_shadow": "hand_arm"}
    reviews: dict = {}

    def walk_with(nodes, records):
        ran, written = [], {}

        def run_node(node, key, inputs, version, p, fault):
            ran.append(node.id)
            return {"key": key, "outcome": "ok", "version": version, "params": p, "inputs": inputs,
                    "outputs": {"status": f"s-{node.unit.stage}"}}

        result = walk(nodes, lambda s: (1, {}), records, run_node, lambda n, r: written.__setitem__(n.id, r),
                      WalkResult("c"), attrs=lambda unit, name: reviews.get((unit.path, name)))
        return result, ran, {**records, **written}

    _, _, stored = walk_with(build_nodes(CLIP, hand_arm), {})
    reviews[(Unit("retarget", "c", embodiment="ur5e_shadow").path, "reviews")] = {"right": {"choice": 3}}
    result, ran, stored = walk_with(build_nodes(CLIP, hand_arm), stored)
    assert [nid[0].stage for nid in ran] == ["retarget"] and result.recomputed == {"retarget[ur5e_shadow]: reviews changed": 1}
    # new weights at the same path: the stage that runs the model, and only it
    weights = tmp_path / "segmenter.onnx"
    weights.write_bytes(b"one")

    def with_model():
        cfg = CurateConfig(out="x", frames_per_chunk=8, segment={"method": "onnx", "model_path": str(weights)})
        return clip_nodes(CLIP, ["hand"], WalkConfig.from_json(cfg.model_dump_json()))

    _, _, stored = walk_with(with_model(), {})
    _, ran, stored = walk_with(with_model(), stored)
    assert ran == []
    weights.write_bytes(b"two")
    result, ran, _ = walk_with(with_model(), stored)
    assert {nid[0].stage for nid in ran} == {"segment"} and set(result.recomputed) == {"segment: model file model changed"}
