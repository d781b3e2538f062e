"""The Zarr layout, chunk I/O, provenance and ledger, without a cluster."""

from __future__ import annotations

import json

import dask.array as da
import numpy as np
import pytest
import xarray as xr
import zarr

from handedit.reasons import Reason
from handedit.storage import (
    ChunkRecord,
    StoreError,
    Unit,
    chunk_ranges,
    create_or_open_store,
    create_unit,
    is_current,
    open_store,
    provenance_key,
    read_chunk,
    read_ledger,
    read_records,
    writable,
    write_chunk,
    write_records,
)
from handedit.storage.store import jsonable

F = 4


@pytest.fixture
def root(tmp_path):
    return create_or_open_store(tmp_path / "s.zarr", frames_per_chunk=F, code_version="test")


def test_unit_paths_and_validation():
    assert Unit("ingest", "c1").path == "clips/c1/source"
    assert Unit("restore_background", "c1", scope="hand_arm").path == "clips/c1/restore_background/hand_arm"
    assert Unit("render", "c1", embodiment="allegro").path == "clips/c1/embodiments/allegro/render"
    with pytest.raises(ValueError, match="unknown stage"):
        Unit("nope", "c1")
    with pytest.raises(ValueError, match="per embodiment"):
        Unit("render", "c1")
    with pytest.raises(ValueError, match="invalid clip id"):
        Unit("ingest", "a/b").path


def test_chunk_ranges_cover_clip_once():
    ranges = chunk_ranges(10, 4)
    assert ranges == [(0, 4), (4, 8), (8, 10)]
    covered = np.concatenate([np.arange(a, b) for a, b in ranges])
    assert np.array_equal(covered, np.arange(10))


def test_arrays_chunked_per_writer_and_open_with_zarr_dask_xarray(root, tmp_path):
    unit = Unit("ingest", "c1")
    create_unit(root, unit, 10, {"H": 8, "W": 6, "S": 2}, F, has_object=True, has_gt=True)
    frames = root[unit.path]["frames"]
    assert frames.shape == (10, 8, 6, 3) and frames.chunks == (1, 8, 6, 3) and frames.shards == (F, 8, 6, 3)
    assert "zstd" in str(frames.compressors) and "noshuffle" in str(frames.compressors)  # colour: zstd level 1
    mask = root[unit.path]["object_mask"]
    assert "zstd" in str(mask.compressors) and "bitshuffle" in str(mask.compressors)  # masks: bit-shuffled
    assert root[unit.path]["keypoints"].chunks == (F, 2, 21, 3)  # a hand axis
    # two chunk-aligned writers fill disjoint files
    a = np.random.default_rng(0).integers(0, 255, (4, 8, 6, 3), dtype=np.uint8)
    b = np.random.default_rng(1).integers(0, 255, (4, 8, 6, 3), dtype=np.uint8)
    write_chunk(root, unit, 0, {"frames": a})
    write_chunk(root, unit, 4, {"frames": b})
    got = read_chunk(zarr.open_group(str(tmp_path / "s.zarr"), mode="r"), unit, ["frames"], 0, 8)["frames"]
    assert np.array_equal(got, np.concatenate([a, b]))
    # plain zarr, dask.array and xarray open it
    store = str(tmp_path / "s.zarr")
    assert da.from_zarr(store, component=f"{unit.path}/frames")[:8].compute().sum() == got.sum()
    ds = xr.open_zarr(store, group=unit.path, consolidated=False)
    assert ds["frames"].dims == ("frame", "y", "x", "rgb") and ds.sizes["frame"] == 10


def test_write_chunk_rejects_wrong_shapes(root):
    unit = Unit("segment", "c1")
    create_unit(root, unit, 8, {"H": 4, "W": 4, "S": 1}, F)
    with pytest.raises(ValueError, match="segment"):
        write_chunk(root, unit, 0, {"hand_mask": np.zeros((4, 1, 5, 4), bool)})
    with pytest.raises(KeyError, match="no array"):
        write_chunk(root, unit, 0, {"bogus": np.zeros((4,))})


