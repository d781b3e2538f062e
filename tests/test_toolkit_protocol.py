"""The toolkit scoring protocol (handedit.metrics.toolkit) pinned to hand-computed values and to
independent implementations (scikit-image, scipy, PIL called directly), on small fixtures."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image
from scipy.ndimage import binary_dilation
from skimage.color import rgb2hsv, rgb2lab
from skimage.metrics import structural_similarity

from _bench_onnx import EMB_W, TOOLKIT_SIZES, write_encoders
from handedit.benchmark.manifest import ManifestItem
from handedit.metrics import toolkit as tk
from handedit.metrics.encoders import Encoders, load_encoders

H, W = 80, 96


def _f32(a: np.ndarray) -> np.ndarray:
    return a.astype(np.float32) / 255.0


@pytest.fixture
def files(tmp_path):
    rng = np.random.default_rng(0)
    gt = rng.integers(0, 255, (H, W, 3), np.uint8)
    gt[..., 2] = np.maximum(gt[..., 2], gt[..., :2].max(-1))  # bluish: no skin in the GT
    pred = gt.copy()
    pred[20:40, 30:45] = (220, 170, 140)  # a skin-coloured patch inside the ROI
    pred[60:70, 5:15] = np.clip(pred[60:70, 5:15].astype(int) + 30, 0, 255)  # a change in the background
    human, robot, obj = (np.zeros((H, W), np.uint8) for _ in range(3))
    human[20:40, 30:50] = 255
    robot[25:45, 40:60] = 255
    obj[42:50, 55:70] = 255
    paths = {}
    for name, a in dict(gt=gt, pred=pred, src=gt, human=human, robot=robot, obj=obj).items():
        paths[name] = str(tmp_path / f"{name}.png")
        Image.fromarray(a).save(paths[name])
    roi = (human > 0) | (robot > 0)
    return {"gt": gt, "pred": pred, "roi": roi, "robot": robot > 0, "obj": obj > 0, "paths": paths, "dir": tmp_path}


def _sample(f, **kw) -> ManifestItem:
    p = f["paths"]
    base = dict(id="a", replacement_scope="hand", target_name="Allegro", pred_path=p["pred"], src_path=p["src"],
                gt_path=p["gt"], human_mask_path=p["human"], robot_mask_path=p["robot"], gt_mask_path=p["robot"],
                object_mask_path=p["obj"], urdf_ref_paths=[p["gt"]], urdf_mask_paths=[p["robot"]])
    return ManifestItem(**{**base, **kw})


def test_generic_metrics_match_hand_computation_and_skimage(files):
    row, feats = tk.score_sample(_sample(files), tk.Neural(Encoders()))
    g, p, roi = _f32(files["gt"]), _f32(files["pred"]), files["roi"]
    se = (p - g) ** 2
    assert row["Full-PSNR"] == pytest.approx(10 * math.log10(1 / float(se.mean())), abs=1e-9)
    assert row["ROI-PSNR"] == pytest.approx(10 * math.log10(1 / float(se[roi].mean())), abs=1e-9)  # MSE over ROI pixels only
    assert row["BG-PSNR"] == pytest.approx(10 * math.log10(1 / float(se[~roi].mean())), abs=1e-9)
    assert row["Full-SSIM"] == pytest.approx(structural_similarity(p, g, channel_axis=-1, data_range=1.0), abs=1e-6)
    ys, xs = np.where(roi)
    box = (slice(max(0, ys.min() - 8), ys.max() + 9), slice(max(0, xs.min() - 8), xs.max() + 9))
    assert row["ROI-SSIM"] == pytest.approx(structural_similarity(p[box], g[box], channel_axis=-1, data_range=1.0), abs=1e-6)
    bg = (~roi).astype(np.float32)[..., None]
    assert row["BG-SSIM"] == pytest.approx(structural_similarity(p * bg, g * bg, channel_axis=-1, data_range=1.0), abs=1e-6)
    assert math.isnan(row["Full-LPIPS"]) and math.isnan(row["Fidelity-Shape"]) and feats == {}  # no encoders


def test_removal_lab_and_the_small_roi_rule(files):
    row, _ = tk.score_sample(_sample(files), tk.Neural(Encoders()))
    p, roi = _f32(files["pred"]), files["roi"]
    hsv = rgb2hsv(p)
    skin = ((hsv[..., 0] <= 0.12) | (hsv[..., 0] >= 0.90)) & (hsv[..., 1] >= 0.2) & (hsv[..., 1] <= 0.75) \
        & (hsv[..., 2] >= 0.2) & (hsv[..., 2] <= 0.98)
    assert skin[20:40, 30:45].all()
    assert row["Removal"] == pytest.approx(1 - (skin & roi).sum() / roi.sum(), abs=1e-9) and row["Removal"] < 1
    assert row["Removal_pct"] == pytest.approx(100 * row["Removal"])
    # Lab: both robot-mask crops (+8 px) at 224 x 224, Delta E over both masks
    box = (slice(25 - 8, 45 + 8), slice(40 - 8, 60 + 8))
    a = np.asarray(Image.fromarray(files["pred"][box]).resize((224, 224), Image.BILINEAR)).astype(np.float32) / 255
    b = np.asarray(Image.fromarray(files["gt"][box]).resize((224, 224), Image.BILINEAR)).astype(np.float32) / 255
    m = np.asarray(Image.fromarray(files["robot"][box].astype(np.uint8) * 255).resize((224, 224), Image.NEAREST)) > 127
    d = float(np.sqrt(((rgb2lab(a) - rgb2lab(b)) ** 2).sum(-1))[m].mean())
    assert row["Fidelity-ID-lab-dist"] == pytest.approx(d, rel=1e-9) and row["Fidelity-ID-lab"] == pytest.approx(math.exp(-d / 25))
    assert math.isnan(row["Fidelity-ID"]) and math.isnan(row["Fidelity"])  # no CLIP: not the toolkit's number
    tiny = np.zeros((H, W), np.uint8)
    tiny[5:8, 5:8] = 255  # 9 pixels: the toolkit computes no embodied metric
    Image.fromarray(tiny).save(files["dir"] / "tiny.png")
    row2, _ = tk.score_sample(_sample(files, human_mask_path=str(files["dir"] / "tiny.png"), robot_mask_path=""),
                              tk.Neural(Encoders()))
    assert math.isnan(row2["Removal"]) and not math.isnan(row2["Full-PSNR"])


def test_resizing_and_mask_rules(files):
    d = files["dir"]
    small = Image.fromarray(files["pred"]).resize((W // 2, H // 2), Image.BILINEAR)
    small.save(d / "small.png")
    grey = np.zeros((H // 2, W // 2, 3), np.uint8)  # an RGB mask at another size: luma > 0.5, nearest resize
    grey[10:20, 15:30] = 128
    grey[0:5, 0:5] = 127
    Image.fromarray(grey).save(d / "human_small.png")
    row, _ = tk.score_sample(_sample(files, pred_path=str(d / "small.png"), human_mask_path=str(d / "human_small.png"),
                                     robot_mask_path=""), tk.Neural(Encoders()))
    assert row["pred_size"] == f"{W // 2}x{H // 2}" and row["resized"] is True
    up = np.asarray(Image.open(d / "small.png").convert("RGB").resize((W, H), Image.BILINEAR)).astype(np.float32) / 255
    g = _f32(files["gt"])
    assert row["Full-PSNR"] == pytest.approx(10 * math.log10(1 / float(((up - g) ** 2).mean())), abs=1e-9)
    roi = np.zeros((H, W), bool)
    roi[20:40, 30:60] = True  # 128 counts (128/255 > 0.5), 127 does not; x2 nearest
    assert row["BG-PSNR"] == pytest.approx(10 * math.log10(1 / float(((up - g) ** 2)[~roi].mean())), abs=1e-9)
    mask = tk.load_mask(d / "human_small.png")
    assert mask[10, 15] == 1 and mask[0, 0] == 0 and tk.resize_mask(mask, (H, W)).sum() == roi.sum()
    none, _ = tk.score_sample(_sample(files, human_mask_path="", robot_mask_path=""), tk.Neural(Encoders()))
    assert none["ROI-PSNR"] == none["Full-PSNR"]  # no human/robot masks: the ROI is the whole image


def test_colour_conversions_match_skimage():
    rng = np.random.default_rng(3)
    x = rng.random((40, 50, 3)).astype(np.float32)
    x[0, :3] = [[1, 1, 1], [0, 0, 0], [0.5, 0.5, 0.2]]  # ties and greys
    np.testing.assert_allclose(tk.rgb_to_hsv(x), rgb2hsv(x), atol=1e-6)
    np.testing.assert_allclose(tk.rgb_to_lab(x), rgb2lab(x), atol=1e-4)


def test_interaction_region_follows_the_toolkit(files):
    cfg = tk.ToolkitConfig()
    roi = files["roi"].astype(np.uint8)
    np.testing.assert_array_equal(tk.interaction_region(roi, files["obj"].astype(np.uint8), cfg),
                                  binary_dilation(files["obj"], iterations=12))
    band = binary_dilation(files["roi"], iterations=12) & ~files["roi"]
    np.testing.assert_array_equal(tk.interaction_region(roi, None, cfg), band)


def _hf(image_u8: np.ndarray, shortest: int, mean, std) -> np.ndarray:
    """The Hugging Face image processors' steps, written out with PIL for the test."""
    im = Image.fromarray(image_u8)
    w, h = im.size
    size = (shortest, int(shortest * h / w)) if w <= h else (int(shortest * w / h), shortest)
    a = np.asarray(im.resize(size, Image.BICUBIC))
    top, left = (a.shape[0] - 224) // 2, (a.shape[1] - 224) // 2
    a = a[top:top + 224, left:left + 224].astype(np.float32) / 255
    return ((a - np.float32(mean)) / np.float32(std)).transpose(2, 0, 1)


