"""Nothing silently lost: a skip proves its data is there, corrupt bytes are named and
recomputed, two fresh runs on different worker counts write the same bytes.

Each test tampers with a copy of one finished run (1 synthetic clip, 2 chunks) and checks
that the pipeline ends with exactly the reference's data again.
"""

from __future__ import annotations

import os
import shutil
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from handedit.flows.cli import main
from handedit.flows.config import ClusterConfig, CurateConfig
from handedit.flows.curate import run_curate
from handedit.sources.synthetic import make_clip_specs
from handedit.storage import Location, StoreError, Unit, open_store
from handedit.storage.integrity import object_keys, verify
from handedit.storage.ledger import iter_units

W, H, T, F = 96, 72, 16, 8
CLIP = "synthetic-0000"


def config(out, cluster: ClusterConfig) -> CurateConfig:
    return CurateConfig(out=str(out), clips=make_clip_specs(1, seed=5, n_frames=T, width=W, height=H),
                        embodiments=["allegro"], frames_per_chunk=F, cluster=cluster)


def arrays(root) -> dict[str, np.ndarray]:
    return {f"{u.path}/{n}": root[u.path][n][:] for u in iter_units(root) for n in root[u.path].array_keys()}


def assert_same_bytes(a: Path, b: Path) -> None:
    """Every array of every stage, chunk by chunk; the message names each chunk that differs."""
    da, db = arrays(open_store(a)), arrays(open_store(b))
    assert set(da) == set(db)
    differ = [f"{k}#{s // F}" for k in da for s in range(0, len(da[k]), F)
              if da[k].dtype != db[k].dtype or da[k][s:s + F].tobytes() != db[k][s:s + F].tobytes()]
    assert not differ, differ


@contextmanager
def busy_cores(n: int | None = None):
    """Other processes keep every core busy (how the runs that differed were made)."""
    import subprocess
    import sys

    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n or os.cpu_count() or 2)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


@pytest.fixture(scope="module")
def cluster(dask_cluster) -> ClusterConfig:
    return ClusterConfig(address=dask_cluster.scheduler_address)


@pytest.fixture(scope="module")
def reference(tmp_path_factory, prefect_api, cluster) -> Path:
    out = tmp_path_factory.mktemp("reference") / "run"
    summary = run_curate(config(out, cluster))
    assert not summary["errors"] and summary["stages"]["harmonize"]["ran"] == T // F
    return out


@pytest.fixture()
def run(reference, tmp_path) -> Path:
    out = tmp_path / "run"
    shutil.copytree(reference, out)
    return out


def object_file(out: Path, unit: Unit, array: str, chunk: int) -> Path:
    arr = open_store(out)[f"{unit.path}/{array}"]
    return out / "handedit.zarr" / object_keys(arr, chunk * F, (chunk + 1) * F)[0]


HARMONIZE = Unit("harmonize", CLIP, embodiment="allegro")
SEGMENT = Unit("segment", CLIP)


def test_two_fresh_runs_on_different_worker_counts_write_the_same_bytes(reference, tmp_path, prefect_api):
    # the reference ran on 2 worker processes; this one starts its own 1-worker cluster with 2 threads,
    # while other processes keep the cores busy
    with busy_cores():
        summary = run_curate(config(tmp_path / "one", ClusterConfig(n_workers=1, threads_per_worker=2)))
    assert not summary["errors"]
    assert_same_bytes(reference, tmp_path / "one")


def test_a_deleted_chunk_and_a_deleted_array_are_recomputed(run, reference, cluster):
    object_file(run, HARMONIZE, "image", 1).unlink()
    shutil.rmtree(run / "handedit.zarr" / SEGMENT.path / "hand_mask")
    missing = verify(Location(run))
    assert {(p.array.rsplit("/", 1)[-1], p.kind) for p in missing} == {("image", "missing"), ("hand_mask", "missing")}
    summary = run_curate(config(run, cluster))
    assert summary["shards"]["ran"] == 1 and not summary["errors"]
    assert sorted(n.split(":")[0] for n in summary["recovered"]) == [
        "harmonize[synthetic-0000/allegro]#1", "segment[synthetic-0000]#0", "segment[synthetic-0000]#1"]
    assert summary["stages"]["harmonize"] == {"ran": 1, "skipped": 1, "failed": 0}
    assert_same_bytes(run, reference)
    assert verify(Location(run), deep=True) == []


