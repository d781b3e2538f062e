"""Every input in the key: a change re-runs the stages that read it (and what its new data
reaches), an unchanged re-run skips every chunk, and the run says why it recomputed.

Bare loops over the two tasks' bodies (no cluster), on one small synthetic clip, with a copy
of a real robot's assets (Allegro, dex-urdf) so its meshes can be edited in place.
"""

from __future__ import annotations

import shutil
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from handedit.flows.config import CurateConfig
from handedit.flows.curate import code_version, plan_embodiments
from handedit.sources.synthetic import make_clip_specs
from handedit.storage import Location, Unit, create_or_open_store, open_store
from handedit.tasks.clip import ClipJob, EmbodimentJob, run_clip, run_embodiment

EMB = "allegro"


@pytest.fixture()
def robot(tmp_path, robots_dir, monkeypatch) -> Path:
    """Allegro's dex-urdf assets copied to an asset dir of the test's own, found first."""
    dest = tmp_path / "assets"
    shutil.copytree(robots_dir / "hands" / "allegro_hand", dest / "hands" / "allegro_hand")
    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(dest))
    return dest / "hands" / "allegro_hand"


def curate(out: Path, **overrides) -> dict:
    """One run of the clip's task and the embodiment's: chunks ran per stage, and why."""
    spec = make_clip_specs(1, seed=2, n_frames=8, width=64, height=48)[0]
    cfg = CurateConfig(out=str(out), clips=[spec], embodiments=[EMB], frames_per_chunk=4, **overrides)
    loc = Location(cfg.out)
    create_or_open_store(loc, cfg.frames_per_chunk, "test")
    (emb,) = [asdict(e) for e in plan_embodiments(cfg.embodiments)]
    results = [run_clip(ClipJob(loc.store_url, spec.model_dump_json(), cfg.model_dump_json(), ("hand",), code_version())),
               run_embodiment(EmbodimentJob(loc.store_url, spec.id, emb, cfg.model_dump_json(), code_version()))]
    ran, why = {}, {}
    for r in results:
        assert not r["errors"], r["errors"]
        ran.update({stage: c["ran"] for stage, c in r["stages"].items() if c["ran"]})
        why.update(r["recomputed"])
    return {"ran": ran, "why": why, "clip": spec.id}


def test_an_unchanged_rerun_skips_every_chunk(tmp_path, robot):
    first = curate(tmp_path / "run")
    assert first["ran"]["render"] == 2 and not first["why"]
    assert curate(tmp_path / "run") == {"ran": {}, "why": {}, "clip": first["clip"]}


def test_a_robot_mesh_edited_in_place_rerenders(tmp_path, robot):
    import trimesh

    first = curate(tmp_path / "run")
    root = open_store(tmp_path / "run")
    render = Unit("render", first["clip"], embodiment=EMB)
    before = root[render.path]["rgba"][:]
    # same URDF, same file name, new geometry: the palm twice as thick
    mesh_file = robot / "meshes" / "visual" / "base_link.glb"
    scene = trimesh.load(mesh_file)
    scene.apply_transform(np.diag([2.0, 2.0, 2.0, 1.0]))
    scene.export(mesh_file)
    again = curate(tmp_path / "run")
    assert {"ingest", "registration", "segment", "restore_background"}.isdisjoint(again["ran"])
    assert again["ran"]["render"] == 2 and again["ran"]["retarget"] == 2
    assert again["why"]["render[allegro]: robot URDF or meshes changed"] == 2
    after = open_store(tmp_path / "run")[render.path]["rgba"][:]
    assert not np.array_equal(before, after)  # the new mesh was rendered, not a cached one


def test_a_nested_config_version_reruns_retarget(tmp_path, robot, monkeypatch):
    from handedit.retarget.qc import RetargetQCConfig

    curate(tmp_path / "run")
    monkeypatch.setattr(RetargetQCConfig, "VERSION", RetargetQCConfig.VERSION + 1)
    again = curate(tmp_path / "run")
    assert again["why"] == {"retarget[allegro]: config versions changed": 2}
    assert again["ran"]["retarget"] == 2 and "segment" not in again["ran"]


def test_a_setting_is_a_parameter_and_a_speed_switch_changes_no_byte(tmp_path, robot, monkeypatch):
    """How a model runs is run configuration (``onnx``: providers, threads), hence keyed; the
    compiled solvers' switch is speed only: interpreted solvers give the same bytes."""
    from handedit.vision.segment import SegmentConfig

    assert "onnx" in SegmentConfig().model_dump() and SegmentConfig().onnx.providers == ("CPUExecutionProvider",)
    curate(tmp_path / "run")
    monkeypatch.setenv("HANDEDIT_CASADI_COMPILE", "0")
    again = curate(tmp_path / "fresh")
    a, b = open_store(tmp_path / "run"), open_store(tmp_path / "fresh")
    path = Unit("retarget", again["clip"], embodiment=EMB).path
    assert np.array_equal(a[path]["qpos"][:], b[path]["qpos"][:]) and np.array_equal(a[path]["root_pose"][:],
                                                                                     b[path]["root_pose"][:])


def test_a_stage_parameter_reruns_that_stage_and_says_so(tmp_path, robot):
    curate(tmp_path / "run")
    again = curate(tmp_path / "run", harmonize={"strength": 0.5})
    assert again["ran"] == {"harmonize": 2}
    assert again["why"] == {"harmonize[allegro]: parameters strength": 2}
