"""Prefect options shared by every stage task: retries live here, caching is ours."""

from __future__ import annotations

from prefect.cache_policies import NO_CACHE

from handedit.tasks.common import RETRIES, RETRY_DELAYS, retry_transient


def stage_options(stage: str) -> dict:
    """Options for ``@task``; provenance keys (storage.provenance) replace Prefect caching."""
    return {
        "name": stage,
        "retries": RETRIES,
        "retry_delay_seconds": RETRY_DELAYS,
        "retry_condition_fn": retry_transient,
        "cache_policy": NO_CACHE,
        "persist_result": False,
        "task_run_name": stage + "[{job.unit.clip}|{job.unit.embodiment}|{job.unit.scope}]#{job.chunk}",
    }
