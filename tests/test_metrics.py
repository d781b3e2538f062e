"""The metric suite against independent references: scikit-image (PSNR/SSIM), a
scipy.linalg.sqrtm Frechet distance, numpy re-computations of LPIPS/FID through small
ONNX encoders, and hand-computed skin / Lab / ID-fidelity cases."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import scipy.linalg
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from _bench_onnx import EMB_W, LP_HEADS, LP_W0, LP_W1, write_encoders
from handedit.metrics import embodied, similarity
from handedit.metrics.encoders import LPIPS_MEAN, LPIPS_STD, load_encoders, missing_encoders
from handedit.metrics.frechet import fid, frechet_distance
from handedit.metrics.suite import ItemImages, score_item

RNG = np.random.default_rng(7)


def natural(h=48, w=64, seed=0) -> np.ndarray:
    r = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.stack([128 + 80 * np.sin(xx / 7 + c) * np.cos(yy / 9 - c) for c in range(3)], -1)
    return np.clip(base + r.normal(0, 12, (h, w, 3)), 0, 255).astype(np.uint8)


def noisy(a, sigma, seed=1):
    return np.clip(a + np.random.default_rng(seed).normal(0, sigma, a.shape), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def enc(tmp_path_factory):
    return load_encoders(write_encoders(tmp_path_factory.mktemp("enc")))


def test_psnr_ssim_match_scikit_image():
    a = natural()
    b = noisy(a, 20)
    assert similarity.psnr(a, b) == pytest.approx(peak_signal_noise_ratio(a, b, data_range=255), rel=1e-9)
    assert similarity.ssim(a, b) == pytest.approx(structural_similarity(a, b, channel_axis=2, data_range=255), abs=1e-9)
    # background: masked mean of skimage's SSIM map (half-window border excluded like skimage)
    mask = np.zeros(a.shape[:2], bool)
    mask[10:30, 20:50] = True
    _, smap = structural_similarity(a, b, channel_axis=2, data_range=255, full=True)
    valid = np.zeros_like(mask)
    valid[3:-3, 3:-3] = True
    assert similarity.ssim(a, b, ~mask) == pytest.approx(smap.mean(axis=2)[valid & ~mask].mean(), abs=1e-9)
    mse = ((a.astype(float) - b) ** 2)[~mask].mean()
    assert similarity.psnr(a, b, ~mask) == pytest.approx(10 * np.log10(255**2 / mse))
    # ROI crop
    box = similarity.bbox(mask)
    ca, cb = similarity.crop(a, box), similarity.crop(b, box)
    assert similarity.ssim(ca, cb) == pytest.approx(structural_similarity(ca, cb, channel_axis=2, data_range=255), abs=1e-9)
    # more noise -> worse
    assert similarity.psnr(a, noisy(a, 40)) < similarity.psnr(a, b)
    assert similarity.psnr(a, a) == similarity.PSNR_CAP_DB


def reference_frechet(mu1, s1, mu2, s2):
    covmean, _ = scipy.linalg.sqrtm(s1 @ s2, disp=False)
    covmean = covmean.real
    d = mu1 - mu2
    return d @ d + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean)


def test_frechet_distance_matches_sqrtm_reference():
    for seed in range(3):
        r = np.random.default_rng(seed)
        a = r.normal(size=(200, 6))
        b = r.normal(size=(150, 6)) @ r.normal(size=(6, 6)) * 0.7 + r.normal(size=6)
        mu1, s1, mu2, s2 = a.mean(0), np.cov(a, rowvar=False), b.mean(0), np.cov(b, rowvar=False)
        assert frechet_distance(mu1, s1, mu2, s2) == pytest.approx(reference_frechet(mu1, s1, mu2, s2), rel=1e-6)
    x = RNG.normal(size=(50, 4))
    assert fid(x, x) == pytest.approx(0, abs=1e-6)


def _lpips_ref(a, b):
    """numpy LPIPS through the test backbone: 1x1 convs + 2x2 average pool."""
    def prep(im):
        return (im.astype(np.float64) / 255 - np.array(LPIPS_MEAN)) / np.array(LPIPS_STD)
    def feats(x):
        h, w = x.shape[0] // 2 * 2, x.shape[1] // 2 * 2
        pooled = x[:h, :w].reshape(h // 2, 2, w // 2, 2, 3).mean(axis=(1, 3))
        return [x @ LP_W0.T.astype(np.float64), pooled @ LP_W1.T.astype(np.float64)]
    total = 0.0
    for f0, f1, w in zip(feats(prep(a)), feats(prep(b)), LP_HEADS):
        n0 = f0 / (np.linalg.norm(f0, axis=-1, keepdims=True) + 1e-10)
        n1 = f1 / (np.linalg.norm(f1, axis=-1, keepdims=True) + 1e-10)
        total += (((n0 - n1) ** 2) @ w).mean()
    return total


def test_lpips_arithmetic_through_onnx(enc):
    a, b = natural(), noisy(natural(), 30)
    assert enc.lpips.distance(a, b) == pytest.approx(_lpips_ref(a, b), rel=1e-4)
    assert enc.lpips.distance(a, a) == pytest.approx(0, abs=1e-9)
    assert enc.lpips.distance(a, noisy(a, 60)) > enc.lpips.distance(a, noisy(a, 10))
    full = np.ones(a.shape[:2], bool)
    assert enc.lpips.masked_distance(a, b, full) == pytest.approx(enc.lpips.distance(a, b), rel=0.05)
    # masked: difference only inside a region -> background LPIPS ~ 0, region LPIPS > 0
    c = a.copy()
    c[20:40, 30:60] = 255 - c[20:40, 30:60]
    region = np.zeros(a.shape[:2], bool)
    region[16:44, 26:64] = True
    far = np.zeros_like(region)
    far[:8, :16] = True
    assert enc.lpips.masked_distance(a, c, far) < 1e-6 < enc.lpips.masked_distance(a, c, region)


def test_fid_arithmetic_through_onnx(enc):
    # the test inception is a 1x1 conv + global pool at a static 32x32 input: features are
    # W @ mean colour (INTER_AREA halving 64x64 -> 32x32 keeps block means exactly)
    ims_a = [natural(64, 64, s) for s in range(6)]
    ims_b = [noisy(natural(64, 64, s + 10), 25, s) for s in range(6)]
    fa, fb = enc.inception.embed(ims_a), enc.inception.embed(ims_b)
    ref = lambda ims: np.stack([EMB_W["inception"].astype(np.float64) @ (im.reshape(-1, 3).mean(0) / 255) for im in ims])  # noqa: E731
    np.testing.assert_allclose(fa, ref(ims_a), rtol=1e-4, atol=1e-5)
    ra, rb = ref(ims_a), ref(ims_b)
    want = reference_frechet(ra.mean(0), np.cov(ra, rowvar=False), rb.mean(0), np.cov(rb, rowvar=False))
    assert fid(fa, fb) == pytest.approx(want, rel=1e-3, abs=1e-6)


def test_skin_rule_removal_hand_computed():
    skin, blue = (220, 170, 140), (40, 60, 200)  # YCrCb (181, 155, 105) inside the box; (70, 107, 219) outside
    img = np.zeros((10, 10, 3), np.uint8)
    img[:] = blue
    img[:5, :5] = skin  # 25 skin pixels
    roi = np.ones((10, 10), bool)
    assert embodied.removal(img, roi) == pytest.approx(0.75)
    roi2 = np.zeros((10, 10), bool)
    roi2[:, 5:] = True  # no skin there
    assert embodied.removal(img, roi2) == 1.0
    assert np.isnan(embodied.removal(img, np.zeros((10, 10), bool)))


def test_lab_delta_e_and_id_fidelity_hand_computed():
    white, black = np.full((4, 4, 3), 255, np.uint8), np.zeros((4, 4, 3), np.uint8)
    m = np.ones((4, 4), bool)
    assert embodied.delta_e_lab(white, black, m) == pytest.approx(100.0, abs=1e-3)
    red = np.zeros((4, 4, 3), np.uint8)
    red[..., 0] = 255  # sRGB red = Lab (53.24, 80.09, 67.20)
    assert embodied.delta_e_lab(red, black, m) == pytest.approx(np.sqrt(53.24**2 + 80.09**2 + 67.20**2), abs=0.05)
    assert embodied.lab_score(100.0, 25.0) == pytest.approx(np.exp(-4))
    assert embodied.id_fidelity(0.8, np.exp(-1), 0.5) == pytest.approx(0.4 + 0.5 * np.exp(-1))
    assert embodied.delta_e_lab(red, red, m) == 0.0


def test_score_item_and_missing_encoder_skips_loudly(enc, tmp_path, caplog):
    gt = natural(48, 64, 3)
    src = gt.copy()
    human = np.zeros(gt.shape[:2], bool)
    human[12:30, 20:40] = True
    robot = np.zeros_like(human)
    robot[14:32, 22:44] = True
    src[human] = (220, 170, 140)  # a skin-coloured "hand"
    obj = np.zeros_like(human)
    obj[28:40, 40:56] = True
    refs = [gt.copy()]
    items = lambda pred: ItemImages(src, pred, gt, human, robot, obj, refs, [robot])  # noqa: E731
    good, _ = score_item(items(gt.copy()), enc)
    bad, feats = score_item(items(src.copy()), enc)
    assert good["psnr_full"] == 100.0 and good["lpips_full"] == pytest.approx(0, abs=1e-9)
    assert good["struct_fidelity"] == pytest.approx(1.0) and good["id_fidelity"] == pytest.approx(1.0)
    for m in ("psnr_full", "psnr_roi", "ssim_full", "ssim_roi", "removal", "struct_fidelity", "id_fidelity"):
        assert good[m] > bad[m], m
    assert bad["removal"] < 0.8 and set(feats) == {"full_pred", "full_gt", "roi_pred", "roi_gt"}
    # wrong-size prediction: a clear error
    with pytest.raises(ValueError, match="source resolution"):
        score_item(items(gt[:40]), enc)
    # no LPIPS, no CLIP: those metrics are NaN (skipped), the rest still computed, and it is logged
    folder = write_encoders(tmp_path / "partial", skip=("lpips", "clip"))
    with caplog.at_level(logging.ERROR, logger="handedit.metrics"):
        partial = load_encoders(folder)
    assert "lpips" in caplog.text and "clip" in caplog.text
    assert set(missing_encoders(folder)) == {"lpips", "clip"}
    assert set(partial.skipped_metrics) >= {"lpips_full", "interaction", "id_fidelity"}
    out, _ = score_item(items(gt.copy()), partial)
    assert np.isnan(out["lpips_full"]) and np.isnan(out["interaction"]) and np.isnan(out["id_fidelity"])
    assert out["struct_fidelity"] == pytest.approx(1.0) and out["id_lab"] == 1.0
