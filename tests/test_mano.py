"""The numpy MANO model against smplx's MANO layer (torch, CPU), per dataset convention."""

from __future__ import annotations

import pickle
import sys
import types

import numpy as np
import pytest

from handedit.hands.mano import (TIPS_MANOPTH, TIPS_SMPLX, TO_MANO21, ManoConvention, ManoError, ManoModel,
                                 quat_wxyz_to_axis_angle, write_model_file)

T = 5


@pytest.fixture(scope="module")
def mano_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("mano")
    rng = np.random.default_rng(7)
    write_model_file(d / "MANO_RIGHT.pkl", rng)
    write_model_file(d / "MANO_LEFT.pkl", rng)
    return d


def _params(seed=0, n=45):
    rng = np.random.default_rng(seed)
    return rng.normal(0, 1, (T, 10)), rng.normal(0, 0.6, (T, 3)), rng.normal(0, 0.4, (T, n)), rng.normal(0, 0.3, (T, 3))


def _smplx(mano_dir, side, betas, go, hp, tr, pca, n, flat):
    import torch
    import smplx

    layer = smplx.MANO(str(mano_dir), is_rhand=side == "right", use_pca=pca, num_pca_comps=n, flat_hand_mean=flat,
                       create_transl=False, dtype=torch.float64)
    out = layer(betas=torch.tensor(betas), global_orient=torch.tensor(go), hand_pose=torch.tensor(hp), transl=torch.tensor(tr))
    v = out.vertices.detach().numpy()
    return v, np.concatenate([out.joints.detach().numpy(), v[:, list(TIPS_SMPLX)]], 1)[:, list(TO_MANO21)]


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("pca,n,flat", [(False, 45, False),  # ARCTIC: axis-angle, flat_hand_mean False
                                        (False, 45, True),  # OakInk2 / HOI4D-style flat mean
                                        (True, 12, False),  # PCA with the mean pose added
                                        (True, 6, True)])
def test_numpy_mano_matches_smplx(mano_dir, side, pca, n, flat):
    betas, go, hp, tr = _params(n=n)
    model = ManoModel.find(mano_dir, side)
    ours = model.forward(betas, go, hp, tr, ManoConvention(pca=pca, flat_hand_mean=flat))
    v, j = _smplx(mano_dir, side, betas, go, hp, tr, pca, n, flat)
    assert np.abs(ours.vertices - v).max() < 1e-6 and np.abs(ours.joints - j).max() < 1e-6


def test_45_component_pca_is_the_axis_angle_pose_it_spans(mano_dir):
    """HO-Cap's 45-PCA hand pose (smplx treats 45 components as no PCA, manopth projects):
    the same as the axis-angle pose hp @ components, which smplx checks."""
    betas, go, hp, tr = _params(1)
    model = ManoModel.find(mano_dir, "right")
    ours = model.forward(betas, go, hp, tr, ManoConvention(pca=True, flat_hand_mean=False))
    v, j = _smplx(mano_dir, "right", betas, go, hp @ model.hands_components, tr, False, 45, False)
    assert np.abs(ours.joints - j).max() < 1e-6
    plain = model.forward(betas, go, hp, tr, ManoConvention(pca=False, flat_hand_mean=False))
    assert np.abs(plain.joints - ours.joints).max() > 1e-3  # the projection matters


def test_quaternions_tips_and_centring():
    from scipy.spatial.transform import Rotation

    aa = np.random.default_rng(2).normal(0, 1.2, (50, 3))
    xyzw = Rotation.from_rotvec(aa).as_quat()
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], 1) * np.where(np.arange(50) % 2, -1, 1)[:, None]  # either sign
    back = Rotation.from_rotvec(quat_wxyz_to_axis_angle(wxyz))
    assert (Rotation.from_rotvec(aa).inv() * back).magnitude().max() < 1e-9
    assert TIPS_MANOPTH != TIPS_SMPLX and len(set(TO_MANO21)) == 21


def test_centre_joint_is_where_transl_puts_it(mano_dir):
    betas, go, hp, tr = _params(3)
    out = ManoModel.find(mano_dir, "right").forward(betas, go, hp, tr, ManoConvention(center_joint=9, tips=TIPS_MANOPTH))
    assert np.allclose(out.joints[:, 9], tr)  # manotorch center_idx=9: the middle knuckle sits at trans


def test_missing_and_malformed_model_files(tmp_path, monkeypatch):
    monkeypatch.delenv("HANDEDIT_MANO_DIR", raising=False)
    with pytest.raises(ManoError, match="--mano-dir"):
        ManoModel.find(None, "right")
    with pytest.raises(ManoError, match="mano.is.tue.mpg.de"):
        ManoModel.find(tmp_path, "right")
    (tmp_path / "MANO_RIGHT.pkl").write_bytes(b"not a pickle")
    with pytest.raises(ManoError, match="not a readable MANO pickle"):
        ManoModel.load(tmp_path / "MANO_RIGHT.pkl")
    with open(tmp_path / "MANO_LEFT.pkl", "wb") as f:
        pickle.dump({"v_template": np.zeros((778, 3))}, f)
    with pytest.raises(ManoError, match="lacks"):
        ManoModel.load(tmp_path / "MANO_LEFT.pkl")


def test_chumpy_pickles_load_without_chumpy(tmp_path, mano_dir):
    """The official files hold chumpy arrays; a stand-in module pickles one like it."""
    mod = types.ModuleType("chumpy.ch")

    class Ch:
        def __init__(self, x):
            self.x = x

        def __reduce__(self):
            return (Ch, (), {"x": self.x})

    Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"
    mod.Ch = Ch
    sys.modules["chumpy"], sys.modules["chumpy.ch"] = types.ModuleType("chumpy"), mod
    try:
        with open(mano_dir / "MANO_RIGHT.pkl", "rb") as f:
            d = pickle.load(f, encoding="latin1")
        d["shapedirs"], d["v_template"] = Ch(d["shapedirs"]), Ch(d["v_template"])
        with open(tmp_path / "MANO_RIGHT.pkl", "wb") as f:
            pickle.dump(d, f, protocol=2)
    finally:
        del sys.modules["chumpy"], sys.modules["chumpy.ch"]
    a, b = ManoModel.load(tmp_path / "MANO_RIGHT.pkl"), ManoModel.load(mano_dir / "MANO_RIGHT.pkl")
    assert np.array_equal(a.shapedirs, b.shapedirs) and np.array_equal(a.v_template, b.v_template)