def test_digest_changes_with_content(root):
    unit = Unit("segment", "c1")
    create_unit(root, unit, 8, {"H": 4, "W": 4, "S": 1}, F)
    d1 = write_chunk(root, unit, 0, {"confidence": np.zeros((4, 1), np.float32)})
    d2 = write_chunk(root, unit, 0, {"confidence": np.ones((4, 1), np.float32)})
    d3 = write_chunk(root, unit, 4, {"confidence": np.zeros((4, 1), np.float32)})
    assert d1["confidence"] != d2["confidence"] and d1["confidence"] == d3["confidence"]


def test_deep_check_recomputes_the_recorded_kind_of_digest(root):
    """Records written before the XXH3 digests carry blake2b ones: the deep check recomputes
    the kind each record holds, so an older store still verifies, and a changed frame is a
    mismatch under either kind."""
    from handedit.storage.integrity import check_unit, object_keys
    from handedit.storage.store import digest

    unit = Unit("segment", "c1")
    create_unit(root, unit, 8, {"H": 4, "W": 4, "S": 1}, F)
    value = np.arange(4, dtype=np.float32).reshape(4, 1)
    new = write_chunk(root, unit, 0, {"confidence": value})["confidence"]
    old = digest(value, like="0" * 32)
    assert new.startswith("xxh3:") and len(new) == 5 + 32 and len(old) == 32 and old not in new
    assert digest(value, like=new) == new and digest(value + 1, like=old) != old
    present = set(object_keys(root[unit.path]["confidence"], 0, 4))
    for recorded in (new, old):
        write_records(root, unit, [ChunkRecord("segment", 0, 0, 4, "k", 1, {}, {}, outputs={"confidence": recorded})])
        assert check_unit(root, unit, present, deep=True) == [], recorded
        write_chunk(root, unit, 0, {"confidence": value + 1})
        assert [p.kind for p in check_unit(root, unit, present, deep=True)] == ["mismatch"], recorded
        write_chunk(root, unit, 0, {"confidence": value})


def test_provenance_key_and_records(root):
    k1 = provenance_key("harmonize", 1, {"strength": 0.5}, {"a": "x"})
    assert k1 == provenance_key("harmonize", 1, {"strength": 0.5}, {"a": "x"})
    assert k1 != provenance_key("harmonize", 1, {"strength": 0.6}, {"a": "x"})
    assert k1 != provenance_key("harmonize", 2, {"strength": 0.5}, {"a": "x"})
    assert k1 != provenance_key("harmonize", 1, {"strength": 0.5}, {"a": "y"})
    unit = Unit("harmonize", "c1", embodiment="allegro")
    create_unit(root, unit, 8, {"H": 4, "W": 4, "S": 1}, F)
    rec = ChunkRecord("harmonize", 1, 4, 8, k1, 1, {"strength": 0.5}, {"a": "x"}, seconds=np.float64(0.5))
    write_records(root, unit, [rec])
    back = read_records(open_store(root.store.root, mode="r"), unit)[1]
    assert back.key == k1 and back.start == 4 and back.seconds == 0.5
    assert is_current(back, k1) and not is_current(back, "other")
    back.outcome = "error"
    assert not is_current(back, k1)  # failed chunks are retried


def test_jsonable_handles_numpy_and_nan():
    out = jsonable({"a": np.float32(1.5), "b": np.int64(3), "c": float("nan"), "d": np.arange(2), "e": np.bool_(True)})
    assert out == {"a": 1.5, "b": 3, "c": None, "d": [0, 1], "e": True}
    json.dumps(out, allow_nan=False)


