"""The hand-arm track in the curate flow: 1 synthetic clip x 16 frames at 192x144 on
xArm + Ability (composed URDF). One retarget node per sequence reads the whole clip, searches the virtual
base once per sequence and write composed-order joint trajectories that render."""

from __future__ import annotations

import numpy as np
import pytest

from handedit.flows.config import ClusterConfig, CurateConfig
from handedit.flows.curate import run_curate
from handedit.embodiments.kinematics import get_kinematics
from handedit.embodiments.roster import get_embodiment, resolve_urdf
from handedit.reasons import Reason
from handedit.retarget.arm import arm_model
from handedit.retarget.config import RetargetConfig, VirtualBaseConfig
from handedit.sources.synthetic import make_clip_specs
from handedit.storage import Unit, open_store, read_ledger, read_records

W, H, T, F = 192, 144, 16, 8
EMB = "xarm_ability"


def _set_env(value):
    import os

    if value is None:
        os.environ.pop("HANDEDIT_ASSET_DIRS", None)
    else:
        os.environ["HANDEDIT_ASSET_DIRS"] = value


@pytest.fixture(scope="module")
def run(tmp_path_factory, prefect_api, dask_cluster, robots_dir):
    """Assets on the driver and on the (session) workers, as a deployment sets them; restored after."""
    import os

    from distributed import Client

    before = os.environ.get("HANDEDIT_ASSET_DIRS")
    _set_env(str(robots_dir))
    with Client(dask_cluster) as client:
        worker_before = client.run(lambda: os.environ.get("HANDEDIT_ASSET_DIRS"))
        client.run(_set_env, str(robots_dir))
    try:
        out = tmp_path_factory.mktemp("handarm") / "handedit.zarr"
        specs = make_clip_specs(1, seed=3, n_frames=T, width=W, height=H)
        config = CurateConfig(out=out, clips=specs, embodiments=[EMB], frames_per_chunk=F,
                              cluster=ClusterConfig(address=dask_cluster.scheduler_address),
                              retarget=RetargetConfig(virtual_base=VirtualBaseConfig(previews=True)))
        summary = run_curate(config)
        yield config, summary, specs[0].clip_id
    finally:
        _set_env(before)
        with Client(dask_cluster) as client:
            for addr, value in worker_before.items():
                client.run(_set_env, value, workers=[addr])


