"""The ``handedit`` command: the README's main job (small), inspection commands, bad input."""

from __future__ import annotations

import pytest

from handedit.flows.cli import main


def test_curate_demo_then_status_ledger_dashboard(tmp_path, capsys, prefect_api, dask_cluster):
    out = tmp_path / "run"
    code = main(["curate", "--demo", "--out", str(out), "--clips", "1", "--frames", "8", "--width", "160",
                 "--height", "120", "--frames-per-chunk", "8", "--address", dask_cluster.scheduler_address,
                 "--no-progress"])
    text = capsys.readouterr().out
    assert code == 0
    assert str(out / "handedit.zarr") in text and "dask dashboard:" in text
    assert "harmonize" in text and "rejections:" in text
    assert main(["status", str(out)]) == 0
    status = capsys.readouterr().out
    assert "qc" in status and "OK" in status
    assert main(["ledger", str(out), "--csv"]) == 0
    assert capsys.readouterr().out.startswith("stage,clip,scope,embodiment,side,frame,reason,reason_name,detail")
    assert main(["dashboard", str(out)]) == 0
    page = (out / "qa.html").read_text()
    assert "Kept frames" in page and "synthetic-0000" in page and "data:image/png;base64" in page


def test_unknown_embodiment_fails_before_any_work(tmp_path, capsys):
    assert main(["curate", "--demo", "--out", str(tmp_path / "x"), "--embodiment", "allegr0"]) == 2
    err = capsys.readouterr().err
    assert "unknown embodiment id 'allegr0'" in err and "allegro" in err
    assert not (tmp_path / "x").exists()


def test_inspecting_something_that_is_not_a_store(tmp_path, capsys):
    assert main(["ledger", str(tmp_path)]) == 2
    assert "not a handedit store" in capsys.readouterr().err


def test_curate_needs_an_input(tmp_path):
    with pytest.raises(SystemExit, match="give --demo, --video FILE, --source NAME --root DIR or --config FILE"):
        main(["curate", "--out", str(tmp_path)])


def test_bad_values_are_one_line_each_before_any_work(tmp_path, capsys, caplog):
    import yaml

    from handedit.flows.config import CurateConfig
    from handedit.flows.curate import preflight

    with pytest.raises(SystemExit, match="--clips 0: give 1 or more"):
        main(["curate", "--demo", "--clips", "0", "--out", str(tmp_path / "x")])
    assert main(["curate", "--demo", "--clips", "1", "--width", "8", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "width: Input should be greater than or equal to 16" in err and "pydantic" not in err
    for bad in ("8", -5):  # a string where a count belongs, a negative count: refused with the config, not later
        cfg = tmp_path / f"bad{bad}.yaml"
        cfg.write_text(yaml.safe_dump({"out": str(tmp_path / "y"), "clips": [{"kind": "synthetic", "n_frames": bad}]}))
        with pytest.raises(ValueError, match="n_frames"):
            CurateConfig.from_yaml(cfg)
    # --out inside the dataset's tree: a warning, not a refusal
    tree = tmp_path / "egodex"
    tree.mkdir()
    import logging

    with caplog.at_level(logging.WARNING):
        preflight(CurateConfig(out=str(tree / "runs" / "a"), sources=[{"kind": "egodex", "root": str(tree)}]))
    assert "inside the source tree" in caplog.text