def test_bench_build_refuses_a_hole_and_leaves_no_half_written_folder(run, tmp_path, capsys):
    object_file(run, HARMONIZE, "image", 0).unlink()
    bench = tmp_path / "bench"
    assert main(["bench", "build", "--store", str(run), "--out", str(bench), "-n", "2"]) == 2
    err = capsys.readouterr().err
    assert "missing" in err and "harmonize/image" in err and "verify" in err
    assert not bench.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".bench")]


def test_garbage_bytes_are_named_then_repaired(run, reference, cluster, capsys):
    image, status = object_file(run, HARMONIZE, "image", 1), object_file(run, SEGMENT, "status", 0)
    image.write_bytes(os.urandom(image.stat().st_size))
    status.write_bytes(os.urandom(64))
    # every reader says which file, and what to run; none prints a traceback
    for argv in (["status", str(run)], ["dashboard", str(run)], ["ledger", str(run)]):
        code = main(argv)
        err = capsys.readouterr().err
        if code:  # the ledger reads only records: it may not touch the bytes
            assert code == 2 and str(status) in err and "verify" in err and "Traceback" not in err, argv
    assert main(["dashboard", str(run)]) == 2 and str(status) in capsys.readouterr().err
    # verify: presence passes (the objects exist), --deep names both
    assert main(["verify", str(run)]) == 0
    assert main(["verify", str(run), "--deep"]) == 1
    out = capsys.readouterr().out
    assert "harmonize/image frames 8-15" in out and "segment/status frames 0-7" in out and "unreadable" in out
    assert main(["verify", str(run), "--deep", "--repair"]) == 0
    summary = run_curate(config(run, cluster))
    assert not summary["errors"] and summary["shards"]["ran"] == 1
    assert_same_bytes(run, reference)
    assert main(["verify", str(run), "--deep"]) == 0


def test_curate_recomputes_a_corrupt_chunk_it_owns(run, reference, cluster):
    """A chunk whose bytes fail to decode when its own task's next stage reads it."""
    src = object_file(run, Unit("ingest", CLIP), "frames", 0)
    src.write_bytes(os.urandom(src.stat().st_size))
    from handedit.storage.provenance import drop_records

    drop_records(open_store(run, mode="r+"), SEGMENT, [0])  # segment must read the corrupt frames again
    from handedit.storage.shards import invalidate

    invalidate(Location(run), [CLIP])
    summary = run_curate(config(run, cluster))
    assert not summary["errors"], summary["errors"]
    assert [n.split(":")[0] for n in summary["recovered"]] == ["ingest[synthetic-0000]#0"]  # and nothing else
    assert_same_bytes(run, reference)


def test_damaged_root_metadata_is_one_message(run, cluster, capsys):
    meta = run / "handedit.zarr" / "zarr.json"
    meta.write_text(meta.read_text()[:20])
    with pytest.raises(StoreError, match="zarr.json is not valid JSON"):
        open_store(run)
    assert main(["status", str(run)]) == 2
    err = capsys.readouterr().err
    assert "zarr.json is not valid JSON" in err and "verify" in err and "--repair" in err
    # its few fields are rebuilt from the groups; nothing else was lost
    assert main(["verify", str(run), "--repair"]) == 0
    assert "rebuilt" in capsys.readouterr().out
    assert open_store(run).attrs["frames_per_chunk"] == F
    summary = run_curate(config(run, cluster))
    assert not summary["errors"] and all(c["ran"] == 0 for c in summary["stages"].values())


def test_deleted_index_and_ledger_are_rebuilt(run, cluster):
    shutil.rmtree(run / "index")
    shutil.rmtree(run / "ledger")
    summary = run_curate(config(run, cluster))
    assert not summary["errors"] and summary["shards"]["ran"] == 1
    assert all(c["ran"] == 0 for c in summary["stages"].values())  # every chunk skipped
    assert list((run / "index").glob("*.parquet")) and list((run / "ledger").glob("*.parquet"))


