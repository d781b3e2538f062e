"""The curate flow end to end: real Prefect API, Dask LocalCluster of 2 worker processes.

2 synthetic clips x Allegro (the packaged example-robot-data hand), small frames so
CI stays fast; every array, status and provenance record is checked, then re-runs.
"""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from handedit.flows.config import ClusterConfig, CurateConfig
from handedit.flows.curate import run_curate
from handedit.reasons import Reason
from handedit.sources import VideoSpec
from handedit.sources.synthetic import make_clip_specs
from handedit.storage import Unit, open_store, read_ledger, read_records, stage_arrays
from handedit.storage.layout import arrays_for

W, H, T, F = 192, 144, 16, 8
EMB = "allegro"
CLIPS = ["synthetic-0000", "synthetic-0001"]
STAGES = ("ingest", "registration", "segment", "restore_background", "retarget", "render", "composite", "harmonize", "qc")


def make_config(out, cluster, **kw) -> CurateConfig:
    specs = make_clip_specs(2, seed=3, n_frames=T, width=W, height=H)
    return CurateConfig(out=out, clips=kw.pop("clips", specs), embodiments=[EMB], frames_per_chunk=F,
                        cluster=ClusterConfig(address=cluster.scheduler_address), **kw)


def units_of(clip: str) -> list[Unit]:
    return [
        Unit("ingest", clip), Unit("registration", clip), Unit("segment", clip), Unit("restore_background", clip, scope="hand"),
        *(Unit(s, clip, embodiment=EMB) for s in ("retarget", "render", "composite", "harmonize", "qc")),
    ]


@pytest.fixture(scope="module")
def first_run(tmp_path_factory, prefect_api, dask_cluster):
    out = tmp_path_factory.mktemp("curate") / "handedit.zarr"
    config = make_config(out, dask_cluster)
    summary = run_curate(config)
    return config, summary


def test_every_array_status_and_record(first_run):
    config, summary = first_run
    root = open_store(config.out)
    n_chunks = T // F
    assert summary["stages"]["ingest"] == {"ran": 2 * n_chunks, "skipped": 0, "failed": 0}
    for clip in CLIPS:
        for unit in units_of(clip):
            group = root[unit.path]
            for spec in arrays_for(unit.stage, has_object=True, has_gt=True):
                assert spec.name in group, f"{unit.label} lacks {spec.name}"
                assert group[spec.name].shape[0] == T
            status = group["status"][:]
            assert (status != Reason.PENDING).all(), f"{unit.label} left frames pending: {status}"
            records = read_records(root, unit)
            assert sorted(records) == list(range(n_chunks)), unit.label
            names = {a.name for a in stage_arrays(unit.stage) if a.name in group}
            for k, rec in records.items():
                assert rec.outcome == "ok" and rec.stage == unit.stage and (rec.start, rec.stop) == (k * F, (k + 1) * F)
                assert rec.key and rec.inputs and rec.code_version and rec.host and rec.started
                assert rec.attempts >= 1 and rec.seconds > 0 and 0 <= rec.setup_seconds <= rec.seconds
                assert set(rec.outputs) == names, (unit.label, set(rec.outputs) ^ names)
                assert rec.version >= 1 and isinstance(rec.params, dict)
                # the record's rejections are exactly the chunk's rejected frames
                rejected = [rec.start + i for i in np.flatnonzero(status[rec.start:rec.stop] >= 100)]
                assert [r["frame"] for r in rec.rejections] == rejected