def test_ledger_table_from_records(root):
    unit = Unit("segment", "c1")
    create_unit(root, unit, 8, {"H": 4, "W": 4, "S": 1}, F)
    rec = ChunkRecord("segment", 0, 0, 4, "k", 1, {}, {},
                      rejections=[{"frame": 2, "reason": int(Reason.EMPTY_MASK), "detail": "empty"}])
    write_records(root, unit, [rec])
    # an unreadable clip has no units: its row comes from its shard's index partition
    from handedit.storage.location import location_of
    from handedit.storage.shards import INDEX, write_partition
    from handedit.storage.summary import index_rows

    index = index_rows(root, [], {"bad": "bad.mp4: cannot decode"})
    index["written"] = 1.0
    write_partition(location_of(root), INDEX, "clips-00000", index)
    ledger = read_ledger(root)
    assert list(ledger.columns) == ["stage", "clip", "scope", "embodiment", "side", "frame", "reason", "reason_name", "detail"]
    rows = ledger.to_dict(orient="records")
    assert {"stage": "segment", "clip": "c1", "frame": 2, "reason_name": "EMPTY_MASK"}.items() <= rows[1].items()
    assert rows[0]["frame"] == -1 and rows[0]["reason_name"] == "SOURCE_UNREADABLE"
    # re-recording the chunk replaces its rows instead of appending
    rec.rejections = []
    write_records(root, unit, [rec])
    assert list(read_ledger(root)["clip"]) == ["bad"] and int(read_ledger(root)["frame"][0]) == -1


def test_store_open_errors(tmp_path):
    with pytest.raises(StoreError, match="not a handedit store"):
        open_store(tmp_path / "missing.zarr")
    create_or_open_store(tmp_path / "s.zarr", 4, "t")
    with pytest.raises(StoreError, match="frames_per_chunk=4"):
        create_or_open_store(tmp_path / "s.zarr", 8, "t")


def test_recreated_array_drops_provenance(root):
    unit = Unit("retarget", "c1", embodiment="e")
    create_unit(root, unit, 8, {"dof": 16, "S": 1}, F)
    write_records(root, unit, [ChunkRecord("retarget", 0, 0, 4, "k", 1, {}, {})])
    create_unit(root, unit, 8, {"dof": 16, "S": 1}, F)  # same shapes: records kept
    assert read_records(root, unit)
    create_unit(root, unit, 8, {"dof": 22, "S": 1}, F)  # new DoF: empty array, nothing is current
    assert root[unit.path]["qpos"].shape == (8, 1, 22) and read_records(root, unit) == {}


def test_handoff_serves_what_was_written_until_its_last_reader(root):
    """storage.handoff: a written chunk a later node reads is served from memory, read-only,
    only while it has readers, only for the walk's own store and within the budget; the
    last reader of an array takes the writer's own (writable) array over."""
    from handedit.storage.handoff import Handoff, handing_over

    unit = Unit("segment", "c1")
    create_unit(root, unit, 8, {"H": 4, "W": 4, "S": 1}, F)
    a = np.random.default_rng(0).random((4, 1), np.float32)
    b = np.random.default_rng(1).random((4, 1), np.float32)
    k0, k4 = (unit.path, 0), (unit.path, 4)
    kept = Handoff(root.store, {k0: 2, k4: 2}, {k0: ["confidence", "confidence"], k4: ["confidence", "confidence"]}, 1 << 20)
    with handing_over(kept):
        write_chunk(root, unit, 0, {"confidence": a, "hand_status": np.zeros((4, 1), np.int16)})
        write_chunk(root, unit, 4, {"confidence": b})
        got = read_chunk(root, unit, ["confidence"], 2, 7)["confidence"]  # spans both kept chunks
        assert np.array_equal(got, np.concatenate([a, b])[2:7]) and kept.served == 1
        with pytest.raises(ValueError, match="read-only"):  # shared: a stage that writes into it allocates instead
            got[:] = -1
        assert writable(got) is None and writable(got.copy()) is not None
        first = read_chunk(root, unit, ["confidence"], 0, 4)["confidence"]
        assert np.array_equal(first, a) and writable(first) is None  # another reader is still to come
        # an array no reader named was not kept: read from the store
        assert kept.get(root.store, unit.path, "hand_status", 0, 4) is None
        assert kept.get(object(), unit.path, "confidence", 0, 4) is None  # another store
        kept.done([(unit.path, 0, ("confidence",))])  # one of chunk 0's readers ran
        last = read_chunk(root, unit, ["confidence"], 0, 4)["confidence"]
        assert np.array_equal(last, a) and writable(last) is not None  # the last reader takes the written array over
        assert kept.get(root.store, unit.path, "confidence", 0, 4) is None
        kept.done([(unit.path, 0, ("confidence",)), (unit.path, 4, ("confidence",)), (unit.path, 4, ("confidence",))])
        assert kept.nbytes == 0 and not kept.kept[unit.path] and not kept.written
        served = kept.served
        assert np.array_equal(read_chunk(root, unit, ["confidence"], 0, 8)["confidence"], np.concatenate([a, b]))
        assert kept.served == served  # from the store
    tight = Handoff(root.store, {k0: 1}, {k0: ["confidence"]}, a.nbytes - 1)
    with handing_over(tight):  # over the budget: not kept
        write_chunk(root, unit, 0, {"confidence": a})
        assert tight.nbytes == 0 and tight.get(root.store, unit.path, "confidence", 0, 4) is None


