"""casadi functions compiled once per machine (handedit.retarget.compiled): the same values as
the interpreted function, built once and loaded after, rebuilt over a broken file, and the
interpreted function (saying why) where no compiler works."""

from __future__ import annotations

import subprocess

import casadi as ca
import numpy as np
import pytest

from handedit.retarget.compiled import compiled


def _function(name: str = "toy_fgh") -> ca.Function:
    x, p = ca.SX.sym("x", 3), ca.SX.sym("p", 2)
    cost = ca.sumsqr(ca.sin(x) * p[0] - p[1]) + ca.exp(x[0] * x[2])
    hess, grad = ca.hessian(cost, x)
    return ca.Function(name, [x, p], [cost, grad, ca.densify(hess)])


def _same(a: ca.Function, b: ca.Function) -> None:
    rng = np.random.default_rng(7)
    for _ in range(5):
        x, p = rng.normal(size=3), rng.normal(size=2)
        for u, v in zip(a(x, p), b(x, p)):
            np.testing.assert_array_equal(np.asarray(u), np.asarray(v))


@pytest.fixture
def cache(monkeypatch, tmp_path):
    monkeypatch.setenv("HANDEDIT_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("HANDEDIT_CASADI_COMPILE", raising=False)
    return tmp_path / "casadi"


def test_compiled_once_then_loaded(cache, monkeypatch):
    fn = _function()
    first = compiled(fn)
    assert first.how.startswith("compiled") and first.fn.class_name() == "External"
    (so,) = cache.glob("toy_fgh-*.so")
    _same(fn, first.fn)

    def no_compiler(*a, **k):
        raise AssertionError("compiled again")

    monkeypatch.setattr(subprocess, "run", no_compiler)
    again = compiled(fn)
    assert again.how == f"compiled {so}"
    _same(fn, again.fn)


def test_a_broken_cached_file_is_built_again(cache):
    fn = _function("toy_broken")
    compiled(fn)
    (so,) = cache.glob("toy_broken-*.so")
    so.write_bytes(b"not a shared library")
    again = compiled(fn)
    assert again.how == f"compiled {so}" and so.stat().st_size > 1000
    _same(fn, again.fn)


def test_without_a_compiler_the_interpreted_function_says_why(cache, monkeypatch):
    monkeypatch.setenv("CC", "/nonexistent/cc")
    fn = _function("toy_nocc")
    got = compiled(fn)
    assert got.fn is fn and got.how.startswith("interpreted") and "/nonexistent/cc" in got.how
    assert not list(cache.glob("toy_nocc-*"))  # nothing half-written
    monkeypatch.setenv("HANDEDIT_CASADI_COMPILE", "0")
    assert compiled(fn).how == "interpreted: HANDEDIT_CASADI_COMPILE=0"


def test_retargeting_is_the_same_compiled_or_interpreted(monkeypatch):
    """The hand fit (projected Newton on the exact Hessian) gives bit-identical joints."""
    import importlib

    from handedit.retarget import RetargetConfig, retarget
    from handedit.sources.synthetic import frame_keypoints, frame_state, make_clip_specs, make_plan

    api = importlib.import_module("handedit.retarget.api")
    spec = make_clip_specs(1, n_frames=12)[0]
    plan = make_plan(spec)
    kps = []
    for t in range(12):
        st = frame_state(plan, t, 12)
        cw = np.linalg.inv(st.world_from_camera)
        kps.append(frame_keypoints(plan, st) @ cw[:3, :3].T + cw[:3, 3])
    kps, valid = np.array(kps), np.ones((12, 21), bool)
    runs = {}
    for mode in ("1", "0"):
        monkeypatch.setenv("HANDEDIT_CASADI_COMPILE", mode)
        api._build.cache_clear()
        try:
            rt = api.get_retargeter("allegro", RetargetConfig())
            assert rt.newton.evaluation.startswith("compiled" if mode == "1" else "interpreted")
            runs[mode] = retarget(kps, valid, "allegro", RetargetConfig()).qpos
        finally:
            api._build.cache_clear()
    np.testing.assert_array_equal(runs["1"], runs["0"])