def test_hf_and_cleanfid_preprocessing_definitions():
    rng = np.random.default_rng(5)
    img = rng.integers(0, 255, (200, 300, 3), np.uint8)
    x = tk.hf_pixel_values(img, tk.HF_DINOV2)
    assert x.shape == (3, 224, 224)  # 300x200 -> 384x256 -> centre 224
    np.testing.assert_allclose(x, _hf(img, 256, tk.HF_DINOV2["mean"], tk.HF_DINOV2["std"]), atol=1e-6)
    tall = rng.integers(0, 255, (301, 97, 3), np.uint8)
    np.testing.assert_allclose(tk.hf_pixel_values(tall, tk.HF_CLIP), _hf(tall, 224, tk.HF_CLIP["mean"], tk.HF_CLIP["std"]), atol=1e-6)
    r = tk.cleanfid_resize(img)
    ch = np.asarray(Image.fromarray(img[..., 1].astype(np.float32), mode="F").resize((299, 299), Image.BICUBIC))
    assert r.shape == (299, 299, 3) and r.min() >= 0 and r.max() <= 255
    np.testing.assert_allclose(r[..., 1], np.clip(ch, 0, 255), atol=1e-4)
    assert np.abs(r - np.asarray(Image.fromarray(img).resize((299, 299), Image.BICUBIC))).max() > 0  # not a uint8 resize