def test_reused_chunks_keep_the_running_clip_and_evict_other_clips_first():
    """storage.handoff.Reused: within its budget; a clip never evicts its own chunks (a scan
    longer than the budget keeps its first chunks for the next embodiment), others go oldest first."""
    from handedit.storage.handoff import Reused

    r, budget = Reused(), 4 * 100
    chunk = lambda: np.zeros(100, np.uint8)
    for k in range(3):
        r.put(("B", k), "clip-b", chunk(), budget)
    for k in range(2):  # clip a: evicts b's, oldest first
        r.put(("A", k), "clip-a", chunk(), budget)
    assert list(r.entries) == [("B", 1), ("B", 2), ("A", 0), ("A", 1)] and r.nbytes == 400
    for k in range(2, 6):  # then stops: never its own
        r.put(("A", k), "clip-a", chunk(), budget)
    assert list(r.entries) == [("A", 0), ("A", 1), ("A", 2), ("A", 3)] and r.nbytes == 400
    assert r.get(("A", 0)) is not None and not r.get(("A", 0)).flags.writeable and r.get(("A", 4)) is None
    r.put(("big",), "clip-c", np.zeros(401, np.uint8), budget)  # larger than the budget: not kept, nothing evicted
    assert len(r.entries) == 4


def test_walks_hand_over_their_chunks_and_store_the_same_data(tmp_path, monkeypatch, robots_dir):
    """A clip's and its embodiments' walks (the task bodies, hand and hand-arm) with the
    hand-over equal the same walks decoding every read: array for array, digest for digest;
    and with it, no stage reads back from the store what its own walk wrote, and the second
    embodiment's walk reuses the clip's frames the first one decoded."""
    from dataclasses import asdict

    import handedit.storage.store as store_mod
    from handedit.flows.config import CurateConfig
    from handedit.flows.curate import code_version, plan_embodiments
    from handedit.sources.synthetic import make_clip_specs
    from handedit.storage import Location
    from handedit.storage.handoff import REUSED
    from handedit.storage.ledger import iter_units
    from handedit.tasks.clip import ClipJob, EmbodimentJob, run_clip, run_embodiment

    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))  # the hand-arm robot's meshes
    spec = make_clip_specs(1, seed=5, n_frames=8, width=96, height=72)[0]
    read_paths: list[str] = []
    real_read = store_mod.read_array
    monkeypatch.setattr(store_mod, "read_array", lambda a, sel=slice(None): read_paths.append(a.path) or real_read(a, sel))

    def curate(out, mib: int):
        cfg = CurateConfig(out=str(out), clips=[spec], embodiments=["allegro", "xarm_ability"], frames_per_chunk=4,
                           handoff_mib=mib, reuse_mib=mib)
        loc = Location(cfg.out)
        create_or_open_store(loc, cfg.frames_per_chunk, "test")
        embs = [asdict(e) for e in plan_embodiments(cfg.embodiments)]
        scopes = tuple(sorted({e["scope"] for e in embs}))
        read_paths.clear()
        assert not run_clip(ClipJob(loc.store_url, spec.model_dump_json(), cfg.model_dump_json(), scopes, code_version()))["errors"]
        clip_reads = list(read_paths)
        emb_reads = []
        REUSED.clear()
        for e in embs:
            read_paths.clear()
            result = run_embodiment(EmbodimentJob(loc.store_url, spec.id, e, cfg.model_dump_json(), code_version()))
            assert not result["errors"] and all(not c["failed"] for c in result["stages"].values()), result
            emb_reads.append(list(read_paths))
        return open_store(loc.store_url), clip_reads, emb_reads

    kept, clip_reads, emb_reads = curate(tmp_path / "kept", 512)
    plain, plain_clip_reads, plain_emb_reads = curate(tmp_path / "plain", 0)
    def of(paths: list[str], stages: tuple[str, ...]) -> list[str]:  # reads of these stages' units
        units = {Unit(s, spec.id, embodiment=e).path for s in stages for e in (None, "allegro", "xarm_ability")
                 if (e is None) == (s in ("ingest", "registration", "segment"))}
        return [p for p in paths if p.rsplit("/", 1)[0] in units]

    clip_own, emb_own = ("ingest", "registration", "segment"), ("retarget", "render", "composite", "harmonize")
    assert of(plain_clip_reads, clip_own) and of(sum(plain_emb_reads, []), emb_own)
    assert not of(clip_reads, clip_own) and not of(sum(emb_reads, []), emb_own)
    frames = Unit("ingest", spec.id).path + "/frames"
    assert [r.count(frames) for r in plain_emb_reads] == [2, 2]  # each embodiment decodes the clip's 2 chunks
    assert [r.count(frames) for r in emb_reads] == [2, 0]  # the second reuses them
    for unit in iter_units(plain):
        for name in plain[unit.path].array_keys():
            if not name.startswith("previews"):
                np.testing.assert_array_equal(kept[unit.path][name][:], plain[unit.path][name][:], err_msg=f"{unit.path}/{name}")
        a, b = read_records(kept, unit), read_records(plain, unit)
        assert {k: r.outputs for k, r in a.items()} == {k: r.outputs for k, r in b.items()} and a


