"""``handedit worker``: a Prefect process worker for the project's deployments that stops on SIGTERM.

    handedit worker --pool handedit [--name NAME] [--limit N]

Why not ``prefect worker start``: Prefect 3.8's CLI answers SIGTERM by sending itself
SIGINT, and the worker then keeps polling (measured here: still alive 90 s after SIGTERM,
its main thread in the event loop's select), so ``systemctl stop``, ``kill`` or a pod's
termination leaves it running until SIGKILL. This command runs the same ``ProcessWorker`` in
a task of its own and cancels that task on SIGTERM or SIGINT: the worker leaves its pool
and the command exits 0 within seconds.
"""

from __future__ import annotations

import argparse
import asyncio
import signal
import sys


async def serve(pool: str, name: str | None = None, limit: int | None = None) -> None:
    """Run a process worker on ``pool`` until SIGTERM or SIGINT."""
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL
    from prefect.workers.process import ProcessWorker

    async with get_client() as client:  # Prefect's worker retries an unreachable API forever, a traceback a minute
        failed = await client.api_healthcheck()
    if failed is not None:
        raise ConnectionError(f"the Prefect API at {PREFECT_API_URL.value() or '(none: PREFECT_API_URL is unset)'} "
                              f"does not answer ({failed})")

    async def work() -> None:
        async with ProcessWorker(work_pool_name=pool, name=name, limit=limit) as worker:
            await worker.start(printer=print)

    task = asyncio.ensure_future(work())
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, task.cancel)  # cancelled in the task that entered the worker's scopes
    try:
        await task
    except asyncio.CancelledError:
        print(f"handedit worker: stopped (pool {pool})", flush=True)


def cmd_worker(args: argparse.Namespace) -> int:
    try:
        asyncio.run(serve(args.pool, args.name, args.limit))
    except ConnectionError as exc:
        print(f"handedit worker: {exc}; start the server (`prefect server start`) and set PREFECT_API_URL to it on "
              f"this shell, e.g. export PREFECT_API_URL=http://HOST:4200/api", file=sys.stderr)
        return 1
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("worker", help="a Prefect process worker for the deployments (stops on SIGTERM)")
    p.add_argument("--pool", required=True, help="the work pool (deploy/prefect.yaml's deployments name it)")
    p.add_argument("--name", help="the worker's name (default: Prefect's)")
    p.add_argument("--limit", type=int, help="at most this many flow runs at once")
    p.set_defaults(func=cmd_worker)