def test_damaged_group_metadata_is_found_and_rebuilt(run, reference, cluster, capsys):
    meta = run / "handedit.zarr" / SEGMENT.path / "zarr.json"
    meta.write_text(meta.read_text()[:30])
    assert main(["status", str(run)]) == 2
    err = capsys.readouterr().err
    assert "zarr.json in the store is damaged" in err and "verify" in err and "Traceback" not in err
    assert main(["verify", str(run)]) == 1
    assert f"{SEGMENT.path}/zarr.json: damaged metadata" in capsys.readouterr().out
    assert main(["verify", str(run), "--repair"]) == 0
    summary = run_curate(config(run, cluster))
    assert not summary["errors"] and summary["stages"]["segment"]["ran"] == T // F
    assert summary["stages"]["harmonize"]["skipped"] == T // F  # recomputed bytes are the same: nothing downstream re-runs
    assert_same_bytes(run, reference)


def test_changed_but_decodable_bytes_are_never_published(run, reference, cluster, tmp_path, capsys):
    """Valid bytes, the wrong pixels (the second chunk's harmonized frames over the first's):
    presence checks pass; release and bench build re-hash what they publish and refuse."""
    from handedit.storage.releases import read_release, versions

    first, second = object_file(run, HARMONIZE, "image", 0), object_file(run, HARMONIZE, "image", 1)
    first.write_bytes(second.read_bytes())
    assert main(["verify", str(run)]) == 0  # presence only: nothing to see
    capsys.readouterr()
    rel = tmp_path / "releases"
    assert main(["release", "--from", str(run), "--out", str(rel), "--address", cluster.address]) != 0
    err = capsys.readouterr().err
    assert "harmonize/image frames 0-7" in err and str(first) in err and "--deep --repair" in err, err
    assert versions(Location(rel)) == []
    bench = tmp_path / "bench"
    assert main(["bench", "build", "--store", str(run), "--out", str(bench), "-n", "2"]) == 2
    assert "harmonize/image frames 0-7" in capsys.readouterr().err and not bench.exists()
    # the advice repairs: the deep check finds it, curate recomputes it, the release publishes verified shards
    assert main(["verify", str(run), "--deep", "--repair"]) == 0
    assert not run_curate(config(run, cluster))["errors"]
    assert_same_bytes(run, reference)
    assert main(["release", "--from", str(run), "--out", str(rel), "--address", cluster.address]) == 0
    manifest = read_release(Location(rel), versions(Location(rel))[-1])
    assert manifest["shards"] and all(s["verified"] for s in manifest["shards"])


@contextmanager
def small_disk(path: Path, size: str):
    """A tmpfs of ``size`` mounted at ``path`` (root, as in CI)."""
    import subprocess

    path.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True, text=True)
    if done.returncode:
        pytest.fail(f"mounting a tmpfs needs root (CI runs as root): {done.stderr.strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


def test_a_full_disk_fails_the_run_and_release_refuses_it(tmp_path, cluster, prefect_api, capsys):
    from handedit.storage import read_ledger

    with small_disk(tmp_path / "small", "700k") as disk:
        out = disk / "run"
        argv = ["curate", "--demo", "--clips", "1", "--frames", "16", "--width", "96", "--height", "72",
                "--frames-per-chunk", "8", "--out", str(out), "--address", cluster.address, "--no-progress"]
        assert main(argv) == 1
        said = "".join(capsys.readouterr())
        assert "No space left on device" in said and "free space" in said, said
        # no frame was rejected for it: a rejection would be published as a removed pair
        ledger = read_ledger(open_store(out))
        assert "STAGE_ERROR" not in set(ledger["reason_name"])
        assert main(["release", "--from", str(out), "--out", str(tmp_path / "releases"), "--address", cluster.address]) == 2
        assert "left incomplete" in capsys.readouterr().err