def test_neural_terms_use_the_toolkit_crops_fill_and_preprocessing(files, tmp_path):
    """The test encoders are a 1x1 conv and a global average pool, so each embedding is W times
    the mean of the preprocessed pixels: recomputed here from the toolkit's definitions."""
    enc = load_encoders(write_encoders(tmp_path / "models", sizes=TOOLKIT_SIZES))
    row, feats = tk.score_sample(_sample(files), tk.Neural(enc))
    g8, p8, roi = files["gt"], files["pred"], files["roi"]

    def emb(name, x):
        v = EMB_W[name] @ x.reshape(3, -1).mean(1)
        return v / (np.linalg.norm(v) + 1e-8)

    ys, xs = np.where(roi)
    box = (slice(max(0, ys.min() - 8), ys.max() + 9), slice(max(0, xs.min() - 8), xs.max() + 9))
    dm, ds = tk.HF_DINOV2["mean"], tk.HF_DINOV2["std"]
    shape = 0.5 * (1 + emb("dinov2", _hf(p8[box], 256, dm, ds)) @ emb("dinov2", _hf(g8[box], 256, dm, ds)))
    assert row["Fidelity-Shape"] == pytest.approx(shape, abs=1e-5)  # unmasked padded ROI crop

    rb = (slice(25 - 8, 45 + 8), slice(40 - 8, 60 + 8))
    rm = files["robot"][rb][..., None]

    def filled(img):  # the robot-mask crop with 0.5 grey outside the mask, as the toolkit makes it
        return (np.clip(np.where(rm, img[rb].astype(np.float32) / 255, np.float32(0.5)), 0, 1) * 255).astype(np.uint8)

    cm, cs = tk.HF_CLIP["mean"], tk.HF_CLIP["std"]
    cos = float(emb("clip", _hf(filled(p8), 224, cm, cs)) @ emb("clip", _hf(filled(g8), 224, cm, cs)))
    assert row["Fidelity-ID-clip-cos"] == pytest.approx(cos, abs=5e-4)  # onnxruntime sums the 224x224 pool in float32
    assert row["Fidelity-ID"] == pytest.approx(0.5 * row["Fidelity-ID-clip"] + 0.5 * row["Fidelity-ID-lab"])
    a, b = row["Fidelity-Shape"], row["Fidelity-ID"]
    assert row["Fidelity"] == pytest.approx(2 * a * b / (a + b))
    assert row["Full-LPIPS"] == pytest.approx(enc.lpips.distance(p8, g8), abs=1e-5)
    region = binary_dilation(files["obj"], iterations=12)
    ys, xs = np.where(region)
    ib = (slice(max(0, ys.min() - 8), ys.max() + 9), slice(max(0, xs.min() - 8), xs.max() + 9))
    h, w = g8[ib].shape[:2]
    assert min(h, w) < 64  # so both crops go up to 64 px on the short side, bicubic

    def up(a):  # from the float image, through the toolkit's truncating uint8 conversion
        a = (np.clip(_f32(a), 0, 1) * 255).astype(np.uint8)
        s = 64 / min(h, w)
        return np.asarray(Image.fromarray(a).resize((max(64, round(w * s)), max(64, round(h * s))), Image.BICUBIC))

    assert row["Interaction"] == pytest.approx(1 - enc.lpips.distance(up(g8[ib]), up(p8[ib])), abs=1e-5)
    inc = EMB_W["inception"] @ (tk.cleanfid_resize(g8) / 255).reshape(-1, 3).mean(0)
    np.testing.assert_allclose(feats["full_gt"], inc, atol=1e-4)
    assert set(feats) == {"full_gt", "full_pred", "roi_gt", "roi_pred"}


