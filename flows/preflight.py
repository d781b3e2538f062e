"""Workers checked before any task: the store, the Prefect API and the robots, from each worker.

A worker on another host that cannot reach the run's store or Prefect API, or lacks the robot
assets, would otherwise fail deep inside its first task (or retry an HTTP call for minutes).
``check_workers`` registers ``WorkerPreflight`` on the cluster: each worker, as it joins, checks
what the run needs from where it runs, and the first problem comes back to the driver as one
``WorkerSetupError`` naming the worker's host, the setting and the fix. Workers that join later
(adaptive or job-queue clusters) run the same checks and log the same message.
"""

from __future__ import annotations

import os
import socket

from distributed.diagnostics.plugin import WorkerPlugin

from handedit.flows.config import PreflightError

API_TIMEOUT_S = 5.0


class WorkerSetupError(PreflightError):
    """A worker that cannot do the run's work where it runs."""


def worker_problems(store_url: str, api_url: str | None, embodiments: list[str], robots: list[str] = ()) -> list[str]:
    """What this process lacks for the run (empty: ready); ``robots``: the run's robot folders,
    added as its embodiment tasks add them."""
    from handedit.storage.location import Location

    problems = []
    try:
        ok = Location(store_url).store_exists()
        why = "it does not exist here"
    except Exception as exc:  # noqa: BLE001 - any failure to look is the answer
        ok, why = False, f"{type(exc).__name__}: {exc}"
    if not ok:
        problems.append(f"cannot reach the store {store_url} ({why}); every worker needs it at the same path or URL: "
                        f"put --out on storage every host mounts there, or use object storage (s3://...) with its "
                        f"credentials in the workers' environment")
    if api_url:  # the run's API: Prefect sends its settings with every task, so this is the URL workers use
        import httpx

        try:
            httpx.get(api_url.rstrip("/") + "/health", timeout=API_TIMEOUT_S).raise_for_status()
        except Exception as exc:  # noqa: BLE001
            problems.append(f"cannot reach the run's Prefect API at {api_url} ({type(exc).__name__}: {exc}); run the "
                            f"server on a host the workers reach (`prefect server start --host 0.0.0.0`) and set "
                            f"PREFECT_API_URL to that address on the driver")
    from handedit.embodiments import EmbodimentError, get_embodiment, resolve_urdf
    from handedit.embodiments.robot_files import robot_dirs_added

    for emb_id in embodiments:
        try:
            with robot_dirs_added(list(robots)):
                resolve_urdf(get_embodiment(emb_id))
        except EmbodimentError as exc:
            problems.append(f"embodiment {emb_id}: {exc} (HANDEDIT_ASSET_DIRS here: "
                            f"{os.environ.get('HANDEDIT_ASSET_DIRS')!r}; set it on the workers as on the driver)")
    return problems


class WorkerPreflight(WorkerPlugin):
    name = "handedit-preflight"

    def __init__(self, store_url: str, api_url: str | None, embodiments: list[str], robots: list[str] = ()):
        self.store_url, self.api_url, self.embodiments, self.robots = store_url, api_url, list(embodiments), list(robots)

    def setup(self, worker) -> None:
        problems = worker_problems(self.store_url, self.api_url, self.embodiments, self.robots)
        if problems:
            host = f"{socket.gethostname()} ({worker.address})"
            raise WorkerSetupError(f"worker {host}: " + "; ".join(problems))


def check_workers(address: str, store_url: str, embodiments: list[str], timeout_s: float, robots: list[str] = ()) -> None:
    """Wait for a first worker, then check every worker (``WorkerSetupError`` on the first problem)."""
    from distributed import Client

    from handedit.flows.api import configured_url

    api = configured_url() or os.environ.get("PREFECT_API_URL")
    with Client(address, timeout=30) as client:
        try:
            client.wait_for_workers(1, timeout=timeout_s)
        except TimeoutError:
            return  # no worker yet: the run's watchdog reports a cluster without workers
        client.register_plugin(WorkerPreflight(store_url, api, embodiments, robots))