def test_hand_arm_track(run):
    config, summary, clip = run
    assert summary["stages"]["retarget"]["failed"] == 0, summary.get("errors")
    root = open_store(config.out)
    ret = root[Unit("retarget", clip, embodiment=EMB).path]
    names = list(get_kinematics(resolve_urdf(get_embodiment(EMB))).joint_names)
    assert list(ret.attrs["joint_names"]) == names and ret["qpos"].shape == (T, 1, len(names))  # one hand
    status = ret["status"][:]
    assert (status != Reason.PENDING).all() and (status == Reason.OK).sum() >= T // 2, status
    # one base for the whole sequence: camera_from_base varies only with the camera (world-fixed base)
    src = root[Unit("ingest", clip).path]
    world_from_base = np.einsum("tij,tjk->tik", src["world_from_camera"][:], ret["root_pose"][:, 0])
    np.testing.assert_allclose(world_from_base, np.broadcast_to(world_from_base[0], world_from_base.shape), atol=1e-6)
    np.testing.assert_allclose(world_from_base[0][:3, 2], [0, 0, 1], atol=1e-9)  # upright
    # the arm puts the hand's wrist link where the hand retargeting wanted it
    arm = arm_model(EMB)
    q = ret["qpos"][:, 0].astype(float)
    lo, hi = arm.kin.lower, arm.kin.upper
    assert np.all(q >= np.where(np.isfinite(lo), lo, -np.inf) - 1e-6) and np.all(q <= np.where(np.isfinite(hi), hi, np.inf) + 1e-6)
    recs = read_records(root, Unit("retarget", clip, embodiment=EMB))
    assert sorted(recs) == [0] and (recs[0].start, recs[0].stop) == (0, T)  # one search for the sequence
    vb = [recs[0].extra["virtual_base"]["right"]]  # one base per hand; the synthetic clip has the right one
    assert len(vb[0]["candidates"]) == 27 * (1 + vb[0]["diagnosis"]["refined"]) and vb[0]["selected_by"] == "auto:top1"
    assert vb[0]["chosen"] == vb[0]["ranking"][0]
    assert all("reason_name" in c and "critical_success" in c for c in vb[0]["candidates"])
    # the top-3 candidates' egocentric and third-person previews are in the store
    from handedit.storage.store import read_previews

    pv = read_previews(root, Unit("retarget", clip, embodiment=EMB), "right")
    assert list(pv["candidates"]) == vb[0]["ranking"][:3] and list(pv["frames"]) == [0, T // 2, T - 1]
    assert (pv["ego"][..., 3] > 0).any(axis=(2, 3)).all() and (pv["third"][..., 3] > 0).any(axis=(2, 3)).all()
    assert recs[0].extra["previews"]["right"]["previews/ego"]
    ren = root[Unit("render", clip, embodiment=EMB).path]
    drawn = ren["status"][:] == Reason.OK
    assert drawn.any() and (ren["rgba"][:][drawn][..., 3] > 0).any(axis=(1, 2)).all()
    ledger = read_ledger(root)
    rows = ledger[(ledger["stage"] == "retarget") & (ledger["clip"] == clip)]
    assert sorted(rows["frame"]) == list(np.flatnonzero(ret["hand_status"][:, 0] >= 100))


def test_review_choose_rerun_and_previews(run, dask_cluster, tmp_path, capsys):
    from handedit.flows.cli import main

    config, _, clip = run
    out_dir = str(config.out)
    assert main(["review", out_dir]) == 0
    listing = capsys.readouterr().out
    assert f"{clip} / {EMB} / right: chosen" in listing and "auto:top1" in listing
    vb = read_records(open_store(config.out), Unit("retarget", clip, embodiment=EMB))[0].extra["virtual_base"]["right"]
    assert len(vb["ranking"]) >= 2, "need two valid candidates to exercise a review"
    k = vb["ranking"][1]
    bad = next(i for i in range(27) if i not in vb["ranking"][:3])
    assert main(["review", out_dir, "--clip", clip, "--embodiment", EMB, "--choose", str(bad)]) == 2
    assert "not one of the top-3" in capsys.readouterr().err
    assert main(["review", out_dir, "--clip", clip, "--embodiment", EMB, "--previews", str(tmp_path / "pv")]) == 0
    pngs = sorted((tmp_path / "pv").glob("*.png"))
    assert len(pngs) == 3 * 3 * 2  # top-3 x first/middle/last frame x (egocentric, third-person)
    assert [_video(v) for v in sorted((tmp_path / "pv").glob("*.mp4"))] == [(3, H, 2 * W)] * 3  # a replay per candidate
    assert main(["review", out_dir, "--clip", clip, "--embodiment", EMB, "--choose", str(k)]) == 0
    again = run_curate(config)
    assert again["stages"]["retarget"]["ran"] == 1 and again["stages"]["ingest"]["ran"] == 0
    root = open_store(config.out)
    rec = read_records(root, Unit("retarget", clip, embodiment=EMB))[0].extra["virtual_base"]["right"]
    assert rec["chosen"] == k and rec["selected_by"] == f"review:{k}"
    ret = root[Unit("retarget", clip, embodiment=EMB).path]
    world_from_base = root[Unit("ingest", clip).path]["world_from_camera"][0] @ ret["root_pose"][0, 0]
    np.testing.assert_allclose(world_from_base, rec["candidates"][k]["camera_from_base"], atol=1e-5)


def test_unreviewed_bases_are_held_back_from_releases_and_the_benchmark(run, monkeypatch):
    """``review: manual``: a side whose base waits for ``handedit review`` (``pending:manual``)
    publishes none of its pairs and gives the benchmark none; both count them as held back."""
    import dataclasses

    import handedit.flows.release as rel
    from handedit.storage import Location

    config, _, clip = run
    root = open_store(config.out)
    recs = read_records(root, Unit("retarget", clip, embodiment=EMB))
    assert rel.pending_review(recs) == set()  # auto:top1 is a decision
    vb = recs[0].extra["virtual_base"]
    pending = {0: dataclasses.replace(recs[0], extra={**recs[0].extra,
                                                      "virtual_base": {"right": {**vb["right"], "selected_by": "pending:manual"}}})}
    assert rel.pending_review(pending) == {"right"}
    pairs, source = rel.plan_pairs(Location(str(config.out)), root, [clip], [EMB], 1 << 30)
    assert pairs and source["held_back_unreviewed"] == 0
    monkeypatch.setattr(rel, "read_records", lambda r, u: pending if u.stage == "retarget" else read_records(r, u))
    held, source = rel.plan_pairs(Location(str(config.out)), root, [clip], [EMB], 1 << 30)
    assert held == [] and source["held_back_unreviewed"] == len(pairs)
    # nor are they benchmark items
    import handedit.storage.provenance as provenance
    from handedit.flows.benchmark import StoreItems

    free = StoreItems(root, [clip]).kept(clip, EMB)
    monkeypatch.setattr(provenance, "read_records", lambda r, u: pending if u.stage == "retarget" else read_records(r, u))
    items = StoreItems(root, [clip])
    assert not items.kept(clip, EMB).any() and items.held_back_unreviewed == int(free.sum()) == len(pairs)


def _video(path) -> tuple[int, int, int]:
    import cv2

    cap, n, shape = cv2.VideoCapture(str(path)), 0, None
    while True:
        ok, frame = cap.read()
        if not ok:
            return n, *shape[:2]
        n, shape = n + 1, frame.shape


def test_preview_frames_span_the_sequence():
    from handedit.retarget.preview import preview_frames

    assert preview_frames(16) == [0, 8, 15] and preview_frames(94) == [0, 47, 93]  # first, middle, last
    replay = preview_frames(96, 24)
    assert len(replay) == 24 and replay[0] == 0 and replay[-1] == 95 and np.all(np.diff(replay) >= 4)
    assert preview_frames(10, 24) == list(range(10)) and preview_frames(1, 24) == [0]


def test_manual_review_stores_a_replay_of_each_top_candidate(run, tmp_path, capsys):
    """``review: manual``: where a person will choose the base, each top candidate is stored as a
    short replay (``replay_frames`` frames over the sequence), and ``handedit review --previews``
    writes it as a video: egocentric over the source beside the third-person view."""
    from handedit.flows.cli import main
    from handedit.storage.store import read_previews

    config, _, clip = run
    manual = config.model_copy(update={"retarget": RetargetConfig(virtual_base=VirtualBaseConfig(review="manual",
                                                                                                 replay_frames=6))})
    assert run_curate(manual)["stages"]["retarget"]["ran"] == 1
    pv = read_previews(open_store(config.out), Unit("retarget", clip, embodiment=EMB), "right")
    assert list(pv["frames"]) == [0, 3, 6, 9, 12, 15] and pv["ego"].shape[1] == 6
    assert (pv["ego"][..., 3] > 0).any(axis=(2, 3)).all() and (pv["third"][..., 3] > 0).any(axis=(2, 3)).all()
    assert main(["review", str(config.out), "--clip", clip, "--embodiment", EMB, "--previews", str(tmp_path / "pv")]) == 0
    assert "6 frames (replay)" in capsys.readouterr().out
    videos = sorted((tmp_path / "pv").glob("*.mp4"))
    assert len(videos) == len(pv["candidates"]) and all(_video(v) == (6, H, 2 * W) for v in videos)
    assert len(list((tmp_path / "pv").glob("*.png"))) == len(pv["candidates"]) * 3 * 2  # stills: first, middle, last


def test_auto_runs_render_previews_only_when_asked(run, capsys):
    """Under ``review: auto_top1`` nobody chooses from the previews: by default they are not
    rendered, an earlier run's are dropped, and ``handedit review --previews`` says how to get them."""
    from handedit.flows.cli import main
    from handedit.storage.layout import preview_path

    assert not VirtualBaseConfig().wants_previews() and VirtualBaseConfig(review="manual").wants_previews()
    config, _, clip = run
    plain = config.model_copy(update={"retarget": RetargetConfig()})
    assert run_curate(plain)["stages"]["retarget"]["ran"] == 1
    root = open_store(config.out)
    unit = Unit("retarget", clip, embodiment=EMB)
    assert preview_path(unit, "right") not in root
    assert read_records(root, unit)[0].extra["previews"] == {}
    assert main(["review", str(config.out), "--clip", clip, "--embodiment", EMB, "--previews", "unused"]) == 2
    assert "previews: true" in capsys.readouterr().err