def test_summary_and_leaderboard_shapes():
    from handedit.benchmark import toolkit_report as tr

    rows = [tr.per_sample_row({"id": str(i), "Full-PSNR": float(v), "VLM": float(i), "track": "hand", "error": ""},
                              {"id": str(i), "dataset": "D", "task": t, "replacement_scope": "hand-only"})
            for i, (v, t) in enumerate([(10, "a"), (20, "a"), (30, "b")])]
    assert list(rows[0])[:3] == ["id", "dataset", "task"] and "Fidelity-ID" in rows[0]
    s = tr.summarize(rows, {"Full-FID": 1.5, "ROI-FID": float("nan")}, "x")
    assert set(s) == {"_meta", "D/a", "D/b"} and s["D/a"]["n"] == 2
    assert s["D/a"]["Full-PSNR_mean"] == 15 and s["D/a"]["Full-PSNR_std"] == pytest.approx(math.sqrt(50))
    assert s["D/a"]["Full-PSNR_median"] == 15 and math.isnan(s["D/b"]["Full-PSNR_std"]) and s["D/b"]["Full-FID"] == 1.5
    csv_text, md = tr.leaderboard(s)
    assert csv_text.splitlines()[1].startswith("D,b")  # sorted by VLM_mean, descending
    assert md.startswith("| exp_name | dataset | task | n |") and "Full-PSNR_mean" in md and "Full-PSNR_std" not in md
    json.dumps(s)  # NaN written as the toolkit writes it


