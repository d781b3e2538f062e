"""estimate_hands: MediaPipe's hand models without mediapipe, lifting to 3-D, sides, smoothing,
QC, the ONNX plug-in, `handedit models fetch`, and curate runs on the real video."""

from __future__ import annotations

import math
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from handedit.camera import Intrinsics, project
from handedit.models import fetch as model_fetch
from handedit.models.mediapipe_hands import HandModelError, HandModelFiles, Rect, palm_anchors
from handedit.reasons import Reason
from handedit.sources import VideoSpec
from handedit.sources.synthetic import make_clip_specs
from handedit.vision.estimate_hands import (HUMAN_BONES_M, EstimateHandsConfig, _Det, aligned_error_mm, assign_sides,
                                            bone_lengths, estimate_hands, lift_bones, lift_pnp, one_euro)

INTR = Intrinsics(440.0, 440.0, 320.0, 240.0, 640, 480)


@pytest.fixture(scope="module")
def hand_models() -> Path:
    d = EstimateHandsConfig().hand_model_dir()
    try:
        HandModelFiles.in_dir(d)
    except HandModelError as exc:
        pytest.fail(f"{exc} (deploy/setup.sh runs it)", pytrace=False)
    return d


def _frames(video: Path, n: int, size=(640, 360)) -> np.ndarray:
    cap = cv2.VideoCapture(str(video))
    out = []
    for _ in range(n):
        ok, f = cap.read()
        assert ok
        out.append(cv2.cvtColor(cv2.resize(f, size, interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB))
    return np.stack(out)


# ----------------------------------------------------------------------------- graph pieces


def test_palm_anchors_and_rectangle_geometry():
    a = palm_anchors()
    assert a.shape == (2016, 2)
    assert np.allclose(a[0], [0.5 / 24, 0.5 / 24]) and np.allclose(a[1], a[0])  # two anchors per stride-8 cell
    assert np.allclose(a[1152], [0.5 / 12, 0.5 / 12]) and np.allclose(a[1152:1158], a[1152])  # six per stride-16 cell
    r = Rect(100.0, 50.0, 80.0, 80.0, math.pi / 2)
    A = r.crop_from_image(224)
    centre = A[:, :2] @ [112, 112] + A[:, 2]
    up = A[:, :2] @ [112, 0] + A[:, 2]  # the crop's top edge centre
    assert np.allclose(centre, [100, 50]) and np.allclose(up, [140, 50])  # rotated 90 deg: crop-up is image +x
    assert np.allclose(r.box(), [60, 10, 140, 90])


def test_lift_pnp_recovers_a_rigidly_moved_hand():
    spec = make_clip_specs(1, n_frames=4)[0]
    c = spec.open().read(0, 4)
    gt = c.keypoints[2, 0].astype(np.float64)
    c_ = gt.mean(0)
    ang = 0.7
    R = np.array([[math.cos(ang), 0, math.sin(ang)], [0, 1, 0], [-math.sin(ang), 0, math.cos(ang)]])
    world = (gt - c_) @ R.T  # hand-centred, in other axes: what the model's world landmarks are
    cam, err = lift_pnp(project(gt, INTR), world, INTR)
    assert err < 0.05 and np.abs(cam - gt).max() < 1e-3


def test_lift_bones_puts_joints_on_their_rays_at_human_bone_lengths():
    spec = make_clip_specs(3, n_frames=8)[2]
    c = spec.open().read(0, 8)
    errs = []
    for i in range(8):
        gt = c.keypoints[i, 0].astype(np.float64)
        cam, err = lift_bones(project(gt, INTR), gt - gt.mean(0), INTR)
        assert err < 1e-6  # on the rays
        lengths = bone_lengths(cam)[1:]
        reached = np.isclose(lengths, HUMAN_BONES_M[1:], atol=1e-9)
        assert reached.sum() >= 12 and (lengths >= HUMAN_BONES_M[1:] - 1e-9).all()  # one too short ends nearest its ray
        errs.append(abs(cam[0, 2] - gt[0, 2]) / gt[0, 2])
    # the synthetic hand is not the prior's: depth from a typical hand's size (measured 0.10-0.25)
    assert np.mean(errs) < 0.3, errs


def test_one_euro_smooths_a_still_hand_follows_a_moving_one_and_restarts_after_gaps():
    rng = np.random.default_rng(0)
    T = 90
    still = 0.4 + rng.normal(0, 0.004, (T, 1, 3))
    valid = np.ones(T, bool)
    out = one_euro(still, valid, 30.0, 1.5, 8.0)
    assert out[10:].std(0).max() < 0.5 * still[10:].std(0).max()
    ramp = np.linspace(0, 0.6, T)[:, None, None] * np.ones((1, 1, 3))  # 0.2 m/s
    lag = np.abs(one_euro(ramp, valid, 30.0, 1.5, 8.0) - ramp)[30:].max()
    assert lag < 0.02
    valid[40] = False
    jump = np.where(np.arange(T)[:, None, None] > 40, 1.0, 0.0) * np.ones((1, 1, 3))
    assert np.allclose(one_euro(jump, valid, 30.0, 1.5, 8.0)[41], 1.0)  # a new track, not a glide from the old one


def test_sides_are_voted_per_track_and_split_within_a_frame():
    d = lambda f, t, p: _Det(f, t, None, None, 0.9, p, None)  # noqa: E731
    dets = [d(f, 0, 0.8 if f != 3 else 0.3) for f in range(6)]  # a right hand whose label flickers once
    dets += [d(f, 1, 0.7) for f in range(2, 6)]  # a second hand the classifier also calls right, less surely
    assert assign_sides(dets) == {0: 1, 1: 0}
    # a long, sure track keeps its side against a short one that is surer per frame (the real video's case)
    dets = [d(f, 0, 0.95) for f in range(600)] + [d(f, 1, 0.99) for f in range(100, 104)]
    assert assign_sides(dets) == {0: 1, 1: 0}


def test_qc_reasons_per_side_and_frame():
    """A stand-in detector: a weak hand, a good one, one whose 2-D fingers no hand could
    reach at its palm's depth, and a frame without any hand."""
    from handedit.models.mediapipe_hands import HandLandmarks

    c = make_clip_specs(1, n_frames=4)[0].open().read(0, 4)
    gt = c.keypoints[1, 0].astype(np.float64)
    xy = project(gt, INTR)
    stretched = xy.copy()
    for tip, mcp in ((8, 5), (12, 9), (16, 13), (20, 17)):
        stretched[mcp + 1:tip + 1] = xy[mcp] + 3.0 * (xy[mcp + 1:tip + 1] - xy[mcp])
    rect = Rect(float(xy[:, 0].mean()), float(xy[:, 1].mean()), 120.0, 120.0, 0.0)
    lm = lambda uv, presence: HandLandmarks(uv, np.zeros(21), gt - gt.mean(0), presence, 0.9, rect)  # noqa: E731
    script = [[(0, lm(xy, 0.3))], [(0, lm(xy, 0.95))], [(0, lm(stretched, 0.95))], []]
    frames = iter(np.zeros((4, 480, 640, 3), np.uint8))
    est = estimate_hands(frames, 4, INTR, 30.0, detector=lambda rgb, s=iter(script): next(s))
    right = list(est.hand_status[:, 1])
    assert right == [Reason.LOW_HAND_CONFIDENCE, Reason.OK, Reason.IMPLAUSIBLE_HAND, Reason.NO_HAND_DETECTED]
    assert list(est.hand_status[:, 0]) == [Reason.ABSENT] * 3 + [Reason.NO_HAND_DETECTED]
    assert "presence 0.30" in est.details[(0, 1)] and "bone lengths" in est.details[(2, 1)] and "[6, 7" in est.details[(2, 1)]
    assert est.keypoints_valid[1, 1].all() and not est.keypoints_valid[[0, 2, 3]].any()


def test_missing_models_name_the_fetch_command(tmp_path):
    with pytest.raises(HandModelError, match="handedit models fetch"):
        HandModelFiles.in_dir(tmp_path)
    cfg = EstimateHandsConfig(model_dir=tmp_path)
    assert cfg.model_digests() == {"hand_models": "missing"}
    with pytest.raises(HandModelError, match=str(tmp_path)):
        estimate_hands(iter([]), 0, INTR, 30.0, cfg)


def test_models_fetch_from_a_wheel_checks_digests(tmp_path, hand_models):
    good = tmp_path / "mediapipe-0.10.21-cp311-cp311-manylinux_2_28_x86_64.whl"
    with zipfile.ZipFile(good, "w") as z:
        for name, (inner, _) in model_fetch.MODELS.items():
            z.write(hand_models / name, inner)
    dest = tmp_path / "models"
    r = model_fetch.fetch(dest, good)
    assert sorted(r.fetched) == sorted(model_fetch.MODELS) and (dest / "PROVENANCE.json").is_file()
    assert "Apache-2.0" in (dest / "PROVENANCE.json").read_text()
    assert model_fetch.fetch(dest, good).fetched == []  # in place: nothing again
    bad = tmp_path / "bad.whl"
    with zipfile.ZipFile(bad, "w") as z:
        for name, (inner, _) in model_fetch.MODELS.items():
            z.writestr(inner, b"not the model")
    with pytest.raises(model_fetch.ModelFetchError, match="sha256"):
        model_fetch.fetch(tmp_path / "other", bad)
    assert not (tmp_path / "other" / "palm_detection_full.tflite").exists()


# ----------------------------------------------------------------------------- on pixels


def test_real_video_keypoints_reproject_inside_the_segmented_hand(real_video, hand_models):
    """On the real video, the estimated joints project onto the hand that skin-colour
    segmentation (no keypoints involved) finds, and the hand is called right every frame."""
    from handedit.vision.segment import segment

    frames = _frames(real_video, 24)
    intr = Intrinsics.default_for(640, 360)
    est = estimate_hands(iter(frames), len(frames), intr, 30.0)
    right = est.hand_status[:, 1]
    assert (right == Reason.OK).mean() >= 0.9 and (est.hand_status[:, 0] == Reason.ABSENT).all()
    seg = segment(frames, None, None)
    inside = []
    for i in np.flatnonzero(right == Reason.OK):
        mask = cv2.dilate(seg.handarm_mask[i, 0].astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        uv = np.round(project(est.keypoints[i, 1], intr)).astype(int)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 360)
        inside.append(mask[uv[ok, 1], uv[ok, 0]].mean())
    assert np.mean(inside) > 0.9, inside  # measured 0.98
    assert np.isfinite(est.keypoints_raw[right == Reason.OK]).all()
    assert est.method.startswith("mediapipe-hands:palm_detection_full.tflite") and "bones" in est.method


def test_synthetic_hand_errors_against_ground_truth(hand_models):
    """The synthetic skin-coloured hand (exact keypoints): detection, 3-D shape after a
    rigid alignment, wrist depth. Floors from bench/estimate_hands.py with margin: the
    stylized hand is hard for MediaPipe (measured: 43/64 hand-frames kept, aligned error
    26-34 mm, wrist depth 37-60 %)."""
    kept, mm, depth = 0, [], []
    for spec in (make_clip_specs(3, n_frames=32)[i] for i in (0, 2)):
        src = spec.open()
        info, c = src.info(), src.read(0, 32)
        est = estimate_hands(iter(c.frames), 32, info.intrinsics, info.fps)
        for i in range(32):
            gt = c.keypoints[i, 0].astype(np.float64)
            for k in np.flatnonzero(est.keypoints_valid[i].all(-1)):  # either side (the stylized hand's side is a guess)
                e = est.keypoints_raw[i, k].astype(np.float64)
                if np.linalg.norm(project(e, info.intrinsics) - project(gt, info.intrinsics), axis=1).mean() > 40:
                    continue  # not this hand
                kept += 1
                mm.append(aligned_error_mm(e, gt))
                depth.append(abs(e[0, 2] - gt[0, 2]) / gt[0, 2])
    assert kept >= 30, kept
    assert np.mean(mm) < 45, np.mean(mm)
    assert np.mean(depth) < 0.75, np.mean(depth)


def _plugin_model(path: Path, joints: np.ndarray, camera: np.ndarray) -> None:
    """A test model honouring the contract: constant joints and camera, whatever the crop."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    nodes = [
        helper.make_node("ReduceMean", ["image"], ["m"], axes=[1, 2, 3], keepdims=0),
        helper.make_node("Mul", ["m", "zero"], ["z"]),
        helper.make_node("Unsqueeze", ["z", "ax12"], ["z3"]),
        helper.make_node("Add", ["z3", "J"], ["joints"]),
        helper.make_node("Unsqueeze", ["z", "ax1"], ["z2"]),
        helper.make_node("Add", ["z2", "C"], ["camera"]),
    ]
    inits = [numpy_helper.from_array(np.array(0, np.float32), "zero"), numpy_helper.from_array(np.array([1, 2]), "ax12"),
             numpy_helper.from_array(np.array([1]), "ax1"),
             numpy_helper.from_array(joints[None].astype(np.float32), "J"),
             numpy_helper.from_array(camera[None].astype(np.float32), "C")]
    g = helper.make_graph(nodes, "hand_pose", [helper.make_tensor_value_info("image", TensorProto.FLOAT, ["N", 3, 256, 256])],
                          [helper.make_tensor_value_info("joints", TensorProto.FLOAT, ["N", 21, 3]),
                           helper.make_tensor_value_info("camera", TensorProto.FLOAT, ["N", 3])], inits)
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 13)])
    m.ir_version = 8
    onnx.save(m, str(path))


def test_onnx_hand_pose_plugin_places_joints_like_hamer(tmp_path, real_video, hand_models):
    from handedit.models.hand_pose import HandPoseLifter, square_box, to_camera
    from handedit.models.runtime import ModelContractError

    flat = np.c_[np.random.default_rng(1).uniform(-0.05, 0.05, (21, 2)), np.zeros(21)]  # no depth spread: exact check
    cam = np.array([1.6, 0.02, -0.03])
    box = (400.0, 200.0, 120.0)
    intr = Intrinsics(500.0, 500.0, 330.0, 170.0, 640, 360)
    for mirror in (False, True):
        P = to_camera(flat, cam, box, intr, mirror)
        X = flat[:, 0] * (-1 if mirror else 1)
        tx = cam[1] * (-1 if mirror else 1)
        want = np.c_[box[0] + cam[0] * box[2] / 2 * (X + tx), box[1] + cam[0] * box[2] / 2 * (flat[:, 1] + cam[2])]
        assert np.allclose(project(P, intr), want, atol=1e-6)  # the crop's weak perspective, in the full image
    path = tmp_path / "hand_pose.onnx"
    _plugin_model(path, flat, cam)
    frames = _frames(real_video, 6)
    intr = Intrinsics.default_for(640, 360)
    lifter = HandPoseLifter(path, intr)
    est = estimate_hands(iter(frames), 6, intr, 30.0, EstimateHandsConfig(bone_ratio=50, max_reprojection_px=1e4),
                         lifter=lifter)
    ok = np.flatnonzero(est.hand_status[:, 1] == Reason.OK)
    assert len(ok) >= 5 and "onnx-plugin" in est.method
    for i in ok:  # the plug-in's joints, placed from the frame's hand box
        b = square_box(est.box[i, 1], pad=1.0 / 1.3)
        assert np.allclose(est.keypoints_raw[i, 1], to_camera(flat, cam, b, intr, False), atol=1e-4)
    bad = tmp_path / "bad.onnx"
    _plugin_model(bad, flat, cam)
    import onnx

    m = onnx.load(str(bad))
    m.graph.output[1].name = "cam"
    m.graph.node[-1].output[0] = "cam"
    onnx.save(m, str(bad))
    with pytest.raises(ModelContractError, match="camera"):
        HandPoseLifter(bad, intr)


def _real_then_empty_video(real_video: Path, out: Path, n: int) -> Path:
    """n real frames, then n frames of the same scene without the hand (its left part)."""
    cap = cv2.VideoCapture(str(real_video))
    w = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (640, 360))
    for i in range(2 * n):
        ok, f = cap.read()
        assert ok
        f = cv2.resize(f if i < n else f[:315, :560], (640, 360), interpolation=cv2.INTER_AREA)
        w.write(f)
    w.release()
    return out


def test_curate_real_video_with_estimated_hands(tmp_path, real_video, hand_models, prefect_api, dask_cluster):
    """Keypoints from the pixels: every stage keeps the hand frames (a robot on real pixels);
    the frames without a hand are rejected once, at estimate_hands, with the reason."""
    from handedit.flows.config import ClusterConfig, CurateConfig
    from handedit.flows.curate import run_curate
    from handedit.storage import Unit, open_store, read_ledger, read_records

    n = 8
    video = _real_then_empty_video(real_video, tmp_path / "real_then_empty.mp4", n)
    config = CurateConfig(out=str(tmp_path / "handedit.zarr"), clips=[VideoSpec(path=video, clip_id="real", hfov_deg=65)],
                          embodiments=["allegro"], frames_per_chunk=8, cluster=ClusterConfig(address=dask_cluster.scheduler_address))
    run_curate(config)
    root = open_store(config.out)
    est = root[Unit("estimate_hands", "real").path]
    assert list(root[Unit("ingest", "real").path].attrs["hands"]) == ["left", "right"]
    hs = est["hand_status"][:]
    assert (hs[:n, 1] == Reason.OK).all() and (hs[n:] == Reason.NO_HAND_DETECTED).all()
    rec = read_records(root, Unit("estimate_hands", "real"))[0]
    assert "mediapipe-hands" in rec.method and "hfov 65" in rec.extra["intrinsics_origin"]
    for stage in ("registration", "segment", "retarget", "render", "composite", "harmonize", "qc"):
        u = Unit(stage, "real", embodiment="allegro") if stage in ("retarget", "render", "composite", "harmonize", "qc") \
            else Unit(stage, "real")
        status = root[u.path]["status"][:]
        assert (status[:n] == Reason.OK).all(), (stage, status)
        assert (status[n:] == Reason.UPSTREAM).all(), (stage, status)
    robot = root[Unit("composite", "real", embodiment="allegro").path]["robot_mask"][:n, 1]
    assert (robot.mean(axis=(1, 2)) > 0.005).all()  # a robot hand on every hand frame
    ledger = read_ledger(root)
    rows = ledger[ledger["clip"] == "real"]
    assert set(rows["stage"]) == {"estimate_hands"} and set(rows["reason_name"]) == {"NO_HAND_DETECTED"}
    assert sorted(set(rows["frame"])) == list(range(n, 2 * n)) and "no hand detected" in rows["detail"].iloc[0]


def test_cli_options_reach_the_config_and_models_fetch_runs(tmp_path, capsys, hand_models):
    from handedit.flows.cli import _build_config, main, parser

    args = parser().parse_args(["curate", "--video", "v.mp4", "--fov", "90", "--estimate-hands", "always",
                                "--hand-pose-model", "hp.onnx", "--out", str(tmp_path / "o")])
    config = _build_config(args)
    assert config.estimate_hands.mode == "always" and str(config.estimate_hands.model_path) == "hp.onnx"
    assert config.clips[0].hfov_deg == 90
    args = parser().parse_args(["curate", "--video", "v.mp4", "--intrinsics", "900,910,640,360", "--out", str(tmp_path / "o")])
    assert _build_config(args).clips[0].intrinsics == (900, 910, 640, 360)
    with pytest.raises(SystemExit, match="FX,FY,CX,CY"):
        _build_config(parser().parse_args(["curate", "--video", "v.mp4", "--intrinsics", "900", "--out", "o"]))
    wheel = tmp_path / "mp.whl"
    with zipfile.ZipFile(wheel, "w") as z:
        for name, (inner, _) in model_fetch.MODELS.items():
            z.write(hand_models / name, inner)
    assert main(["models", "fetch", "--dest", str(tmp_path / "m"), "--wheel", str(wheel)]) == 0
    out = capsys.readouterr().out
    assert "4 model file(s) written" in out and "HANDEDIT_HAND_MODEL_DIR" in out
    assert main(["models", "fetch", "--dest", str(tmp_path / "m2"), "--wheel", str(tmp_path / "none.whl")]) == 2
    assert "does not exist" in capsys.readouterr().out


def test_egodex_both_hands_get_their_own_sides(egodex_dir, hand_models):
    """Real bimanual egocentric frames: each estimated side lies on the annotated hand of
    that side (the Vision Pro's joints, 20-40 px off the pixels, are close enough to tell)."""
    from handedit.sources import EgoDexTree

    spec = [s for s in EgoDexTree(root=egodex_dir, resize=(960, 540)).clips() if s.task == "insert_remove"][0]
    src = spec.open()
    info, c = src.info(), src.read(0, 24)
    est = estimate_hands(iter(c.frames), 24, info.intrinsics, info.fps)
    right_side, checked = 0, 0
    for i in range(24):
        for k in range(2):
            if not est.keypoints_valid[i, k].all():
                continue
            uv = project(est.keypoints_raw[i, k], info.intrinsics)
            d = [np.linalg.norm(project(c.keypoints[i, g], info.intrinsics) - uv, axis=1).mean() for g in range(2)]
            checked += 1
            right_side += int(np.argmin(d) == k)
    assert checked >= 36 and right_side / checked > 0.95, (right_side, checked)  # measured 41 of 41