def test_stage_outputs_are_real(first_run):
    config, _ = first_run
    root = open_store(config.out)
    for clip in CLIPS:
        src = root[Unit("ingest", clip).path]
        seg = root[Unit("segment", clip).path]
        ok = seg["status"][:] == Reason.OK
        assert ok.sum() >= T // 2, "segmentation rejected most frames of a synthetic clip"
        gt, pred = src["gt_hand_mask"][:][ok], seg["hand_mask"][:, 0][ok]  # one hand
        iou = (gt & pred).sum() / max((gt | pred).sum(), 1)
        assert iou > 0.5, f"hand-mask IoU {iou:.2f} against ground truth"
        ret = root[Unit("retarget", clip, embodiment=EMB).path]
        assert (ret["status"][:] == Reason.OK).sum() >= T // 2
        assert np.isfinite(ret["qpos"][:]).all() and ret["qpos"].shape[1:] == (1, len(ret.attrs["joint_names"]))
        ren = root[Unit("render", clip, embodiment=EMB).path]
        drawn = ren["status"][:] == Reason.OK
        assert drawn.any() and (ren["rgba"][:][drawn][..., 3] > 0).any(axis=(1, 2)).all()
        comp = root[Unit("composite", clip, embodiment=EMB).path]
        harm = root[Unit("harmonize", clip, embodiment=EMB).path]
        qc = root[Unit("qc", clip, embodiment=EMB).path]["status"][:]
        kept = qc == Reason.OK
        assert kept.any(), f"no frame of {clip} survived QC"
        robot = comp["robot_mask"][:, 0][kept]
        assert robot.any(axis=(1, 2)).all()
        # outside the robot the composite keeps the restored scene, not the human hand
        bg = root[Unit("restore_background", clip, scope="hand").path]["background"][:][kept]
        img = comp["image"][:][kept]
        assert np.abs(img[~robot].astype(int) - bg[~robot]).mean() < 2.0
        assert harm["image"][:][kept].shape == img.shape
    ds = xr.open_zarr(str(config.out), group=Unit("ingest", CLIPS[0]).path, consolidated=False)
    assert ds["keypoints"].dims == ("frame", "hand", "joint", "xyz")


def test_ledger_matches_statuses(first_run):
    config, _ = first_run
    root = open_store(config.out)
    ledger = read_ledger(root)
    for clip in CLIPS:
        for unit in units_of(clip):
            group = root[unit.path]
            # per-hand stages record their hands' rejections; the others their frames'
            status = group["hand_status"][:, 0] if "hand_status" in group else group["status"][:]
            rows = ledger[(ledger["stage"] == unit.stage) & (ledger["clip"] == clip)]
            assert sorted(rows["frame"]) == list(np.flatnonzero(status >= 100))
            assert set(rows["side"]) <= ({"right"} if "hand_status" in group else {""})
    assert (ledger["reason"] >= 100).all()


