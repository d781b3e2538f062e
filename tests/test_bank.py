"""Reference bank: ``handedit bank build`` -> Zarr store -> ``storage.bank.read_bank``."""

from __future__ import annotations

import numpy as np
import pytest

from handedit.flows.cli import main
from handedit.embodiments import get_embodiment
from handedit.storage.bank import bank_embodiments, read_bank, read_bank_entry
from handedit.storage.store import StoreError


@pytest.fixture(autouse=True)
def _env(monkeypatch, robots_dir, tmp_path_factory):
    monkeypatch.setenv("HANDEDIT_ASSET_DIRS", str(robots_dir))
    monkeypatch.setenv("HANDEDIT_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "cache"))


def test_bank_build_and_read(tmp_path, capsys):
    out = tmp_path / "bank.zarr"
    rc = main(["bank", "build", "--out", str(out), "--views", "3", "--width", "96", "--height", "80",
               "--embodiment", "schunk_svh", "--embodiment", "xarm_ability"])
    assert rc == 0
    assert bank_embodiments(out) == ["schunk_svh", "xarm_ability"]
    for emb_id in ("schunk_svh", "xarm_ability"):
        rgb, mask, desc, name = read_bank(out, emb_id)
        emb = get_embodiment(emb_id)
        assert rgb.shape == (3, 80, 96, 3) and rgb.dtype == np.uint8 and mask.shape == (3, 80, 96)
        assert desc == emb.description and name == emb.name
        for v in range(3):
            assert mask[v].sum() > 0.02 * mask[v].size
            assert not np.concatenate([mask[v, 0], mask[v, -1], mask[v, :, 0], mask[v, :, -1]]).any()
            assert not rgb[v][~mask[v]].any() and rgb[v][mask[v]].any()
        assert not np.array_equal(mask[0], mask[1]), "views differ"
    e = read_bank_entry(out, "xarm_ability")
    assert e.qpos.shape == (3, 13) and e.camera_from_root.shape == (3, 4, 4) and e.track == "hand_arm"
    # fixed rig and seed: rebuilding gives the same pixels
    out2 = tmp_path / "again.zarr"
    assert main(["bank", "build", "--out", str(out2), "--views", "3", "--width", "96", "--height", "80",
                 "--embodiment", "schunk_svh"]) == 0
    np.testing.assert_array_equal(read_bank(out2, "schunk_svh")[0], read_bank(out, "schunk_svh")[0])
    with pytest.raises(StoreError, match="not in reference bank.*bank build --embodiment leap"):
        read_bank(out, "leap")


def test_bank_build_errors_are_clear(tmp_path, capsys):
    out = tmp_path / "bank.zarr"
    assert main(["bank", "build", "--out", str(out), "--embodiment", "nope"]) == 2
    assert "unknown embodiment id 'nope'" in capsys.readouterr().err
    assert main(["bank", "build", "--out", str(out), "--embodiment", "rh5dg2"]) == 2
    assert "rh5dg2_right.urdf" in capsys.readouterr().err
    with pytest.raises(StoreError, match="does not exist.*bank build"):
        read_bank(tmp_path / "none.zarr", "leap")


def test_embodiments_list_cli(capsys):
    assert main(["embodiments", "list"]) == 0
    out = capsys.readouterr().out
    lines = [l for l in out.splitlines() if l.split() and l.split()[0] in {"allegro", "ur5_shadow", "rohand", "rh5dg2", "panda_orca"}]
    assert len(lines) == 5
    table = {l.split()[0]: l for l in lines}
    assert " 16 " in table["allegro"] and "hand " in table["allegro"]
    assert " 30 " in table["ur5_shadow"] and "hand_arm" in table["ur5_shadow"]
    assert table["rh5dg2"].rstrip().endswith("missing") and " 24 " in table["panda_orca"]
    assert " 6 " in table["rohand"]  # its 6 actuators, the 19 linkage joints derived
    assert "24/26 embodiments available" in out
