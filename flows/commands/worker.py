"""``handedit worker``: a Prefect process worker for the project's deployments that stops on SIGTERM.

    handedit worker --pool handedit [--name NAME] [--limit N] [--grace SECONDS]

Why not ``prefect worker start``: Prefect 3.8's CLI answers SIGTERM by sending itself
SIGINT, and the worker then keeps polling (measured here: still alive 90 s after SIGTERM,
its main thread in the event loop's select), so ``systemctl stop``, ``kill`` or a pod's
termination leaves it running until SIGKILL. This command runs the same ``ProcessWorker`` in
a task of its own. On SIGTERM or SIGINT it takes no new flow run, waits up to ``--grace``
seconds for the runs it started (a curation shard is minutes of work, and a run killed
halfway is a crashed run to retry), then leaves its pool and exits 0; a second signal stops
it at once.
"""

from __future__ import annotations

import argparse
import asyncio
import signal
import sys

GRACE_S = 600.0
# Without --limit the worker still counts its runs (through Prefect's own limiter, which it
# only creates for a limit): a limit no pool reaches
UNLIMITED = 1_000_000


async def drain(limiter, say) -> None:
    """Hold every token of the worker's ``limiter`` as its runs give theirs back: no new run
    can start (a waiting acquirer is served before any new one), and this returns once the
    runs in progress are done."""
    limiter.total_tokens = max(limiter.borrowed_tokens, 1)
    held: list[object] = []
    while (running := limiter.borrowed_tokens - len(held)) > 0:
        say(f"handedit worker: stopping: waiting for {running} flow run(s) in progress")
        held.append(token := object())
        await limiter.acquire_on_behalf_of(token)


async def serve(pool: str, name: str | None = None, limit: int | None = None, grace: float = GRACE_S) -> None:
    """Run a process worker on ``pool`` until SIGTERM or SIGINT (see the module doc)."""
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL
    from prefect.workers.process import ProcessWorker

    async with get_client() as client:  # Prefect's worker retries an unreachable API forever, a traceback a minute
        failed = await client.api_healthcheck()
    if failed is not None:
        raise ConnectionError(f"the Prefect API at {PREFECT_API_URL.value() or '(none: PREFECT_API_URL is unset)'} "
                              f"does not answer ({failed})")

    say = lambda line: print(line, flush=True)  # noqa: E731
    worker = ProcessWorker(work_pool_name=pool, name=name, limit=limit or UNLIMITED)
    task = asyncio.ensure_future(worker.start(printer=say))
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()

    def on_signal() -> None:
        if stop.is_set():
            say("handedit worker: a second signal: stopping now")
            task.cancel()
        stop.set()

    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, on_signal)

    async def stopper() -> None:
        await stop.wait()
        try:
            limiter = worker.limiter  # its runs are counted there once it has started
        except RuntimeError:  # not started yet: nothing in progress
            limiter = None
        if limiter is not None:
            try:
                await asyncio.wait_for(drain(limiter, say), grace)
            except asyncio.TimeoutError:
                say(f"handedit worker: {grace:.0f} s passed with flow runs still in progress: stopping them")
        task.cancel()  # cancelled in the task that entered the worker's scopes

    stopping = asyncio.ensure_future(stopper())
    try:
        await task
    except asyncio.CancelledError:
        say(f"handedit worker: stopped (pool {pool})")
    finally:
        stopping.cancel()


def cmd_worker(args: argparse.Namespace) -> int:
    try:
        asyncio.run(serve(args.pool, args.name, args.limit, args.grace))
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
    p.add_argument("--grace", type=float, default=GRACE_S, metavar="SECONDS",
                   help=f"on SIGTERM, wait this long for flow runs in progress (default {GRACE_S:.0f}; give your "
                        "service manager's stop timeout, e.g. systemd's TimeoutStopSec, a little more)")
    p.set_defaults(func=cmd_worker)