def test_rerun_skips_everything_and_harmonize_change_reruns_only_harmonize(first_run, dask_cluster):
    config, _ = first_run
    before = {u: read_records(open_store(config.out), u) for c in CLIPS for u in units_of(c)}
    again = run_curate(config)
    # the shard is complete for this exact plan: one manifest read, no task runs at all
    assert again["shards"] == {"ran": 0, "skipped": 1, "held": 0, "incomplete": 0} and again["stages"] == {}
    after = {u: read_records(open_store(config.out), u) for u in before}
    assert all(after[u][k].started == before[u][k].started for u in before for k in before[u])

    harm_cfg = config.harmonize.model_copy(update={"strength": 0.35 if config.harmonize.strength != 0.35 else 0.6})
    changed = run_curate(config.model_copy(update={"harmonize": harm_cfg}))
    ran = {s: c["ran"] for s, c in changed["stages"].items()}
    assert ran["harmonize"] == 2 * (T // F)
    assert all(n == 0 for s, n in ran.items() if s != "harmonize"), ran
    root = open_store(config.out)
    for clip in CLIPS:
        rec = read_records(root, Unit("harmonize", clip, embodiment=EMB))[0]
        assert rec.params["strength"] == harm_cfg.strength


def test_fault_in_one_clip_and_corrupt_source_leave_the_rest_complete(tmp_path, prefect_api, dask_cluster):
    bad_video = tmp_path / "broken.mp4"
    bad_video.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 40)
    specs = [*make_clip_specs(2, seed=3, n_frames=T, width=W, height=H), VideoSpec(path=bad_video, clip_id="broken")]
    config = make_config(tmp_path / "handedit.zarr", dask_cluster, clips=specs, inject_faults=["segment:synthetic-0001"])
    summary = run_curate(config)
    assert summary["stages"]["segment"]["failed"] == T // F
    root = open_store(config.out)
    ledger = read_ledger(root)
    # the failing clip: every frame rejected at segment with the error, downstream marks UPSTREAM
    seg_rows = ledger[(ledger["clip"] == "synthetic-0001") & (ledger["stage"] == "segment")]
    assert sorted(seg_rows["frame"]) == list(range(T))
    assert set(seg_rows["reason_name"]) == {"STAGE_ERROR"} and seg_rows["detail"].str.contains("InjectedFault").all()
    assert (root[Unit("qc", "synthetic-0001", embodiment=EMB).path]["status"][:] == Reason.UPSTREAM).all()
    assert (root[Unit("restore_background", "synthetic-0001", scope="hand").path]["status"][:] == Reason.UPSTREAM).all()
    # the corrupt video: one clip-level rejection naming the file
    broken = ledger[ledger["clip"] == "broken"]
    assert list(broken["reason_name"]) == ["SOURCE_UNREADABLE"] and "broken.mp4" in broken["detail"].iloc[0]
    # the healthy clip is complete
    qc = root[Unit("qc", "synthetic-0000", embodiment=EMB).path]["status"][:]
    assert (qc != Reason.PENDING).all() and (qc == Reason.OK).any()
    assert not ledger[(ledger["clip"] == "synthetic-0000") & (ledger["reason"] == Reason.STAGE_ERROR)].size

    # without the fault, a re-run redoes the failed chunks and what reads them, nothing else
    fixed = run_curate(config.model_copy(update={"inject_faults": []}))
    assert fixed["stages"]["segment"] == {"ran": T // F, "skipped": T // F, "failed": 0}
    # retarget reads which hands were segmented: only the fixed clip's chunks re-run
    assert fixed["stages"]["retarget"]["ran"] == T // F and fixed["stages"]["ingest"]["ran"] == 0
    root = open_store(config.out)
    assert (root[Unit("qc", "synthetic-0001", embodiment=EMB).path]["status"][:] != Reason.UPSTREAM).any()


def test_missing_assets_reject_only_that_embodiment(tmp_path, monkeypatch, prefect_api, dask_cluster):
    monkeypatch.delenv("HANDEDIT_ASSET_DIRS", raising=False)  # shadow ships only with dex-urdf assets
    clip = make_clip_specs(1, seed=5, n_frames=F, width=W, height=H)
    config = make_config(tmp_path / "handedit.zarr", dask_cluster, clips=clip).model_copy(
        update={"embodiments": [EMB, "shadow"]})
    summary = run_curate(config)
    root = open_store(config.out)
    ledger = read_ledger(root)
    missing = ledger[ledger["embodiment"] == "shadow"]
    assert set(missing["reason_name"]) == {"ASSETS_MISSING"} and sorted(missing["frame"]) == list(range(F))
    assert "HANDEDIT_ASSET_DIRS" in missing["detail"].iloc[0] or "shadow" in missing["detail"].iloc[0]
    assert (root[Unit("qc", clip[0].clip_id, embodiment="shadow").path]["status"][:] == Reason.UPSTREAM).all()
    assert (root[Unit("qc", clip[0].clip_id, embodiment=EMB).path]["status"][:] == Reason.OK).any()
    assert summary["stages"]["retarget"]["failed"] == 1


def test_real_video_without_keypoints(tmp_path, real_video, prefect_api, dask_cluster):
    """With hand estimation off (tests/test_estimate_hands.py runs it on): removed, not retargeted."""
    clip = VideoSpec(path=real_video, clip_id="real", max_frames=F)
    config = make_config(tmp_path / "handedit.zarr", dask_cluster, clips=[clip], estimate_hands={"mode": "never"})
    run_curate(config)
    root = open_store(config.out)
    frames = root[Unit("ingest", "real").path]["frames"]
    assert frames.shape == (F, 720, 1280, 3) and frames[F - 1].std() > 10  # real pixels
    seg = root[Unit("segment", "real").path]
    hand_fraction = seg["handarm_mask"][:, 0].mean(axis=(1, 2))
    assert ((hand_fraction > 0.005) & (hand_fraction < 0.6)).all(), hand_fraction  # found a hand, not the scene
    assert (seg["hand_status"][:] == Reason.OK).all()  # segmented by skin colour, and removed
    # no keypoints: the hand is not retargeted; the ledger names the cause once, at registration
    assert (root[Unit("registration", "real").path]["hand_status"][:] == Reason.NO_KEYPOINTS).all()
    assert (root[Unit("retarget", "real", embodiment=EMB).path]["status"][:] == Reason.UPSTREAM).all()
    ledger = read_ledger(root)
    rows = ledger[(ledger["stage"] == "registration") & (ledger["clip"] == "real")]
    assert sorted(rows["frame"]) == list(range(F)) and set(rows["reason_name"]) == {"NO_KEYPOINTS"}
    assert not len(ledger[(ledger["stage"] == "retarget") & (ledger["clip"] == "real")])
    assert (root[Unit("qc", "real", embodiment=EMB).path]["status"][:] == Reason.UPSTREAM).all()
