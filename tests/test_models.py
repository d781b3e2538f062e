"""ONNX plug-ins: real onnxruntime loading, contract checks, pre/post-processing, provenance.

The models are tiny graphs built in code (``handedit.models.toy``), so every path runs
without downloads: a missing file or a mismatched signature must fail with an error that
names the file and the expected signature; a working model must drive each stage and
leave its hash in the stage's ``method`` string.
"""

from __future__ import annotations

import numpy as np
import pytest

from handedit.models import ModelContractError, file_sha256, toy
from handedit.reasons import Reason
from handedit.vision.harmonize import HarmonizeConfig, harmonize
from handedit.vision.restore_background import RestoreConfig, restore_background
from handedit.vision.segment import SegmentConfig, segment


def _frames(n=4, h=48, w=64, seed=0):
    rng = np.random.default_rng(seed)
    base = np.zeros((h, w, 3), np.uint8)
    base[..., 0], base[..., 1], base[..., 2] = 60, 90, 160  # bluish scene: R - B < 0
    base = np.clip(base + rng.integers(-8, 9, base.shape), 0, 255).astype(np.uint8)
    frames = np.repeat(base[None], n, 0).copy()
    masks = np.zeros((n, h, w), bool)
    kp = np.zeros((n, 21, 2), np.float32)
    for i in range(n):
        x0 = 10 + 4 * i
        frames[i, 15:35, x0:x0 + 16] = (220, 160, 120)  # a skin-red "hand" that moves
        masks[i, 15:35, x0:x0 + 16] = True
        kp[i] = np.stack(np.meshgrid(np.linspace(x0 + 2, x0 + 13, 7), np.linspace(17, 32, 3)), -1).reshape(-1, 2)
    return frames, masks, kp[:, None], np.ones((n, 1, 21), bool), base  # one hand


def test_segmenter_drives_prompts_and_records_hash(tmp_path):
    frames, masks, kp, valid, _ = _frames()
    path = toy.make_segmenter(tmp_path / "seg.onnx")
    res = segment(frames, kp, valid, SegmentConfig(method="onnx", model_path=str(path)))
    assert (res.status == Reason.OK).all() and np.allclose(res.confidence, 0.9)
    ious = [(a & b).sum() / (a | b).sum() for a, b in zip(res.hand_mask[:, 0], masks)]
    assert min(ious) > 0.9, ious
    assert (res.handarm_mask >= res.hand_mask).all()
    assert res.method.startswith("onnx:segmenter:seg.onnx@sha256:") and file_sha256(path)[:16] in res.method


def test_segmenter_fixed_size_low_score_blank_and_empty(tmp_path):
    frames, masks, kp, valid, base = _frames()
    frames[1] = 0  # blank
    frames[2] = base  # nothing red: empty mask
    path = toy.make_segmenter(tmp_path / "seg.onnx", score=0.5, image_hw=(32, 40))
    res = segment(frames, kp, valid, SegmentConfig(method="onnx", model_path=str(path)))
    assert res.status[1] == Reason.BLANK_FRAME and res.status[2] == Reason.EMPTY_MASK
    assert res.status[0] == Reason.LOW_CONFIDENCE == res.status[3]  # 0.5 < the paper's 0.75
    assert res.hand_mask[0, 0].shape == masks[0].shape and (res.hand_mask[0, 0] & masks[0]).sum() > 0.6 * masks[0].sum()
    ok = SegmentConfig(method="onnx", model_path=str(path), min_model_confidence=0.4)
    assert segment(frames[:1], kp[:1], valid[:1], ok).status[0] == Reason.OK


def test_missing_and_mismatched_models_name_file_and_signature(tmp_path):
    frames, masks, kp, valid, _ = _frames(2)
    missing = tmp_path / "nope.onnx"
    with pytest.raises(ModelContractError, match=r"nope\.onnx.*image.*points"):
        segment(frames, kp, valid, SegmentConfig(method="onnx", model_path=str(missing)))
    wrong = toy.make_segmenter(tmp_path / "wrong.onnx", image_name="img")
    with pytest.raises(ModelContractError, match=r"wrong\.onnx.*missing input 'image'.*unexpected inputs \['img'\]"):
        segment(frames, kp, valid, SegmentConfig(method="onnx", model_path=str(wrong)))
    # a segmenter offered as a video inpainter: rank/name mismatch, named
    with pytest.raises(ModelContractError, match=r"video inpainter model .*wrong\.onnx.*frames"):
        restore_background(frames, masks, np.arange(2), RestoreConfig(method="onnx", model_path=str(wrong)))
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a model")
    with pytest.raises(ModelContractError, match=r"garbage\.onnx could not be loaded"):
        harmonize(frames, masks, HarmonizeConfig(method="onnx", model_path=str(garbage)))
    with pytest.raises(ValueError, match="needs model_path"):
        SegmentConfig(method="onnx")


@pytest.mark.parametrize("t_fixed", [None, 3])
def test_inpainter_restores_hole_only(tmp_path, t_fixed):
    frames, masks, kp, valid, base = _frames(5)
    path = toy.make_inpainter(tmp_path / "inp.onnx", t_fixed=t_fixed)
    res = restore_background(frames, masks, np.arange(5), RestoreConfig(method="onnx", model_path=str(path), dilate_px=1))
    assert res.method.startswith("onnx:video-inpainter:inp.onnx@sha256:")
    holes = np.stack([np.pad(m, 0) for m in masks])
    for i in range(5):
        grown = np.zeros_like(holes[i])
        grown[14:36, 9 + 4 * i:27 + 4 * i] = True
        assert (res.background[i][~grown] == frames[i][~grown]).all(), "known pixels changed"
        restored = res.background[i][masks[i]].astype(int)
        if t_fixed is None:  # the whole window: every hole pixel was seen somewhere
            assert np.abs(restored - base[masks[i]]).mean() < 12  # the scene, not the hand
        assert np.abs(restored - [220, 160, 120]).mean() > 50, "hand colour left in the hole"
    assert (res.status == Reason.OK).all()


def test_harmonizer_changes_only_the_robot_band(tmp_path):
    frames, masks, *_ = _frames(2)
    path = toy.make_harmonizer(tmp_path / "h.onnx")
    res = harmonize(frames, masks, HarmonizeConfig(method="onnx", model_path=str(path), edge_px=2))
    assert res.method.startswith("onnx:harmonizer:h.onnx@sha256:") and (res.status == Reason.OK).all()
    import cv2

    band = np.stack([cv2.dilate(m.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool) for m in masks])
    assert (res.image[~band] == frames[~band]).all()
    before = frames[masks].astype(float).mean(0)
    after = res.image[masks].astype(float).mean(0)
    mean_all = frames.reshape(-1, 3).astype(float).mean(0)
    assert np.linalg.norm(after - mean_all) < np.linalg.norm(before - mean_all) - 10
    empty = harmonize(frames, np.zeros_like(masks), HarmonizeConfig(method="onnx", model_path=str(path)))
    assert (empty.status == Reason.EMPTY_RENDER).all()
