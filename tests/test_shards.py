"""Shards: lazy planning, stable ids, claims (exclusive, stale ones taken over), the budgets
of a paper-scale plan, and the store's bookkeeping partitions. No cluster needed."""

from __future__ import annotations

import os
import socket
import time
import tracemalloc

import pytest

from handedit.flows.plan import iter_shards
from handedit.sources import EgoDexTree
from handedit.sources.synthetic import make_clip_specs
from handedit.storage import Location
from handedit.storage.shards import current_claim, is_stale, release, renew, try_claim


def test_locations_local_and_url():
    loc = Location("runs/x")
    assert loc.is_local and loc.store_url.endswith("runs/x/handedit.zarr")
    assert Location("runs/x/handedit.zarr") == loc and Location("runs/x/other.zarr").store_url.endswith("x/other.zarr")
    s3 = Location("s3://bucket/prefix")
    assert not s3.is_local and s3.store_url == "s3://bucket/prefix/handedit.zarr" and s3.root == "bucket/prefix"
    import pickle

    assert pickle.loads(pickle.dumps(s3)) == s3


def test_claims_are_exclusive_renewed_released_and_taken_over(tmp_path):
    loc = Location(tmp_path)
    a, held = try_claim(loc, "s-00000", "run-a", lease_s=60)
    assert a is not None and held is None and a.generation == 1
    b, holder = try_claim(loc, "s-00000", "run-b", lease_s=60)
    assert b is None and holder.holder == "run-a" and "run-a" in holder.describe() and str(os.getpid()) in holder.describe()
    assert try_claim(loc, "s-00000", "run-a")[0].generation == 1  # the holder itself: the same claim
    assert renew(loc, a, 60)
    release(loc, a)
    b, _ = try_claim(loc, "s-00000", "run-b", lease_s=60)
    assert b is not None and b.generation == 2  # a released claim is free
    # a claim of a dead process on this host is stale at once; an expired lease anywhere
    dead = current_claim(loc, "s-00000")
    dead.pid = 2 ** 22 + 12345  # no such pid
    assert is_stale(dead)
    far = current_claim(loc, "s-00000")
    far.host, far.expires = "elsewhere", time.time() - 1
    assert is_stale(far)
    far.expires = time.time() + 60
    assert not is_stale(far)
    # take-over: the next generation; the old holder learns it lost the shard
    c, _ = try_claim(loc, "s-00000", "run-c", take_over=True)
    assert c.generation == 3 and not renew(loc, b, 60)


def test_racing_drivers_one_wins_each_generation(tmp_path):
    """create-if-absent: of many processes claiming the same shard at once, exactly one gets it."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    with ctx.Pool(4) as pool:
        won = pool.starmap(_claim, [(str(tmp_path), f"run-{i}") for i in range(8)])
    assert sum(won) == 1


def _claim(path: str, holder: str) -> bool:
    return try_claim(Location(path), "s-00000", holder)[0] is not None


def test_shards_are_cut_lazily_with_stable_ids(tmp_path):
    specs = make_clip_specs(5, n_frames=8)
    shards = list(iter_shards([], specs, 2))
    assert [s.id for s in shards] == ["clips-00000", "clips-00001", "clips-00002"]
    assert [len(s.specs) for s in shards] == [2, 2, 1]
    # a growing list keeps the earlier shards (same ids, same clips, same digests)
    more = list(iter_shards([], make_clip_specs(6, n_frames=8), 2))
    assert [s.digest("k") for s in more[:2]] == [s.digest("k") for s in shards[:2]] and more[2].digest("k") != shards[2].digest("k")
    # tree shards are per group (task): a subset run gives the same ids as the full run
    for t, eps in (("a", 3), ("b", 2)):  # listing only: the files are never opened here
        (tmp_path / t).mkdir()
        for e in range(eps):
            for ext in ("hdf5", "mp4"):
                (tmp_path / t / f"{e}.{ext}").write_bytes(b"x")
    full = {s.id: s.clip_ids for s in iter_shards([EgoDexTree(root=tmp_path)], [], 2)}
    assert full == {"egodex-a-00000": ["egodex-a-0", "egodex-a-1"], "egodex-a-00001": ["egodex-a-2"],
                    "egodex-b-00000": ["egodex-b-0", "egodex-b-1"]}
    sub = {s.id: s.clip_ids for s in iter_shards([EgoDexTree(root=tmp_path, tasks=["b"])], [], 2)}
    assert sub == {"egodex-b-00000": full["egodex-b-00000"]}
    # a touched source file changes its shard's digest (cheap: size + mtime, no hashing)
    before = [s.digest("k") for s in iter_shards([EgoDexTree(root=tmp_path)], [], 2)]
    os.utime(tmp_path / "a" / "2.mp4", ns=(1, 1))
    after = [s.digest("k") for s in iter_shards([EgoDexTree(root=tmp_path)], [], 2)]
    assert before[0] == after[0] and before[1] != after[1] and before[2] == after[2]


def test_paper_scale_plan_fits_its_budgets():
    """10,000 simulated EgoDex-like clips x 26 embodiments, planned as the driver plans them."""
    import sys

    sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[1] / "bench"))
    import handedit.flows.plan  # noqa: F401  (imports are not the plan's memory)
    import handedit.sources.synthetic  # noqa: F401
    from scale import SimulatedTree, simulate_plan

    tracemalloc.start()
    tree = SimulatedTree(n_clips=10_000, clips_per_task=1_700)
    plan = simulate_plan(tree, n_embodiments=26, shard_size=64, frames=266, frames_per_chunk=16)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert plan["clips"] == 10_000 and plan["shards"] == sum(-(-n // 64) for n in tree.task_sizes())
    assert plan["prefect_task_runs"] / plan["clips"] <= 27  # 1 + E per clip
    assert plan["flow_runs"] == plan["shards"] + 1
    assert plan["driver_held_shards"] <= 2  # shards in flight: the driver never holds the listing
    assert peak < 64 * 2**20  # the driver's Python heap while planning (the budget is 1 GB)
    assert plan["largest_bookkeeping_file_clips"] <= 64  # no file grows with the total clip count
