"""``handedit export lerobot``: a curated run as a LeRobot v3.0 dataset that the official
``lerobot`` package loads (in its own venv, ``deploy/lerobot-env.sh``), re-exported
incrementally, refused clearly on bad input and never left half-written; and
``handedit release --videos``: frame-aligned video pairs beside the shards."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from handedit.flows.cli import main
from handedit.reasons import Reason
from handedit.storage import Unit, open_store
from handedit.storage.store import read_array

from test_release import curate

REPO = Path(__file__).resolve().parents[1]
SIDE = Path(__file__).with_name("_lerobot_side.py")
CLIPS = ["synthetic-0000", "synthetic-0001"]


def lerobot_python() -> str:
    py = os.environ.get("HANDEDIT_LEROBOT_PYTHON") or str(REPO / ".venv-lerobot" / "bin" / "python")
    if not Path(py).is_file():
        pytest.fail(f"the official LeRobot's venv is missing ({py}): run `bash deploy/lerobot-env.sh` "
                    f"(deploy/setup.sh --test does), or point HANDEDIT_LEROBOT_PYTHON at a python that has lerobot 0.4.4")
    return py


def load_with_lerobot(root: Path, out: Path, indices: list[int]) -> tuple[dict, dict[str, np.ndarray]]:
    done = subprocess.run([lerobot_python(), str(SIDE), str(root), str(out), *map(str, indices)], capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    meta = json.loads((out / "meta.json").read_text())
    return meta, {p.stem: np.load(p) for p in out.glob("*.npy")}


def export(run: Path, out: Path, *extra: str, emb: str = "allegro", address: str | None = None) -> int:
    return main(["export", "lerobot", "--from", str(run), "--embodiment", emb, "--out", str(out), *extra,
                 *(["--address", address] if address else [])])


def no_partial(parent: Path) -> bool:
    return not [p for p in parent.iterdir() if ".partial-" in p.name or ".old-" in p.name]


@pytest.fixture(scope="module")
def curated(tmp_path_factory, prefect_api, dask_cluster):
    run = tmp_path_factory.mktemp("export") / "run"
    curate(run, 2, dask_cluster)
    return run, dask_cluster


def store_episode(run: Path, clip: str, emb: str = "allegro") -> dict:
    root = open_store(run)
    qc, ret = Unit("qc", clip, embodiment=emb), Unit("retarget", clip, embodiment=emb)
    return {"status": read_array(root[qc.path]["status"]), "hand_status": read_array(root[ret.path]["hand_status"]),
            "qpos": read_array(root[ret.path]["qpos"]), "joints": list(root[ret.path].attrs["joint_names"]),
            "sides": list(root[qc.path].attrs.get("hands") or ["right"]),
            "pseudo_gt": read_array(root[Unit("harmonize", clip, embodiment=emb).path]["image"]),
            "source": read_array(root[Unit("ingest", clip).path]["frames"])}


def test_official_lerobot_loads_the_export(curated, tmp_path, capsys):
    run, cluster = curated
    out = tmp_path / "allegro"
    assert export(run, out, "--include-source", address=cluster.scheduler_address) == 0
    assert "2 encoded, 0 unchanged" in capsys.readouterr().out
    eps = [store_episode(run, c) for c in CLIPS]
    T = len(eps[0]["status"])
    idx = [0, 4, 5, T - 1, T, T + 7]  # both episodes, their ends, a frame and its successor
    meta, got = load_with_lerobot(out, tmp_path / "side", idx)

    assert meta["num_episodes"] == 2 and meta["num_frames"] == 2 * T and meta["fps"] == 30
    names = [f"{s}_{j}" for s in eps[0]["sides"] for j in eps[0]["joints"]]
    feats = meta["features"]
    assert feats["observation.state"]["names"] == names == feats["action"]["names"]
    assert feats["observation.state"]["shape"] == [len(names)] and feats["observation.wrist_pose"]["shape"] == [7 * len(eps[0]["sides"])]
    assert sorted(meta["camera_keys"]) == ["observation.images.egocentric", "observation.images.source"]
    assert {"observation.state", "action", "observation.images.egocentric"} <= set(meta["stats_keys"])
    assert got["observation.state"].shape == (len(idx), len(names))
    for n, i in enumerate(idx):
        ep, t = eps[i // T], i % T
        # the decoded video frame is the stored pseudo-GT (and source) frame, within codec error
        assert np.abs(got["observation.images.egocentric"][n].astype(int) - ep["pseudo_gt"][t]).mean() < 6
        assert np.abs(got["observation.images.source"][n].astype(int) - ep["source"][t]).mean() < 6
        assert bool(got["valid"][n]) == bool(ep["status"][t] == Reason.OK)
        if ep["hand_status"][t, 0] == Reason.OK:
            np.testing.assert_allclose(got["observation.state"][n], ep["qpos"][t].reshape(-1), atol=1e-6)
    np.testing.assert_allclose(got["action"][1], got["observation.state"][2])  # action = the next frame's state
    assert got["episode_index"].tolist() == [0, 0, 0, 0, 1, 1] and got["frame_index"].tolist() == [0, 4, 5, T - 1, 0, 7]
    assert all(t == meta["tasks"][0] and "Allegro" in t for t in meta["tasks"])
    info = json.loads((out / "meta" / "info.json").read_text())["handedit"]
    assert info["robot"]["embodiment"] == "allegro" and len(info["robot"]["urdf"]["sha256"]) == 64
    assert info["robot"]["actuated_joints"] == eps[0]["joints"] and "mirrored" in info["robot"]["left"]
    rows = pd.read_parquet(out / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    intr = [json.loads(x) for x in rows["handedit/intrinsics"]]  # the synthetic clips' cameras differ: per episode
    assert [i["width"] for i in intr] == [96, 96] and info["camera"]["intrinsics"] in (None, intr[0])
    assert rows["handedit/clip"].tolist() == CLIPS and no_partial(tmp_path)


def test_reexport_encodes_only_new_or_changed_episodes(curated, tmp_path, capsys, prefect_api, dask_cluster):
    import shutil

    run0, cluster = curated
    run = tmp_path / "run"
    shutil.copytree(run0, run)
    out = tmp_path / "allegro"
    assert export(run, out, address=cluster.scheduler_address) == 0
    video = lambda e: out / "videos" / "observation.images.egocentric" / "chunk-000" / f"file-{e:03d}.mp4"
    before = {e: (video(e).stat().st_ino, video(e).read_bytes()) for e in (0, 1)}
    capsys.readouterr()
    assert export(run, out, address=cluster.scheduler_address) == 0
    assert "0 encoded, 2 unchanged" in capsys.readouterr().out
    curate(run, 3, dask_cluster)  # one clip more
    assert export(run, out, address=cluster.scheduler_address) == 0
    assert "1 encoded, 2 unchanged" in capsys.readouterr().out
    for e in (0, 1):  # the old episodes' videos were linked, not encoded again
        assert (video(e).stat().st_ino, video(e).read_bytes()) == before[e]
    rows = pd.read_parquet(out / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    assert rows["episode_index"].tolist() == [0, 1, 2] and rows["handedit/clip"].tolist()[-1] == "synthetic-0002"
    assert rows["dataset_from_index"].tolist() == [0, 16, 32] and video(2).is_file()
    assert json.loads((out / "meta" / "info.json").read_text())["total_frames"] == 48
    # another codec changes every file: everything is encoded again
    assert export(run, out, "--codec", "libx264", address=cluster.scheduler_address) == 0
    assert "3 encoded, 0 unchanged" in capsys.readouterr().out and no_partial(tmp_path)


def test_bad_input_is_one_message_and_nothing_half_written(curated, tmp_path, capsys):
    import shutil

    run0, cluster = curated
    out = tmp_path / "ds"
    cases = [(["--embodiment", "nosuchbot"], "unknown embodiment"),
             (["--embodiment", "panda_allegro"], "has no clip curated with 'panda_allegro'"),
             (["--embodiment", "allegro", "--clip", "synthetic-9999"], "no curated clip synthetic-9999")]
    for args, msg in cases:
        assert main(["export", "lerobot", "--from", str(run0), "--out", str(out), *args]) == 2
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err, err
        assert not out.exists() and no_partial(tmp_path)
    # a folder that is not a dataset is never overwritten
    other = tmp_path / "notes"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    assert export(run0, other) == 2 and "holds no LeRobot dataset" in capsys.readouterr().err
    assert [p.name for p in other.iterdir()] == ["keep.txt"]
    # a run with a hole: refused before anything is written, naming the fix
    run = tmp_path / "run"
    shutil.copytree(run0, run)
    chunk = run / "handedit.zarr" / Unit("harmonize", CLIPS[0], embodiment="allegro").path / "image" / "c" / "0"
    shutil.rmtree(chunk) if chunk.is_dir() else chunk.unlink()
    assert export(run, out) == 2
    err = capsys.readouterr().err
    assert "missing" in err and "harmonize/image" in err and "verify" in err and not out.exists()
    # changed but decodable bytes: the task refuses them; the earlier export stays whole
    good = tmp_path / "good"
    assert export(run0, good, address=cluster.scheduler_address) == 0
    run2 = tmp_path / "run2"
    shutil.copytree(run0, run2)
    img = run2 / "handedit.zarr" / Unit("harmonize", CLIPS[1], embodiment="allegro").path / "image" / "c"
    files = sorted(p for p in img.rglob("*") if p.is_file())
    files[0].write_bytes(files[-1].read_bytes())
    before = sorted(str(p.relative_to(good)) for p in good.rglob("*"))
    assert export(run2, good, "--codec", "libx264", address=cluster.scheduler_address) != 0
    assert "changed after they were written" in capsys.readouterr().err
    assert sorted(str(p.relative_to(good)) for p in good.rglob("*")) == before and no_partial(tmp_path)


def test_release_videos_are_frame_aligned_pairs(curated, tmp_path, capsys):
    from handedit.export.video import decode

    run, cluster = curated
    rel = tmp_path / "releases"
    argv = ["release", "--from", str(run), "--out", str(rel), "--videos", "--address", cluster.scheduler_address]
    assert main(argv) == 0
    m = json.loads((rel / "v0001" / "manifest.json").read_text())
    assert m["counts"]["videos"] == 2 and m["counts"]["videos_reused"] == 0
    pairs = pd.read_parquet(rel / "v0001" / "pairs.parquet")
    for v in m["videos"]:
        ep = store_episode(run, v["clip"])
        index = json.loads((rel / v["index"]).read_text())
        assert index["kept"] == sorted(pairs.loc[pairs["clip"] == v["clip"], "frame"].tolist())
        src, gt, mask = (decode(rel / v["files"][k]["path"]) for k in ("source", "pseudo_gt", "robot_mask"))
        assert len(src) == len(gt) == len(mask) == v["frames"] == len(ep["status"])
        assert np.abs(src.astype(int) - ep["source"]).mean() < 4 and np.abs(gt.astype(int) - ep["pseudo_gt"]).mean() < 4
        robot = read_array(open_store(run)[Unit("composite", v["clip"], embodiment="allegro").path]["robot_mask"]).any(1)
        assert np.array_equal(mask[..., 0] > 127, robot)  # masks are lossless
    assert main(argv) == 0
    m2 = json.loads((rel / "v0002" / "manifest.json").read_text())
    assert m2["counts"]["videos_reused"] == 2 and [v["key"] for v in m2["videos"]] == [v["key"] for v in m["videos"]]
