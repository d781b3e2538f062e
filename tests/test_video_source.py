"""VideoSource: the real hand video, exact frame ranges, broken files, keypoints files."""

from __future__ import annotations

import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

from handedit.sources.base import SourceError
from handedit.sources.video import VideoSpec


def _decode_all(path: Path, stop: int) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    out = []
    while len(out) < stop:
        ok, f = cap.read()
        if not ok:
            break
        out.append(cv2.cvtColor(f, cv2.COLOR_BGR2RGB))
    cap.release()
    return out


@pytest.fixture(scope="module")
def real_src(real_video):
    return VideoSpec(path=real_video).open()


@pytest.fixture()
def small_avi(tmp_path) -> Path:
    """20 distinct MJPG frames (160x96): small, intra-only, easy to corrupt per frame."""
    path = tmp_path / "small.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (160, 96))
    assert w.isOpened()
    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, (96, 160, 3), dtype=np.uint8)
    for t in range(20):
        f = base.copy()
        cv2.putText(f, str(t), (40, 70), cv2.FONT_HERSHEY_SIMPLEX, 2.0, (255, 255, 255), 4)
        w.write(f)
    w.release()
    return path


def test_real_video_info(real_src, real_video):
    info = real_src.info()
    assert (info.n_frames, info.width, info.height) == (621, 1280, 720)
    assert info.fps == pytest.approx(30.0)
    assert not info.has_keypoints and not info.has_object
    assert info.clip_id == "human_hand_video"
    assert info.meta["intrinsics_origin"].startswith("default")
    assert info.intrinsics.width == 1280 and info.intrinsics.cx == 640.0
    assert len(info.fingerprint) == 64
    assert VideoSpec(path=real_video).open().info().fingerprint == info.fingerprint  # stable
    other = VideoSpec(path=real_video, intrinsics=(900.0, 900.0, 640.0, 360.0)).open().info()
    assert other.meta["intrinsics_origin"] == "spec" and other.fingerprint != info.fingerprint


def test_real_video_read_matches_sequential_decode(real_src, real_video):
    ref = _decode_all(real_video, 104)
    chunk = real_src.read(100, 104)
    assert chunk.start == 100 and chunk.n == 4 and chunk.frame_ok.all()
    for i in range(4):
        np.testing.assert_array_equal(chunk.frames[i], ref[100 + i])
    back = real_src.read(2, 4)  # backwards after forwards: re-seek
    np.testing.assert_array_equal(back.frames, np.stack(ref[2:4]))
    np.testing.assert_array_equal(real_src.read(4, 5).frames[0], ref[4])  # continue sequentially


def test_real_video_no_keypoints(real_src):
    c = real_src.read(10, 12)
    assert c.keypoints.shape == (2, 1, 21, 3) and not c.keypoints_valid.any() and not c.keypoints.any()
    np.testing.assert_array_equal(c.world_from_camera, np.tile(np.eye(4), (2, 1, 1)))
    assert c.object_mask is None and c.object_pose is None
    assert real_src.object_mesh() is None
    assert c.frames.dtype == np.uint8 and c.frames.shape == (2, 720, 1280, 3)


def test_read_range_checked_and_pickle(real_src):
    with pytest.raises(SourceError):
        real_src.read(600, 700)
    real_src.read(0, 1)
    clone = pickle.loads(pickle.dumps(real_src))  # open decoder handles are not pickled
    assert clone.read(0, 1).frame_ok.all()


