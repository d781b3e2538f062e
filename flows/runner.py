"""The Prefect task runner of every flow: prefect-dask's, with Dask keys that say what a task does.

prefect-dask submits every task as the same wrapper function, so Dask's dashboard groups them
all under one name and its *Progress* panel shows a single bar. Here a task's Dask key starts
with the embodiment it works for (``("xarm_ability", <run id>)``), or else with the task's
name (``curate_clip``, ``write_release_shard``): the Progress panel shows one bar per
embodiment, and one for the clips, each with its tasks done of those submitted (the panel cuts
a label at about 15 characters, so the embodiment comes first).
"""

from __future__ import annotations

from typing import Any, Iterable

from prefect_dask import DaskTaskRunner
from prefect_dask.task_runners import PrefectDaskFuture


def task_key(task_name: str, parameters: dict[str, Any], run_id: str) -> tuple[str, str]:
    """A Dask key whose prefix (``dask.utils.key_split``: a tuple's first item, up to its first
    ``-``) names the work; the run id makes it unique."""
    emb = parameters.get("emb_id")
    return str(emb or task_name).replace("-", "_"), run_id


class LabelledDaskTaskRunner(DaskTaskRunner):
    """prefect-dask's runner; only the Dask key of each submitted task differs (``task_key``)."""

    def submit(self, task, parameters: dict[str, Any], wait_for: Iterable | None = None,
               dependencies: dict | None = None) -> PrefectDaskFuture:
        if not self._started:
            raise RuntimeError("The task runner must be started before submitting work.")
        from uuid import uuid4

        future = self.client.submit(task, key=task_key(task.name, parameters, uuid4().hex),
                                    parameters=self._optimize_futures(parameters),
                                    wait_for=self._optimize_futures(wait_for) if wait_for else None,
                                    dependencies=dependencies, return_type="state")
        return PrefectDaskFuture(wrapped_future=future, task_run_id=future.task_run_id)


def task_runner(address: str) -> LabelledDaskTaskRunner:
    """The task runner for a flow on the Dask cluster at ``address``."""
    return LabelledDaskTaskRunner(address=address)


__all__ = ["LabelledDaskTaskRunner", "task_key", "task_runner"]
