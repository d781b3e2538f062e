"""The curate flow with every learned plug-in configured (tiny ONNX models from code).

Only the stage configs change (``method="onnx"``, ``model_path``): the flow, the tasks
and the store are the same. The clip is a synthetic clip written to a video file with
one frame blanked, plus its keypoints sidecar, so the blank frame is rejected with a
reason at ingest and the rest of the clip still goes through every stage.
"""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import cv2
import numpy as np
import pytest

from handedit.flows.config import ClusterConfig, CurateConfig
from handedit.flows.curate import run_curate
from handedit.models import file_sha256, toy
from handedit.reasons import Reason
from handedit.sources import VideoSpec
from handedit.sources.synthetic import make_clip_specs
from handedit.vision.harmonize import HarmonizeConfig
from handedit.vision.restore_background import RestoreConfig
from handedit.vision.segment import SegmentConfig
from handedit.storage import Unit, open_store, read_ledger, read_records

W, H, T, F, BLANK = 192, 144, 8, 8, 3
EMB = "allegro"


@pytest.fixture(scope="module")
def onnx_run(tmp_path_factory, prefect_api, dask_cluster):
    d = tmp_path_factory.mktemp("onnx")
    spec = make_clip_specs(1, seed=3, n_frames=T, width=W, height=H)[0]
    src = spec.open()
    info, chunk = src.info(), src.read(0, T)
    video = d / "clip.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (W, H))
    for i, f in enumerate(chunk.frames):
        w.write(np.zeros_like(f) if i == BLANK else cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    w.release()
    k = info.intrinsics
    K = np.array([[k.fx, 0, k.cx], [0, k.fy, k.cy], [0, 0, 1.0]])
    np.savez(d / "clip.npz", keypoints=chunk.keypoints, valid=chunk.keypoints_valid, K=K)
    models = {
        "segment": toy.make_segmenter(d / "segmenter.onnx"),
        "restore_background": toy.make_inpainter(d / "inpainter.onnx"),
        "harmonize": toy.make_harmonizer(d / "harmonizer.onnx"),
    }
    config = CurateConfig(
        out=d / "handedit.zarr", clips=[VideoSpec(path=video, keypoints_path=d / "clip.npz", clip_id="clip")],
        embodiments=[EMB], frames_per_chunk=F, cluster=ClusterConfig(address=dask_cluster.scheduler_address),
        segment=SegmentConfig(method="onnx", model_path=str(models["segment"])),
        restore_background=RestoreConfig(method="onnx", model_path=str(models["restore_background"])),
        harmonize=HarmonizeConfig(method="onnx", model_path=str(models["harmonize"])),
    )
    return config, run_curate(config), models


def test_every_stage_runs_the_models_and_records_their_hashes(onnx_run):
    config, summary, models = onnx_run
    assert all(s["failed"] == 0 for s in summary["stages"].values()), summary["stages"]
    root = open_store(config.out)
    for stage, unit in (("segment", Unit("segment", "clip")),
                        ("restore_background", Unit("restore_background", "clip", scope="hand")),
                        ("harmonize", Unit("harmonize", "clip", embodiment=EMB))):
        recs = read_records(root, unit)
        assert sorted(recs) == list(range(T // F))
        for rec in recs.values():
            assert rec.method.startswith("onnx:") and file_sha256(models[stage])[:16] in rec.method, (stage, rec.method)
            assert rec.params["model_path"] == str(models[stage])
    qc = root[Unit("qc", "clip", embodiment=EMB).path]["status"][:]
    assert (qc == Reason.OK).sum() >= T // 2, qc
    harm = root[Unit("harmonize", "clip", embodiment=EMB).path]["image"][:]
    comp = root[Unit("composite", "clip", embodiment=EMB).path]
    kept = qc == Reason.OK
    robot = comp["robot_mask"][:, 0][kept]
    assert robot.any() and (harm[kept][robot] != comp["image"][:][kept][robot]).any(), "harmonizer changed nothing"


def test_blank_frame_rejected_with_reason_rest_of_clip_proceeds(onnx_run):
    config, _, _ = onnx_run
    root = open_store(config.out)
    ingest = root[Unit("ingest", "clip").path]["status"][:]
    assert ingest[BLANK] == Reason.BLANK_FRAME and (np.delete(ingest, BLANK) == Reason.OK).all()
    ledger = read_ledger(root)
    rows = ledger[ledger["clip"] == "clip"]
    assert list(rows[rows["frame"] == BLANK]["reason_name"]) == ["BLANK_FRAME"]
    qc = root[Unit("qc", "clip", embodiment=EMB).path]["status"][:]
    assert qc[BLANK] == Reason.UPSTREAM
    # its chunk-mates still made it through every stage
    same_chunk = [i for i in range(F) if i != BLANK]
    assert (qc[same_chunk] == Reason.OK).sum() >= len(same_chunk) // 2, qc


def test_new_weights_at_the_same_path_rerun_only_that_stage(onnx_run, tmp_path):
    config, _, models = onnx_run
    path = models["harmonize"]
    original = path.read_bytes()
    try:
        toy.make_harmonizer(tmp_path / "other.onnx", pull=0.8)
        path.write_bytes((tmp_path / "other.onnx").read_bytes())
        assert path.read_bytes() != original
        summary = run_curate(config)
        ran = {s: c["ran"] for s, c in summary["stages"].items()}
        assert ran["harmonize"] == T // F and all(n == 0 for s, n in ran.items() if s != "harmonize"), ran
    finally:
        path.write_bytes(original)
