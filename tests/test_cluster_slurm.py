"""Curating on Slurm for real (issue 37): a single-node Slurm from Debian's packages
(``deploy/slurm-local.sh``, the README's steps), workers submitted with ``sbatch`` by
dask-jobqueue's ``SLURMCluster`` from ``deploy/cluster/slurm-local.yaml``. The demo's store
equals a LocalCluster run's byte for byte, and still does when a worker job is cancelled
mid-run (``scancel``)."""

from __future__ import annotations

import os
import random
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from test_integrity import assert_same_bytes

REPO = Path(__file__).resolve().parents[1]
HANDEDIT = [sys.executable, "-m", "handedit.flows.cli"]


def _free_port_pair(rng: random.Random) -> int:
    """Two consecutive ports free on every interface (slurmctld and slurmd bind 0.0.0.0), drawn
    below Linux's ephemeral range: a port the kernel just gave a client (or a server on one
    interface) passes a 127.0.0.1 check and still makes slurmd's bind fail."""
    for _ in range(200):
        p = rng.randrange(20000, 32000)
        with socket.socket() as a, socket.socket() as b:
            try:
                a.bind(("", p))
                b.bind(("", p + 1))
                return p
            except OSError:
                continue
    raise RuntimeError("no two free consecutive ports in 20000-32000")


@pytest.fixture(scope="module")
def slurm(tmp_path_factory):
    if os.geteuid() != 0:
        pytest.fail("the Slurm test starts slurmctld and slurmd as root (CI runs as root)")
    rng, errors = random.Random(os.getpid()), []
    for _ in range(3):  # a port taken between the check and slurmd's bind: start again on others
        d = tmp_path_factory.mktemp("slurm")
        env = {**os.environ, "SLURM_PORT": str(_free_port_pair(rng))}
        start = subprocess.run(["bash", str(REPO / "deploy" / "slurm-local.sh"), "start", str(d)], env=env,
                               capture_output=True, text=True, timeout=600)
        if start.returncode == 0:
            break
        errors.append(start.stderr)
        subprocess.run(["bash", str(REPO / "deploy" / "slurm-local.sh"), "stop", str(d)], env=env, timeout=60)
    assert start.returncode == 0, "\n".join(errors)
    conf = start.stdout.strip().rsplit("=", 1)[-1]
    env["SLURM_CONF"] = conf
    yield env, d
    subprocess.run(["bash", str(REPO / "deploy" / "slurm-local.sh"), "stop", str(d)], env=env, timeout=60)


def _squeue(env, *args) -> list[str]:
    out = subprocess.run(["squeue", "-h", *args], env=env, capture_output=True, text=True, timeout=30)
    return out.stdout.split()


def test_the_demo_on_slurm_is_the_local_run_byte_for_byte(slurm, tmp_path):
    env, d = slurm
    spec = yaml.safe_load((REPO / "deploy" / "cluster" / "slurm-local.yaml").read_text())
    spec["cluster"]["cluster_kwargs"]["log_directory"] = str(d / "jobs")
    cluster = tmp_path / "slurm.yaml"
    cluster.write_text(yaml.safe_dump(spec))
    t0 = time.perf_counter()
    done = subprocess.run([*HANDEDIT, "curate", "--demo", "--out", str(tmp_path / "local"), "--no-progress"],
                          env=env, capture_output=True, text=True, timeout=900)
    local_s = time.perf_counter() - t0
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]

    # the same demo on Slurm, one worker job cancelled mid-run: the other finishes its tasks, nothing is lost,
    # and the store is the LocalCluster's byte for byte (one Slurm run proves both: CI time)
    out = tmp_path / "cancelled"
    t0 = time.perf_counter()
    proc = subprocess.Popen([*HANDEDIT, "curate", "--demo", "--out", str(out), "--no-progress", "--cluster", str(cluster)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline, cancelled = time.time() + 300, None
    while time.time() < deadline and proc.poll() is None:
        running = _squeue(env, "-t", "R", "-o", "%i")
        records = out / "handedit.zarr.records" / "clips"
        if len(running) >= 2 and records.is_dir() and any(records.rglob("embodiments/*/retarget/*.json")):
            cancelled = sorted(running, key=int)[0]
            subprocess.run(["scancel", cancelled], env=env, check=True, timeout=30)
            break
        time.sleep(0.5)
    stdout, stderr = proc.communicate(timeout=900)
    slurm_s = time.perf_counter() - t0
    assert cancelled is not None, "the run ended before a job could be cancelled: " + stdout[-1000:]
    assert proc.returncode == 0, stdout[-2000:] + stderr[-3000:]
    assert "SLURMCluster started for the run (2 jobs)" in stdout
    submitted = sorted((d / "jobs").glob("*.err")) or sorted((d / "jobs").glob("*.out"))
    assert len(submitted) >= 2, "the workers ran as Slurm jobs (their logs)"
    assert cancelled not in _squeue(env, "-o", "%i")
    assert_same_bytes(tmp_path / "local", out)
    print(f"\ndemo: LocalCluster {local_s:.1f} s, SLURMCluster (one job cancelled) {slurm_s:.1f} s")
