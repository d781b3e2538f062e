"""deploy/: the Prefect deployments load, and every config they reference validates."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
import yaml
from prefect.flows import load_flow_from_entrypoint

from handedit.flows.config import ClusterConfig, CurateConfig
from handedit.flows.curate import load_config

REPO = Path(__file__).resolve().parents[1]
DEPLOY = yaml.safe_load((REPO / "deploy" / "prefect.yaml").read_text())


@pytest.mark.parametrize("deployment", DEPLOY["deployments"], ids=lambda d: d["name"])
def test_deployment_entrypoint_and_parameters(deployment, monkeypatch):
    monkeypatch.chdir(REPO)
    flow = load_flow_from_entrypoint(deployment["entrypoint"])
    params = inspect.signature(flow.fn).parameters
    assert set(deployment["parameters"]) <= set(params)
    required = {n for n, p in params.items() if p.default is inspect.Parameter.empty}
    assert required <= set(deployment["parameters"])
    if "config_path" in deployment["parameters"]:
        config = load_config(deployment["parameters"]["config_path"], deployment["parameters"].get("cluster_path"))
        assert config.clips and config.embodiments
        assert config.cluster.threads_per_worker == 1
    for schedule in deployment.get("schedules", []):
        assert len(schedule["cron"].split()) == 5


@pytest.mark.parametrize("path", sorted((REPO / "deploy" / "cluster").glob("*.yaml")), ids=lambda p: p.stem)
def test_cluster_specs_validate(path):
    spec = yaml.safe_load(path.read_text())
    cluster = ClusterConfig.model_validate(spec["cluster"])
    assert cluster.address or cluster.cluster_class or cluster.n_workers >= 1


@pytest.mark.parametrize("path", sorted((REPO / "deploy" / "configs").glob("*.yaml")), ids=lambda p: p.stem)
def test_run_configs_validate(path):
    assert CurateConfig.from_yaml(path).frames_per_chunk >= 1


def test_bad_config_names_the_file(tmp_path):
    bad = tmp_path / "run.yaml"
    bad.write_text("out: [unclosed\n")
    with pytest.raises(ValueError, match="run.yaml"):
        CurateConfig.from_yaml(bad)
