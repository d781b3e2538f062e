"""Shared fixtures: where ../shared lives, and test isolation for Prefect and EGL."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

import pytest


def _scratch(prefix: str) -> str:
    """A temporary folder removed when the test run ends (left behind, each run's Prefect home and
    cache, ~20 MB, piled up in /tmp)."""
    path = tempfile.mkdtemp(prefix=prefix)
    atexit.register(shutil.rmtree, path, ignore_errors=True)
    return path


# Before Prefect is imported anywhere: an isolated home, no telemetry, quiet logs.
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
if "PREFECT_HOME" not in os.environ:
    os.environ["PREFECT_HOME"] = _scratch("handedit-prefect-")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "error")
# A private cache: derived URDFs are rebuilt, and robots a developer fetched into the user
# cache (which the roster searches by default) cannot make "missing asset" tests pass or fail.
# The hand models `handedit models fetch` put in the user cache (deploy/setup.sh) stay found.
if "HANDEDIT_HAND_MODEL_DIR" not in os.environ:
    from handedit.models.fetch import default_model_dir

    os.environ["HANDEDIT_HAND_MODEL_DIR"] = str(default_model_dir())
os.environ["HANDEDIT_CACHE_DIR"] = _scratch("handedit-cache-")

REPO = Path(__file__).resolve().parents[1]


def _shared_dir() -> Path:
    """``$HANDEDIT_SHARED``, else ``shared/`` beside the repository, else (a clone of a local
    checkout, e.g. ``git clone . /tmp/x``) beside the repository it was cloned from."""
    if os.environ.get("HANDEDIT_SHARED"):
        return Path(os.environ["HANDEDIT_SHARED"])
    beside = REPO.parent / "shared"
    if beside.exists():
        return beside
    import subprocess

    try:
        origin = subprocess.run(["git", "-C", str(REPO), "config", "--get", "remote.origin.url"], capture_output=True,
                                text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        origin = ""
    if origin and "://" not in origin and Path(origin).is_dir():
        candidate = Path(origin).resolve().parent / "shared"
        if candidate.exists():
            return candidate
    return beside


SHARED = _shared_dir()


def _need(path: Path, what: str) -> Path:
    if not path.exists():
        pytest.fail(
            f"{what} not found at {path}. Tests need the project's shared/ folder beside the repo "
            f"(or HANDEDIT_SHARED=/path/to/shared).",
            pytrace=False,
        )
    return path


@pytest.fixture(autouse=True)
def _robot_dirs_not_leaked():
    """A run's or a checked file's robot folders count only while it runs
    (``robot_files.robot_dirs_added``). A test that leaves ``$HANDEDIT_ROBOT_DIRS`` changed has
    found a leak: it fails here, by name, instead of later tests failing on its removed tmp_path."""
    from handedit.embodiments.robot_files import ROBOT_DIRS_ENV

    before = os.environ.get(ROBOT_DIRS_ENV)
    yield
    after = os.environ.get(ROBOT_DIRS_ENV)
    if after != before:
        if before is None:
            os.environ.pop(ROBOT_DIRS_ENV, None)
        else:
            os.environ[ROBOT_DIRS_ENV] = before
        pytest.fail(f"the test left ${ROBOT_DIRS_ENV}={after!r} (it was {before!r}): a robot folder outlived its scope",
                    pytrace=False)


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    return _need(SHARED, "shared/ folder")


@pytest.fixture(scope="session")
def robots_dir(shared_dir: Path) -> Path:
    return _need(shared_dir / "assets" / "robots", "dex-urdf robot assets")


@pytest.fixture(scope="session")
def real_video(shared_dir: Path) -> Path:
    return _need(shared_dir / "data" / "real-hand-video" / "human_hand_video.mp4", "real hand video")


@pytest.fixture(scope="session")
def egodex_dir(shared_dir: Path) -> Path:
    """The two real EgoDex episodes (CC BY-NC-ND: read in place, never copied into the repo)."""
    return _need(shared_dir / "data" / "egodex", "EgoDex sample episodes")


@pytest.fixture(scope="session")
def prefect_api():
    """A real Prefect API server on 127.0.0.1 for the whole session."""
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=180):
        yield


@pytest.fixture(scope="session")
def dask_cluster():
    """Two worker processes with one thread each, bound to 127.0.0.1 (configured as the
    flow's own local clusters are: ``handedit.flows.config.LOCAL_WORKER_CONFIG``)."""
    import dask
    from distributed import LocalCluster

    from handedit.flows.config import LOCAL_WORKER_CONFIG

    with dask.config.set(LOCAL_WORKER_CONFIG), LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0", memory_limit="4GiB") as cluster:
        yield cluster