def test_a_stage_declares_its_own_arrays_and_the_store_lays_them_out(root, monkeypatch):
    """A new stage is its tasks module: its ``writes=`` is the unit's schema (no table in storage)."""
    import handedit.storage.layout as layout
    import handedit.tasks as tasks
    from handedit.storage.layout import HAND_STATUS, MASK, MASK_DIMS, STATUS, ArraySpec
    from handedit.tasks.stage import Stage
    from handedit.vision.harmonize import HarmonizeConfig

    def never(*_):
        raise AssertionError("not walked here")

    shade = Stage("shade", "embodiment", HarmonizeConfig, never, never,
                  writes=(ArraySpec("shadow", MASK, "float32", MASK_DIMS, image=True), HAND_STATUS, STATUS))
    monkeypatch.setattr(tasks, "STAGES", (*tasks.STAGES, shade))
    monkeypatch.setattr(layout, "_LAYOUTS", None)
    unit = Unit("shade", "c1", embodiment="allegro")
    assert unit.path == "clips/c1/embodiments/allegro/shade" and layout.stage_layouts()["shade"].per_hand
    create_unit(root, unit, 8, {"H": 4, "W": 6, "S": 2}, F)
    assert root[unit.path]["shadow"].shape == (8, 4, 6) and root[unit.path]["hand_status"].shape == (8, 2)
    with pytest.raises(KeyError, match="schema: \\['shadow', 'hand_status', 'status'\\]"):
        write_chunk(root, unit, 0, {"light": np.zeros((4,))})

    broken = Stage("glow", "embodiment", HarmonizeConfig, never, never, writes=(HAND_STATUS,))  # no status
    monkeypatch.setattr(tasks, "STAGES", (*tasks.STAGES, broken))
    monkeypatch.setattr(layout, "_LAYOUTS", None)
    with pytest.raises(ValueError, match=r"stage 'glow' \(tasks/glow.py\).*'status'"):
        Unit("glow", "c1", embodiment="allegro")
