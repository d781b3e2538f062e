"""One Prefect API per run, and nothing left behind when the driver is SIGKILLed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil


def _is_api_server(p: psutil.Process) -> bool:
    try:
        return "prefect.server.api.server:create_app" in " ".join(p.cmdline())
    except psutil.Error:
        return False


def _is_top_api_server(p: psutil.Process) -> bool:
    """An API server that is not a child of one: a process the server forks shows the server's
    command line until it execs (caught once on a loaded machine), and is not a second API."""
    try:
        return _is_api_server(p) and not _is_api_server(p.parent())
    except psutil.Error:
        return False


def test_killed_driver_leaves_no_process_behind(tmp_path: Path):
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}  # the run starts its own API
    out = tmp_path / "run"
    driver = subprocess.Popen([sys.executable, "-m", "handedit.flows.cli", "curate", "--demo", "--clips", "2", "--frames",
                               "32", "--width", "96", "--height", "72", "--out", str(out), "--no-progress"],
                              env=env, stdout=open(tmp_path / "driver.log", "w"), stderr=subprocess.STDOUT)
    seen: dict[int, psutil.Process] = {}
    servers: set[int] = set()
    deadline = time.time() + 300
    while time.time() < deadline and driver.poll() is None:
        for p in psutil.Process(driver.pid).children(recursive=True):
            seen.setdefault(p.pid, p)
            if _is_top_api_server(p):
                servers.add(p.pid)
        if (out / "handedit.zarr" / "clips").exists() and len(seen) >= 3:
            break  # the cluster is working: chunks are being written
        time.sleep(0.5)
    assert driver.poll() is None, (tmp_path / "driver.log").read_text()[-3000:]
    time.sleep(3)
    for p in psutil.Process(driver.pid).children(recursive=True):
        seen.setdefault(p.pid, p)
        if _is_top_api_server(p):
            servers.add(p.pid)
    assert len(servers) == 1, f"expected the run's one API server, saw {len(servers)}"  # workers start none
    os.kill(driver.pid, signal.SIGKILL)
    driver.wait(30)
    deadline = time.time() + 60
    alive = list(seen.values())
    while time.time() < deadline:
        alive = [p for p in seen.values() if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
        if not alive:
            break
        time.sleep(1)
    assert not alive, [" ".join(p.cmdline())[:100] for p in alive]