def test_toolkit_judge_crops_labels_and_scoring():
    from handedit.metrics import vlm_toolkit as vt

    assert vt.grow_to_min((0, 0, 10, 10), (200, 100), 96) == (0, 0, 96, 96)  # widened, then moved inside
    assert vt.grow_to_min((150, 40, 190, 60), (200, 100), 96) == (104, 2, 200, 98)
    img = np.zeros((120, 160, 3), np.uint8)
    human = np.zeros((120, 160), bool)
    human[50:60, 70:80] = True
    crop = vt.crop_by_masks(img, [human, None], vt.ROI_PAD)
    assert crop.size == (96, 96)  # 10 px + 2 x 24 pad = 58 -> at least 96
    assert vt.crop_by_masks(img, [None], vt.ROI_PAD) is None
    x = vt.JudgeInputs(img, img, "make it a robot", human_mask=human, reference=img, distractors=[img, img])
    sc, pq, flags = vt.requests(x)
    labels = [t for t, _ in sc[1:]]
    assert labels == ["Source image:", "Edited image:", "Edited region (zoom):",
                      "Edited object-contact region:",  # no object mask: the ROI zoom stands in, as in the toolkit
                      "Reference A (the target robot):", "Reference B (another robot):", "Reference C (another robot):"]
    assert all(u.startswith("data:image/jpeg;base64,") for _, u in sc[1:]) and sc[0][1] is None
    assert "make it a robot" in sc[0][0] and "2 render(s) of other robots" in sc[0][0]
    assert [t for t, _ in pq[1:]] == ["Edited image:", "Edited region (zoom):", "Edited boundary or contact region:"]
    assert flags == {"vlm_has_urdf_ref": True, "vlm_num_distractors": 2, "vlm_has_roi_crop": True, "vlm_has_contact_crop": True}
    answer = {"robotness": 4.6, "target_embodiment_match": "5", "interaction_preservation": 9, "scene_preservation": 0,
              "chosen_reference": "B", "target_choice_correct": "no", "correct_ref_alignment": 3}
    row = vt.combine(answer, {"naturalness": 4, "artifact_absence": 4, "local_coherence": 3}, flags)
    assert (row["robotness"], row["interaction_preservation"], row["scene_preservation"]) == (5, 5, 1)  # clamped
    assert row["target_embodiment_match"] == 3  # capped: a distractor was chosen
    assert row["SC"] == 0.0 and row["PQ"] == 0.5 and row["VLM"] == 0.0
    assert row["nearest_wrong_ref_alignment"] is None
    partial = vt.combine({"robotness": 5}, {"naturalness": 4, "artifact_absence": 4, "local_coherence": 4}, flags)
    assert math.isnan(partial["SC"]) and partial["PQ"] == 0.75 and math.isnan(partial["VLM"])
    cols = vt.columns(row)
    assert cols["VLM-target_embodiment_match"] == 3 and cols["VLM-target_choice_correct"] == 0
    assert math.isnan(cols["VLM-nearest_wrong_ref_alignment"]) and cols["VLM-chosen_reference"] == "B"
    with pytest.raises(Exception, match="no JSON object"):
        vt.lenient_json("about a 4")
    assert vt.lenient_json('Sure: {"robotness": 3} ok') == {"robotness": 3}


def test_optional_roi_dilation_is_a_disc(files):
    cfg = tk.ToolkitConfig(roi_dilate_px=3)
    grown = tk.dilate_disc(files["roi"].astype(np.uint8), cfg)
    yy, xx = np.ogrid[-3:4, -3:4]
    np.testing.assert_array_equal(grown, binary_dilation(files["roi"], structure=xx * xx + yy * yy <= 9))
    row, _ = tk.score_sample(_sample(files), tk.Neural(Encoders()), cfg)
    g, p = _f32(files["gt"]), _f32(files["pred"])
    assert row["BG-PSNR"] == pytest.approx(10 * math.log10(1 / float(((p - g) ** 2)[grown == 0].mean())), abs=1e-9)
