"""Servers the tests start as real processes: a free port, a Prefect server on a given host."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def prefect_server(host: str, home: Path, env: dict | None = None, timeout_s: float = 120.0) -> tuple[subprocess.Popen, str]:
    """``prefect server start`` on ``host`` with its own ``PREFECT_HOME``; returns the process and
    its API URL once ``/health`` answers (the caller stops the process)."""
    import httpx

    env = {**(env or os.environ), "PREFECT_HOME": str(home), "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
           "PREFECT_SERVER_UI_ENABLED": "false"}
    env.pop("PREFECT_API_URL", None)
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "prefect", "server", "start", "--host", host, "--port", str(port)],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    url = f"http://{host}:{port}/api"
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        try:
            if httpx.get(url + "/health", timeout=2).status_code == 200:
                return proc, url
        except httpx.HTTPError:
            pass
        time.sleep(0.5)
    proc.kill()
    raise RuntimeError(f"the Prefect server on {host}:{port} did not answer /health in {timeout_s:.0f} s")