def test_truncated_real_video_never_raises_cv2(real_video, tmp_path):
    data = real_video.read_bytes()
    for n in (1000, len(data) // 2, len(data) - 100):
        p = tmp_path / f"trunc_{n}.mp4"
        p.write_bytes(data[:n])
        try:
            src = VideoSpec(path=p).open()
            c = src.read(0, min(src.n_frames, 30))
        except SourceError as e:
            assert str(p) in str(e)
        else:
            assert c.frame_ok.dtype == bool


def test_truncated_avi_marks_missing_frames(small_avi, tmp_path):
    ref = VideoSpec(path=small_avi).open().read(0, 20)
    assert ref.frame_ok.all()
    data = small_avi.read_bytes()
    p = tmp_path / "trunc.avi"
    p.write_bytes(data[: len(data) // 2])
    src = VideoSpec(path=p).open()
    assert src.info().n_frames == 20  # the header still says 20
    c = src.read(0, 20)
    assert c.frame_ok[:5].all() and not c.frame_ok[-5:].any()
    ok = np.flatnonzero(c.frame_ok)
    # The last frame before the cut may be a partial packet that the decoder conceals
    # (it reports success); every earlier one must be exact and in place.
    np.testing.assert_array_equal(c.frames[ok[:-1]], ref.frames[ok[:-1]])
    assert not src.read(15, 20).frame_ok.any()


def test_corrupt_frame_does_not_abort_chunk(small_avi, tmp_path):
    ref = VideoSpec(path=small_avi).open().read(0, 20)
    data = bytearray(small_avi.read_bytes())
    sois = [i for i in range(len(data) - 1) if data[i] == 0xFF and data[i + 1] == 0xD8]
    assert len(sois) == 20
    data[sois[10] : sois[10] + 300] = bytes(300)  # wipe the header of frame 10's JPEG
    p = tmp_path / "corrupt.avi"
    p.write_bytes(bytes(data))
    src = VideoSpec(path=p).open()
    for a, b in ((0, 20), (8, 14), (12, 16), (10, 11)):
        c = src.read(a, b)
        for k in range(b - a):
            i = a + k
            if i == 10:
                continue  # the decoder may conceal or drop it; either way no exception
            assert c.frame_ok[k], (a, b, i)
            np.testing.assert_array_equal(c.frames[k], ref.frames[i])  # nothing shifted


@pytest.mark.parametrize("seek", ["auto", "sequential"])
def test_small_video_ranges(small_avi, seek):
    src = VideoSpec(path=small_avi, seek=seek, max_frames=15).open()
    assert src.info().n_frames == 15
    full = VideoSpec(path=small_avi).open().read(0, 20)
    for a, b in ((5, 9), (0, 2), (13, 15), (7, 8)):
        np.testing.assert_array_equal(src.read(a, b).frames, full.frames[a:b])


def test_missing_and_garbage_video(tmp_path):
    with pytest.raises(SourceError, match="does not exist"):
        VideoSpec(path=tmp_path / "nope.mp4").open()
    g = tmp_path / "garbage.mp4"
    g.write_bytes(np.random.default_rng(0).integers(0, 255, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(SourceError, match=str(g)):
        VideoSpec(path=g).open()


def test_keypoints_npy_and_npz(small_avi, tmp_path):
    kp = np.random.default_rng(1).normal(0, 0.05, (20, 21, 3)).astype(np.float32)
    kp[..., 2] += 0.5
    kp[3, 4] = np.nan
    npy = tmp_path / "kp.npy"
    np.save(npy, kp)
    src = VideoSpec(path=small_avi, keypoints_path=npy).open()
    info = src.info()
    assert info.has_keypoints and info.meta["intrinsics_origin"].startswith("default")
    c = src.read(2, 5)
    assert c.keypoints_valid.sum() == 3 * 21 - 1 and not c.keypoints_valid[1, 0, 4]
    assert np.all(c.keypoints[1, 0, 4] == 0)
    np.testing.assert_allclose(c.keypoints[0, 0], kp[2])
    assert info.hands == ("right",)

    valid = np.ones((20, 21), bool)
    valid[:, 0] = False
    K = np.array([[200.0, 0, 80], [0, 210.0, 48], [0, 0, 1]])
    npz = tmp_path / "kp.npz"
    np.savez(npz, keypoints=kp, valid=valid, K=K)
    src = VideoSpec(path=small_avi, keypoints_path=npz).open()
    info = src.info()
    assert info.meta["intrinsics_origin"] == "keypoints_file:K" and info.intrinsics.fy == 210.0
    assert not src.read(0, 20).keypoints_valid[:, 0, 0].any()
    assert info.fingerprint != VideoSpec(path=small_avi, keypoints_path=npy).open().info().fingerprint

    two = tmp_path / "two.npz"  # two hands, named; stored in (left, right) order
    np.savez(two, keypoints=np.stack([kp, kp + 0.01], axis=1), hands=np.array(["right", "left"]))
    src = VideoSpec(path=small_avi, keypoints_path=two).open()
    assert src.info().hands == ("left", "right")
    np.testing.assert_allclose(src.read(0, 1).keypoints[0, 0], kp[0] + 0.01)
    np.testing.assert_allclose(VideoSpec(path=small_avi, keypoints_path=npy, hand="left").open().read(0, 1).keypoints[0, 0], kp[0])


def _bad_keypoint_files(tmp_path: Path) -> list[Path]:
    files = []

    def save(name, **arrays):
        p = tmp_path / name
        if name.endswith(".npy"):
            np.save(p, arrays["a"])
        else:
            np.savez(p, **arrays)
        files.append(p)

    save("shape.npy", a=np.zeros((20, 21, 2)))
    save("frames.npy", a=np.zeros((19, 21, 3)))
    save("joints.npy", a=np.zeros((20, 16, 3)))
    save("nokey.npz", joints=np.zeros((20, 21, 3)))
    save("badvalid.npz", keypoints=np.zeros((20, 21, 3)), valid=np.ones((20, 20), bool))
    save("badK.npz", keypoints=np.zeros((20, 21, 3)), K=np.eye(2))
    save("unnamed.npz", keypoints=np.zeros((20, 2, 21, 3)))  # two hands, not named
    junk = tmp_path / "junk.npy"
    junk.write_bytes(b"not a numpy file at all")
    files.append(junk)
    txt = tmp_path / "kp.txt"
    txt.write_text("0 0 0")
    files.append(txt)
    files.append(tmp_path / "missing.npy")
    return files


def test_malformed_keypoints_raise_source_error(small_avi, tmp_path):
    for path in _bad_keypoint_files(tmp_path):
        with pytest.raises(SourceError) as e:
            VideoSpec(path=small_avi, keypoints_path=path).open()
        assert str(path) in str(e.value), e.value


def test_spec_via_package_parser(small_avi):
    from handedit.sources import parse_spec

    spec = parse_spec({"kind": "video", "path": str(small_avi)})
    assert isinstance(spec, VideoSpec) and spec.open().info().n_frames == 20


def test_consecutive_chunks_decode_each_frame_once(real_video):
    """A worker reading chunk k then k+1 keeps its decoder: every frame is decoded once, and the
    counts (what ingest records per chunk) say so; a jump ahead seeks instead of decoding the gap."""
    src = VideoSpec(path=real_video).open()
    stats = src.video.stats
    for a in (0, 16, 32):
        src.read(a, a + 16)
    assert stats.decoded == stats.delivered == 48 and stats.seconds > 0
    before = (stats.decoded, stats.delivered)
    src.read(300, 316)  # far ahead: a seek, then at most the frames from the keyframe on
    assert stats.delivered - before[1] == 16 and 16 <= stats.decoded - before[0] < 300 - 48
