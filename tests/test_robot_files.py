"""A robot is one data file (issue 36): the built-in files define exactly the robots the Python
roster did; a user's file in a robot folder joins the roster and curates; bad files are one
message naming the file and the field; ``handedit embodiments check`` reports what
``bench/retarget.py`` does and fits the wrist transform."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from handedit.embodiments import EmbodimentError, describe_embodiment, get_embodiment, list_embodiments
from handedit.embodiments.robot_files import (BUILTIN, ROBOT_DIRS_ENV, RobotFileError, current_files, parse_file,
                                              robot_dirs_added, user_dirs)
from handedit.flows.cli import main

SPECS = Path(__file__).with_name("robot_specs.json")
REPO = Path(__file__).resolve().parents[1]
LATER = {"weight_scale"}  # UrdfAsset's per-robot retargeting weights (issue 38)


def canonical_spec(emb) -> str:
    """sha256 of an embodiment's every field (numbers as floats, mappings in order), less the
    files it came from: equal digests, equal robot. Fields added since (``LATER``) count only
    where a robot sets them."""
    def canon(o):
        if dataclasses.is_dataclass(o):
            return {f.name: canon(getattr(o, f.name)) for f in dataclasses.fields(o)
                    if f.name != "files" and not (f.name in LATER and not getattr(o, f.name))}
        if isinstance(o, dict):
            return [[k, canon(v)] for k, v in o.items()]
        if isinstance(o, (list, tuple)):
            return [canon(x) for x in o]
        if isinstance(o, bool) or o is None or isinstance(o, str):
            return o
        return repr(float(o))
    return hashlib.sha256(json.dumps(canon(emb)).encode()).hexdigest()


def test_every_builtin_robot_is_the_one_the_python_roster_defined(robots_dir, monkeypatch):
    """Spec digests from before the move to files (tests/robot_specs.json); joints from the URDFs."""
    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))
    monkeypatch.delenv(ROBOT_DIRS_ENV, raising=False)
    golden = json.loads(SPECS.read_text())["robots"]
    embs = {e.id: e for e in list_embodiments()}
    assert set(embs) == set(golden)
    for key, want in golden.items():
        assert canonical_spec(embs[key]) == want["spec"], key
        if "joints" in want:  # the 24 whose assets are public
            assert describe_embodiment(key)[1] == want["joints"], key
    assert sum("joints" in w for w in golden.values()) == 24


def test_the_roster_is_its_files(monkeypatch):
    monkeypatch.delenv(ROBOT_DIRS_ENV, raising=False)
    kinds = {}
    for p in BUILTIN.rglob("*.yaml"):
        kinds[p.stem] = yaml.safe_load(p.read_text())["kind"]
    assert [e.id for e in list_embodiments()] == sorted(k for k, v in kinds.items() if v == "hand") + \
        sorted(k for k, v in kinds.items() if v == "hand_arm")
    for e in list_embodiments():
        own = Path(e.files[0])
        assert own.stem == e.id and own.is_relative_to(BUILTIN)
        if e.track == "hand_arm":  # an arm and a hand by reference: their colours are the hand file's
            assert yaml.safe_load(own.read_text())["hand"] == Path(e.files[2]).stem
            assert e.materials == get_embodiment(Path(e.files[2]).stem).materials
    assert not list((REPO / "handedit" / "embodiments").glob("asset_table.py"))
    roster_py = (REPO / "handedit" / "embodiments" / "roster.py").read_text()
    assert "wrist_from_root=_T(" not in roster_py and "description=(" not in roster_py  # no robot in Python


def _my_hand(folder: Path, key: str = "myhand", rgba=(0.9, 0.1, 0.1, 1.0)) -> Path:
    data = yaml.safe_load((BUILTIN / "hands" / "allegro.yaml").read_text())
    data["name"] = "My Hand"
    data["materials"] = {r"link_(3|7|11|15)\.0_tip": [0.92, 0.92, 0.9, 1.0], ".*": list(rgba)}
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{key}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_a_robot_added_by_one_file_curates_a_demo_clip(tmp_path, monkeypatch, capsys, prefect_api, dask_cluster):
    """Only a file in a robot folder (given as the run's ``robots:``): the workers, started
    before, learn the folder from the run's configuration."""
    from handedit.flows.config import ClusterConfig, CurateConfig
    from handedit.flows.curate import run_curate
    from handedit.reasons import Reason
    from handedit.sources.synthetic import make_clip_specs
    from handedit.storage import Unit, open_store

    monkeypatch.delenv(ROBOT_DIRS_ENV, raising=False)
    path = _my_hand(tmp_path / "robots")
    with pytest.raises(EmbodimentError, match="unknown embodiment id 'myhand'"):
        get_embodiment("myhand")
    cfg = CurateConfig(out=str(tmp_path / "run"), robots=[str(tmp_path / "robots")], embodiments=["myhand", "allegro"],
                       clips=make_clip_specs(1, seed=3, n_frames=8, width=96, height=72), frames_per_chunk=8,
                       cluster=ClusterConfig(address=dask_cluster.scheduler_address))
    summary = run_curate(cfg)
    assert not summary["errors"], summary["errors"]
    assert ROBOT_DIRS_ENV not in os.environ  # the driver keeps no folder of the run once it is over
    root = open_store(tmp_path / "run")
    clip = "synthetic-0000"
    kept = root[Unit("qc", clip, embodiment="myhand").path]["status"][:] == Reason.OK
    assert kept.sum() >= 4
    mine, allegro = (root[Unit("render", clip, embodiment=e).path]["rgba"][:] for e in ("myhand", "allegro"))
    red = lambda im: ((im[..., 0] > 120) & (im[..., 1] < 80) & (im[..., 3] > 0)).sum()
    assert red(mine[kept]) > 100 and red(allegro[kept]) == 0  # its own colour, the same robot
    assert np.array_equal(mine[..., 3] > 0, allegro[..., 3] > 0)
    monkeypatch.setenv(ROBOT_DIRS_ENV, str(tmp_path / "robots"))
    assert main(["embodiments", "list"]) == 0
    line = next(l for l in capsys.readouterr().out.splitlines() if l.startswith("myhand "))
    assert "My Hand" in line and str(path) in line
    assert main(["embodiments", "show", "allegro", "--file"]) == 0
    assert capsys.readouterr().out.strip() == str(BUILTIN / "hands" / "allegro.yaml")
    # and the release, like a built-in robot's (the folder in $HANDEDIT_ROBOT_DIRS)
    rel = tmp_path / "releases"
    assert main(["release", "--from", str(tmp_path / "run"), "--out", str(rel), "--address", dask_cluster.scheduler_address]) == 0
    pairs = pd.read_parquet(rel / "v0001" / "pairs.parquet")
    mine = pairs[pairs["embodiment"] == "myhand"]
    assert len(mine) == kept.sum() and mine["instruction"].str.contains("My Hand").all()


def test_a_runs_robot_folders_are_looked_up_for_that_run_only(tmp_path, monkeypatch):
    """A process that validates many runs (a Prefect worker serving deployments) keeps no run's
    folders: once an earlier run's folder is deleted, later runs still validate."""
    from pydantic import ValidationError

    from handedit.flows.config import CurateConfig

    monkeypatch.delenv(ROBOT_DIRS_ENV, raising=False)
    _my_hand(tmp_path / "mine")
    cfg = CurateConfig(out=str(tmp_path / "run"), robots=[str(tmp_path / "mine")], embodiments=["myhand"])
    assert cfg.robots == [str((tmp_path / "mine").resolve())] and ROBOT_DIRS_ENV not in os.environ
    shutil.rmtree(tmp_path / "mine")
    assert CurateConfig(out=str(tmp_path / "run"), embodiments=["allegro"]).embodiments == ["allegro"]
    with pytest.raises(ValidationError, match="unknown embodiment id 'myhand'"):
        CurateConfig(out=str(tmp_path / "run"), embodiments=["myhand"])
    with pytest.raises(ValidationError, match=r"robots: .*mine.*not a folder"):
        CurateConfig(out=str(tmp_path / "run"), robots=[str(tmp_path / "mine")], embodiments=["allegro"])
    assert ROBOT_DIRS_ENV not in os.environ


def test_overlapping_runs_on_one_worker_keep_each_others_folders(tmp_path, monkeypatch):
    """A worker's threads run two runs' tasks at once; the one that ends first must not take the
    other's folder away (nor the folders the worker started with)."""
    own, a, b = (tmp_path / n for n in ("own", "a", "b"))
    for d in (own, a, b):
        d.mkdir()
    monkeypatch.setenv(ROBOT_DIRS_ENV, str(own))
    first, second = robot_dirs_added([str(a)]), robot_dirs_added([str(b), str(own)])
    first.__enter__()
    second.__enter__()
    assert user_dirs() == [own, a, b]
    first.__exit__(None, None, None)
    assert user_dirs() == [own, b]
    second.__exit__(None, None, None)
    assert os.environ[ROBOT_DIRS_ENV] == str(own)
    with robot_dirs_added([str(a)]), robot_dirs_added([str(a)]):
        pass
    assert os.environ[ROBOT_DIRS_ENV] == str(own)


def test_a_bad_robot_file_is_one_message_naming_the_file_and_field(tmp_path, monkeypatch):
    folder = tmp_path / "robots"
    path = _my_hand(folder)
    data = yaml.safe_load(path.read_text())
    data["urdf"][0]["wrist_from_root"] = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(RobotFileError, match=r"myhand.yaml: field urdf\.0\.wrist_from_root: .*4x4"):
        parse_file(path)
    path.write_text("kind: hand\nname: [unclosed\n")
    with pytest.raises(RobotFileError, match="myhand.yaml: not valid YAML"):
        parse_file(path)
    path.unlink()
    _my_hand(folder, key="allegro")  # a user file may not replace a built-in
    monkeypatch.setenv(ROBOT_DIRS_ENV, str(folder))
    with pytest.raises(RobotFileError, match=r"'allegro' is defined twice: .*hands/allegro.yaml and .*robots/allegro.yaml"):
        current_files()
    (folder / "allegro.yaml").unlink()
    (folder / "ur5_myhand.yaml").write_text("kind: hand_arm\nname: UR5 + Mine\ndescription: A test.\narm: ur5\nhand: nohand\n")
    with pytest.raises(RobotFileError, match="ur5_myhand.yaml: field hand: no hand file with key 'nohand'"):
        list_embodiments()
    monkeypatch.setenv(ROBOT_DIRS_ENV, str(tmp_path / "missing"))
    with pytest.raises(RobotFileError, match="not a folder"):
        list_embodiments()


def test_a_robot_file_sets_its_own_retargeting_weights(tmp_path, monkeypatch):
    """``retarget_weights`` multiplies the run's keypoint weights for that robot alone (the built-in
    Allegro doubles its tips); a negative multiplier is one message naming the file and field."""
    from handedit.retarget import RetargetConfig, get_retargeter

    folder = tmp_path / "robots"
    path = _my_hand(folder)
    data = yaml.safe_load(path.read_text())
    data["retarget_weights"] = {"tip": 3.0, "pip": 0.0}
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    monkeypatch.setenv(ROBOT_DIRS_ENV, str(folder))
    cfg = RetargetConfig()
    mine, allegro = get_retargeter("myhand", cfg), get_retargeter("allegro", cfg)
    kinds = [k.kind for k in mine.asset.keypoints]
    for kind, m, a in zip(kinds, mine.base_w, allegro.base_w):
        want = cfg.weight(kind) * {"tip": 3.0, "pip": 0.0}.get(kind, 1.0)
        assert m == want and a == cfg.weight(kind) * (2.0 if kind == "tip" else 1.0), kind
    data["retarget_weights"] = {"tip": -1.0}
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(RobotFileError, match=r"myhand.yaml: field retarget_weights: .*>= 0"):
        parse_file(path)


def test_check_reports_the_bench_residual_and_fits_the_wrist(tmp_path, robots_dir, monkeypatch, capsys):
    """On a shipped hand: bench/retarget.py's residual, to the digit; a new hand's file with no
    wrist transform gets the fitted one, within a millimetre and a degree of the shipped one."""
    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))
    monkeypatch.delenv(ROBOT_DIRS_ENV, raising=False)
    sys.path.insert(0, str(REPO / "bench"))
    import retarget as bench  # bench/retarget.py

    from handedit.retarget import RetargetConfig
    from handedit.retarget.quality import synthetic_keypoints

    sheet = tmp_path / "leap.png"
    assert main(["embodiments", "check", str(BUILTIN / "hands" / "leap.yaml"), "--sheet", str(sheet), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    want = bench.bench_hand("leap", synthetic_keypoints(3, 48), RetargetConfig())
    assert report["residual"]["tip_mean"] == pytest.approx(want["tip_mean"], abs=1e-9) and report["dof"] == 16
    assert report["wrist_fit"]["from_file_mm"] < 1.0 and report["wrist_fit"]["from_file_deg"] < 1.0
    import cv2

    img = cv2.imread(str(sheet))
    assert img.shape == (640, 960, 3) and (img[:320] < 100).any() and (img[320:] < 100).any()  # both sides drawn

    data = yaml.safe_load((BUILTIN / "hands" / "leap.yaml").read_text())
    del data["urdf"][0]["wrist_from_root"]  # a new hand: nobody calibrated it
    new = tmp_path / "robots" / "newleap.yaml"
    new.parent.mkdir()
    new.write_text(yaml.safe_dump(data, sort_keys=False))
    assert main(["embodiments", "check", str(new), "--sheet", str(tmp_path / "n.png"), "--no-retarget"]) == 0
    out = capsys.readouterr().out
    assert "wrist_from_root fitted from the palm geometry" in out and "key 'newleap'" in out
    fitted = np.array(yaml.safe_load(out[out.index("  wrist_from_root:"):])["wrist_from_root"])
    shipped = get_embodiment("leap").hand.assets[0].wrist_from_root_matrix
    assert np.linalg.norm(fitted[:3, 3] - shipped[:3, 3]) < 1e-3
    assert np.degrees(np.arccos(np.clip((np.trace(fitted[:3, :3].T @ shipped[:3, :3]) - 1) / 2, -1, 1))) < 1.0


if __name__ == "__main__" and "--regen" in sys.argv:
    import os

    os.environ.setdefault("HANDEDIT_ASSET_DIRS", str(REPO.parent / "shared" / "assets" / "robots"))
    from handedit.embodiments import asset_status

    robots = {}
    for e in list_embodiments():
        robots[e.id] = {"spec": canonical_spec(e), **({"joints": describe_embodiment(e.id)[1]} if asset_status(e)[0] else {})}
    doc = json.loads(SPECS.read_text())
    SPECS.write_text(json.dumps({**doc, "robots": robots}, indent=1) + "\n")
    print(f"wrote {SPECS}: {len(robots)} robots")
