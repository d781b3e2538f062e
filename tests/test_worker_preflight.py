"""Workers that cannot do the run's work (issue 37): a worker started by its own CLI without the
robot assets, or on another host (its own network namespace) that cannot reach the run's
Prefect API, fails the run at once with one message naming its host, the setting and the fix;
a store path a worker host lacks is named too."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from _servers import free_port, prefect_server
from handedit.flows.preflight import worker_problems

HANDEDIT = [sys.executable, "-m", "handedit.flows.cli"]


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    """A Prefect server of its own (the driver's PREFECT_API_URL; workers may or may not reach it)."""
    proc, url = prefect_server("127.0.0.1", tmp_path_factory.mktemp("prefect-home"))
    yield url
    proc.terminate()
    proc.wait(timeout=30)


def _run(*cmd: str) -> None:
    subprocess.run(cmd, check=True, capture_output=True, timeout=30)


@pytest.fixture()
def other_host():
    """A network namespace joined to this one by a veth pair: 10.77.9.1 here, 10.77.9.2 there
    (the project's own test host; root, as in CI)."""
    if os.geteuid() != 0:
        pytest.fail("the other host is a network namespace: `ip netns` needs root (CI runs as root)")
    ns, here, there = f"he-t{os.getpid() % 10000}", f"het{os.getpid() % 10000}h", f"het{os.getpid() % 10000}n"
    _run("ip", "netns", "add", ns)
    try:
        _run("ip", "link", "add", here, "type", "veth", "peer", "name", there)
        _run("ip", "link", "set", there, "netns", ns)
        _run("ip", "addr", "add", "10.77.9.1/24", "dev", here)
        _run("ip", "link", "set", here, "up")
        for cmd in (["ip", "addr", "add", "10.77.9.2/24", "dev", there], ["ip", "link", "set", there, "up"],
                    ["ip", "link", "set", "lo", "up"]):
            _run("ip", "netns", "exec", ns, *cmd)
        yield ns
    finally:
        subprocess.run(["ip", "link", "del", here], capture_output=True)
        subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def _cluster(worker_env: dict, netns: str | None = None):
    """``dask scheduler`` and one ``dask worker``, each started by its own CLI (the worker in
    ``netns`` when given: another host, reaching the scheduler over the veth pair)."""
    port = free_port()
    host = "10.77.9.1" if netns else "127.0.0.1"
    sched = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", host, "--port",
                              str(port), "--dashboard-address", "127.0.0.1:0"], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
    prefix = ["ip", "netns", "exec", netns] if netns else []
    worker = subprocess.Popen([*prefix, sys.executable, "-m", "distributed.cli.dask_worker", f"tcp://{host}:{port}",
                               "--nthreads", "1", "--nworkers", "1", "--no-dashboard"], env=worker_env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return f"tcp://{host}:{port}", (sched, worker)


def _curate(address: str, env: dict, out: Path) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.perf_counter()
    done = subprocess.run([*HANDEDIT, "curate", "--demo", "--clips", "1", "--out", str(out), "--embodiment", "xarm_ability",
                           "--address", address, "--no-progress"], env=env, capture_output=True, text=True, timeout=600)
    return done, time.perf_counter() - t0


def _stop(procs) -> None:
    for p in procs:
        p.terminate()
        p.wait(timeout=30)


def _told(done: subprocess.CompletedProcess, seconds: float) -> str:
    """The run stopped at once (exit 2, not after a task's retries) with one line about a worker."""
    assert done.returncode == 2, done.stdout[-2000:] + done.stderr[-3000:]
    assert seconds < 120, f"told after {seconds:.0f} s"
    return next(l for l in done.stderr.splitlines() if l.startswith("handedit curate: worker "))


def test_a_worker_without_the_robot_assets_fails_the_run_at_once(api, robots_dir, tmp_path):
    driver = {**os.environ, "PREFECT_API_URL": api, "HANDEDIT_ASSET_DIRS": str(robots_dir)}
    worker = {k: v for k, v in driver.items() if k != "HANDEDIT_ASSET_DIRS"}
    worker["HANDEDIT_CACHE_DIR"] = str(tmp_path / "empty-cache")  # nor fetched ones
    address, procs = _cluster(worker)
    try:
        done, seconds = _curate(address, driver, tmp_path / "run")
    finally:
        _stop(procs)
    line = _told(done, seconds)
    assert socket.gethostname() in line and "embodiment xarm_ability" in line and "HANDEDIT_ASSET_DIRS" in line


def test_a_worker_host_that_cannot_reach_the_prefect_api_fails_the_run_at_once(api, robots_dir, tmp_path, other_host):
    """The API listens on 127.0.0.1 here: the worker's host (its namespace) cannot reach it."""
    driver = {**os.environ, "PREFECT_API_URL": api, "HANDEDIT_ASSET_DIRS": str(robots_dir)}
    address, procs = _cluster(driver, netns=other_host)
    try:
        done, seconds = _curate(address, driver, tmp_path / "run")
    finally:
        _stop(procs)
    line = _told(done, seconds)
    assert "tcp://10.77.9.2:" in line and f"cannot reach the run's Prefect API at {api}" in line
    assert "PREFECT_API_URL" in line


def test_a_store_the_worker_host_lacks_is_named(tmp_path):
    missing = tmp_path / "only-on-the-driver" / "handedit.zarr"
    problems = worker_problems(str(missing), None, [])
    assert len(problems) == 1 and str(missing.parent) in problems[0] and "s3://" in problems[0]
