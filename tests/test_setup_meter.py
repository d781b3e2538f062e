"""Setup metering: builds count once, cache hits not at all, per thread; a renderer's build is
metered where the render stage gets it, and a chunk's record keeps the share."""

from __future__ import annotations

import functools
import os
import threading
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402

from handedit import setup_meter  # noqa: E402


def test_cache_misses_count_nested_blocks_once_hits_not():
    calls = []

    @functools.lru_cache(maxsize=4)
    @setup_meter.metered
    def build(key: int) -> int:
        calls.append(key)
        time.sleep(0.03)
        with setup_meter.building():  # a builder calling another: counted in the outer one only
            time.sleep(0.03)
        return key

    setup_meter.take()
    build(1)
    first = setup_meter.take()
    assert 0.06 <= first < 0.5
    build(1)  # a hit
    assert setup_meter.take() == 0.0
    build(2)
    assert 0.06 <= setup_meter.take() < 0.5
    assert calls == [1, 2]


def test_each_thread_has_its_own_count():
    setup_meter.take()
    seen = {}

    def other() -> None:
        with setup_meter.building():
            time.sleep(0.03)
        seen["other"] = setup_meter.take()

    t = threading.Thread(target=other)
    t.start()
    t.join()
    assert seen["other"] >= 0.03
    assert setup_meter.take() == 0.0, "another thread's build leaked into this one's count"


def test_renderer_build_is_metered_and_reuse_is_not(robots_dir):
    import json

    from handedit.render import get_renderer

    manifest = json.loads((robots_dir / "manifest.json").read_text())
    urdf = robots_dir / manifest["allegro"]["urdf"]
    setup_meter.take()
    t0 = time.perf_counter()
    get_renderer(urdf, 96, 72)  # a size no other test builds: a fresh renderer
    wall = time.perf_counter() - t0
    built = setup_meter.take()
    assert 0.0 < built <= wall
    get_renderer(urdf, 96, 72)
    assert setup_meter.take() == 0.0


def test_chunk_record_keeps_its_setup(tmp_path):
    """``execute`` puts what the body built into the record, not what the thread built before."""
    from handedit.tasks.common import StageOutput, execute

    with setup_meter.building():  # an earlier task's leftovers on this thread
        time.sleep(0.02)

    def body(inputs, job):
        with setup_meter.building():
            time.sleep(0.05)
        return StageOutput({}, np.zeros(job.n, np.int16))

    rec = execute(_job(tmp_path), body, None)
    assert 0.05 <= rec["setup_seconds"] <= rec["seconds"] < 0.05 + 5.0
    assert setup_meter.take() == 0.0


def _job(tmp_path):
    from handedit.storage import Unit, create_or_open_store, create_unit
    from handedit.tasks.common import ChunkJob
    from handedit.tasks.plan import ClipPlan

    path = tmp_path / "s.zarr"
    root = create_or_open_store(path, frames_per_chunk=4, code_version="test")
    unit = Unit("segment", "c1")
    create_unit(root, unit, 8, {"H": 4, "W": 4, "S": 1}, 4)
    plan = ClipPlan(clip="c1", n_frames=8, height=4, width=4, intrinsics={}, source_json="{}", fingerprint="f",
                    has_object=False, has_gt=False)
    return ChunkJob(str(path), unit, 0, 0, 4, "0" * 32, 1, {}, {}, "test", plan)
