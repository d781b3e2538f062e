"""One Prefect API per run, and nothing left behind when the driver dies.

With no ``PREFECT_API_URL`` configured, Prefect starts a temporary API server in every
process that runs a flow or task: the driver and each Dask worker (three ``uvicorn``
processes of ~230 MB for a two-worker local run), and a SIGKILLed driver orphans all of
them. Here the driver starts the one server itself, tied to its own life (Linux
``PR_SET_PDEATHSIG``: the kernel stops it when the driver dies, however it dies), and puts
its URL in the environment before the local cluster starts, so workers use that API.

A configured ``PREFECT_API_URL`` (a ``prefect server start`` or Prefect Cloud) is used as
is. Workers of an existing cluster (``--address``) must have it in their environment
(``deploy/cluster/*.yaml``): a temporary server on 127.0.0.1 is not reachable from them.
"""

from __future__ import annotations

import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:  # not Linux: the atexit stop below still covers normal exits
        pass


def configured_url() -> str | None:
    from prefect.settings import get_current_settings

    url = get_current_settings().api.url
    return str(url) if url else None


_TEMPORARY: list[str] = []  # the URL of the temporary API this process started, while it runs


def api_is_temporary() -> bool:
    """Whether this run's Prefect API is the temporary one ``run_api`` started (its pages
    are gone when the command exits)."""
    return bool(_TEMPORARY)


def run_url() -> str | None:
    """The Prefect UI page of the current flow run (None without a UI, e.g. a temporary API)."""
    try:
        from prefect.runtime import flow_run

        return flow_run.ui_url
    except Exception:  # noqa: BLE001 - a link, never a reason to fail
        return None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class RunServer:
    """A Prefect API server on 127.0.0.1 that lives exactly as long as this process."""

    def __init__(self, timeout_s: float = 180.0):
        self.timeout_s, self.proc, self.port = timeout_s, None, _free_port()

    @property
    def api_url(self) -> str:
        return f"http://127.0.0.1:{self.port}/api"

    def start(self) -> "RunServer":
        import httpx
        import prefect
        from prefect.settings import get_current_settings

        env = {**os.environ, **get_current_settings().to_environment_variables(exclude_unset=True),
               "PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1", "PREFECT__SERVER_FINAL": "1"}
        env.pop("PREFECT_API_URL", None)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "--app-dir", str(Path(prefect.__file__).parent.parent), "--factory",
             "prefect.server.api.server:create_app", "--host", "127.0.0.1", "--port", str(self.port),
             "--log-level", "error", "--lifespan", "on"],
            env=env, preexec_fn=_die_with_parent, stdout=subprocess.DEVNULL)
        deadline = time.monotonic() + self.timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"the run's Prefect API server exited with code {self.proc.returncode}; "
                                   f"set PREFECT_API_URL to a running server (`prefect server start`)")
            try:
                if httpx.get(f"{self.api_url}/health", timeout=2).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"the run's Prefect API server did not answer within {self.timeout_s:.0f} s; "
                           f"set PREFECT_API_URL to a running server (`prefect server start`)")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc = None


@contextmanager
def run_api():
    """The API URL every process of this run talks to (see module doc)."""
    url = configured_url()
    if url:
        yield url
        return
    from prefect.settings import PREFECT_API_URL, temporary_settings

    timeout = float(os.environ.get("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", 180))
    server = RunServer(timeout).start()
    os.environ["PREFECT_API_URL"] = server.api_url  # inherited by the local cluster's workers
    _TEMPORARY.append(server.api_url)
    try:
        with temporary_settings({PREFECT_API_URL: server.api_url}):
            yield server.api_url
    finally:
        _drain()  # the run's last logs and events reach the server before it stops
        _TEMPORARY.remove(server.api_url)
        os.environ.pop("PREFECT_API_URL", None)
        server.stop()


def _drain(timeout_s: float = 15.0) -> None:
    from prefect.events.worker import EventsWorker
    from prefect.logging.handlers import APILogWorker

    for worker in (APILogWorker, EventsWorker):
        try:
            worker.drain_all(timeout=timeout_s)
        except Exception:  # noqa: BLE001 - best effort: the data is in the store either way
            pass
