"""deploy/prefect.yaml on a real Prefect server backed by PostgreSQL: `prefect deploy`, a
process worker (`handedit worker`), `prefect deployment run` of the release deployment (its
outcome read back from its INFO log lines and its artifact through the API), the scheduled
incremental release picking up a clip added to its source, and the worker stopping on SIGTERM
once the flow run it is running has finished. A curate run's artifacts are opened in the
server's UI in headless Chromium (screenshots: ``tests/_browser.py``).

The database (``deploy/prefect-db.sh``, Debian's postgresql), the server, the work pool, the
worker and every flow run are real processes on 127.0.0.1 (not the test harness); the
project's deployments are used as written, with their parameters pointed at this test's
folders and the nightly schedule shortened.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

import httpx
import yaml

from _browser import Tab

from handedit.storage import Location
from handedit.storage.releases import read_pairs, read_release, versions

REPO = Path(__file__).resolve().parents[1]
PREFECT = [sys.executable, "-m", "prefect"]
POOL = "handedit-test"


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _clip(i: int) -> dict:
    return {"kind": "synthetic", "clip_id": f"synthetic-{i:04d}", "seed": i, "n_frames": 8, "width": 96, "height": 72}


class Postgres:
    """A PostgreSQL cluster for the Prefect server, started as the README says:
    ``bash deploy/prefect-db.sh start DIR PORT`` (as root the server runs as the postgres user,
    so DIR lies in a folder it can enter, not under pytest's closed tmp folders)."""

    def __init__(self):
        self.base = Path(tempfile.mkdtemp(prefix="handedit-prefect-db-"))
        self.base.chmod(0o755)
        self.dir = self.base / "db"
        out = subprocess.run(["bash", str(REPO / "deploy" / "prefect-db.sh"), "start", str(self.dir), str(_port())],
                             capture_output=True, text=True, timeout=180)
        assert out.returncode == 0, out.stderr
        self.url = out.stdout.strip().removeprefix("export PREFECT_API_DATABASE_CONNECTION_URL=")
        assert self.url.startswith("postgresql+asyncpg://prefect:"), out.stdout

    def count(self, table: str) -> int:
        """Rows of one of Prefect's tables, read with psql (not through Prefect)."""
        port, password = (self.dir / "port").read_text().strip(), (self.dir / "password").read_text().strip()
        out = subprocess.run(["psql", "-h", "127.0.0.1", "-p", port, "-U", "prefect", "-d", "prefect", "-tAc",
                              f"select count(*) from {table}"], capture_output=True, text=True, timeout=60,
                             env=os.environ | {"PGPASSWORD": password})
        assert out.returncode == 0, out.stderr
        return int(out.stdout)

    def stop(self) -> None:
        subprocess.run(["bash", str(REPO / "deploy" / "prefect-db.sh"), "stop", str(self.dir)], capture_output=True, timeout=120)
        shutil.rmtree(self.base, ignore_errors=True)


class Server:
    def __init__(self, tmp: Path, database: str):
        self.port = _port()
        self.ui = f"http://127.0.0.1:{self.port}"
        self.api = f"{self.ui}/api"
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")} | {
            "PREFECT_HOME": str(tmp / "prefect-home"), "PREFECT_API_URL": self.api,
            "PREFECT_API_DATABASE_CONNECTION_URL": database,
            "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "PREFECT_UI_ENABLED": "true",
            "PREFECT_SERVER_SERVICES_SCHEDULER_LOOP_SECONDS": "5", "PREFECT_WORKER_QUERY_SECONDS": "2",
            "PREFECT_LOGGING_LEVEL": "WARNING", "HANDEDIT_REPO": str(REPO), "PYOPENGL_PLATFORM": "egl"}
        self.procs: list[subprocess.Popen] = []
        self.log = open(tmp / "server.log", "w")

    def spawn(self, args, env: dict | None = None, **kw) -> subprocess.Popen:
        p = subprocess.Popen(args, env=self.env | (env or {}), stdout=self.log, stderr=subprocess.STDOUT,
                             start_new_session=True, **kw)
        self.procs.append(p)
        return p

    def run(self, args, timeout=300, **kw) -> str:
        out = subprocess.run(args, env=self.env, capture_output=True, text=True, timeout=timeout, **kw)
        assert out.returncode == 0, f"{args}: {out.stdout[-2000:]}{out.stderr[-2000:]}"
        return out.stdout

    def start(self) -> None:
        self.spawn([*PREFECT, "server", "start", "--host", "127.0.0.1", "--port", str(self.port)])
        deadline = time.time() + 240
        while time.time() < deadline:
            try:
                if httpx.get(f"{self.api}/health", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(1)
        raise AssertionError("the Prefect server did not start")

    def runs(self, deployment: str) -> list[dict]:
        deps = httpx.post(f"{self.api}/deployments/filter", json={"deployments": {"name": {"any_": [deployment]}}}).json()
        ids = [d["id"] for d in deps]
        return httpx.post(f"{self.api}/flow_runs/filter", json={"flow_runs": {"deployment_id": {"any_": ids}}}).json()

    def with_subflows(self, flow_run: str) -> list[str]:
        subflows = httpx.post(f"{self.api}/flow_runs/filter",
                              json={"flow_runs": {"parent_flow_run_id": {"any_": [flow_run]}}}).json()
        return [flow_run, *(r["id"] for r in subflows)]

    def artifacts(self, flow_run: str) -> dict[str, dict]:
        """A flow run's artifacts (its subflows' included) by key, through the API."""
        body = {"artifacts": {"flow_run_id": {"any_": self.with_subflows(flow_run)}}}
        return {a["key"]: a for a in httpx.post(f"{self.api}/artifacts/filter", json=body).json() if a["key"]}

    def log_lines(self, flow_run: str) -> list[str]:
        """A flow run's log messages at INFO and above, its subflows' included (the deployment's
        entry flow calls the release flow), as the UI shows them."""
        body = {"logs": {"flow_run_id": {"any_": self.with_subflows(flow_run)}, "level": {"ge_": 20}},
                "sort": "TIMESTAMP_ASC", "limit": 200}
        return [r["message"] for r in httpx.post(f"{self.api}/logs/filter", json=body).json()]

    def wait(self, what, timeout=420, poll=2.0, why=None) -> dict:
        deadline = time.time() + timeout
        while time.time() < deadline:
            found = what()
            if found:
                return found
            time.sleep(poll)
        raise AssertionError(why() if why else f"timed out waiting; server log:\n{Path(self.log.name).read_text()[-3000:]}")

    def stop(self) -> None:
        for p in reversed(self.procs):
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        for p in self.procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)


def test_deploy_run_and_scheduled_incremental_release(tmp_path):
    run, releases = tmp_path / "run" / "handedit.zarr", tmp_path / "releases"
    config = tmp_path / "run.yaml"
    config.write_text(yaml.safe_dump({"out": str(run), "frames_per_chunk": 8, "shard_size": 1,
                                      "embodiments": ["allegro"], "clips": [_clip(0), _clip(1)]}))
    cluster = tmp_path / "cluster.yaml"
    cluster.write_text(yaml.safe_dump({"cluster": {"n_workers": 1, "dashboard_address": "127.0.0.1:0"}}))
    spec = yaml.safe_load((REPO / "deploy" / "prefect.yaml").read_text())
    by_name = {d["name"]: d for d in spec["deployments"]}
    assert {"demo", "release", "nightly"} <= set(by_name)
    for d in spec["deployments"]:
        d["work_pool"]["name"] = POOL
        if "config_path" in d["parameters"]:
            d["parameters"].update(config_path=str(config), cluster_path=str(cluster))
    by_name["release"]["parameters"].update(sources=[str(run)], out=str(releases), cluster_path=str(cluster),
                                            shard_mb=0.5)
    by_name["nightly"]["parameters"].update(releases=str(releases), shard_mb=0.5)
    anchor = (datetime.now(timezone.utc) + timedelta(seconds=60)).isoformat()
    by_name["nightly"]["schedules"] = [{"interval": 30, "anchor_date": anchor, "timezone": "UTC"}]
    project = tmp_path / "prefect.yaml"
    project.write_text(yaml.safe_dump(spec, sort_keys=False))

    db = Postgres()
    server = Server(tmp_path, db.url)
    try:
        server.start()
        server.run([*PREFECT, "work-pool", "create", POOL, "--type", "process"])
        server.run([*PREFECT, "work-pool", "set-concurrency-limit", POOL, "1"])
        server.run([sys.executable, "-m", "handedit.flows.cli", "curate", "--config", str(config), "--cluster",
                    str(cluster), "--no-progress"], timeout=600)
        # 0. the curate run's outcome in the UI: its artifacts, drawn by the server's own pages
        (curated,) = httpx.post(f"{server.api}/flow_runs/filter", json={"flows": {"name": {"any_": ["curate"]}}}).json()
        arts = server.artifacts(curated["id"])
        assert {"curate-frames", "curate-outcome", "curate-progress"} <= set(arts), sorted(arts)
        with Tab((1280, 640)) as tab:
            tab.open(f"{server.ui}/artifacts/artifact/{arts['curate-outcome']['id']}", 4.0)
            text = tab.text()
            assert str(run) in text and "kept" in text, text[:2000]
            tab.png(tmp_path / "prefect_curate_outcome.png")
            link = next(line.split(": ", 1)[1].split()[0] for line in text.splitlines() if line.startswith("Prefect run: "))
            assert curated["name"] in tab.open(link, 4.0).text()  # the run's own link opens its page
            tab.open(f"{server.ui}/artifacts/artifact/{arts['curate-frames']['id']}", 4.0)
            assert "status" in tab.text() and "retarget" in tab.text(), tab.text()[:2000]
            tab.png(tmp_path / "prefect_curate_frames.png")
        server.run([*PREFECT, "--no-prompt", "deploy", "--all", "--prefect-file", str(project)], cwd=REPO)
        # its flow runs log at INFO (they inherit the worker's environment), so their outcome reaches the API
        worker = server.spawn([sys.executable, "-m", "handedit.flows.cli", "worker", "--pool", POOL], cwd=REPO,
                              env={"PREFECT_LOGGING_LEVEL": "INFO"})

        # 1. `prefect deployment run` of the release deployment
        out = server.run([*PREFECT, "deployment", "run", "release-from-config/release"], cwd=REPO)
        assert "release-from-config/release" in out
        done = server.wait(lambda: [r for r in server.runs("release") if r["state_type"] in ("COMPLETED", "FAILED", "CRASHED")])
        assert done[0]["state_type"] == "COMPLETED", done[0]["state"]
        loc = Location(releases)
        assert versions(loc) and read_release(loc, versions(loc)[0])["counts"]["pairs"] > 0
        # the run's outcome, as an operator reads it in the UI: its INFO log lines, back through the API. On a
        # busy machine the nightly schedule can fire first and publish v0001: the version is the one this run names
        lines = server.wait(lambda: [m for m in server.log_lines(done[0]["id"]) if m.startswith("published v")], timeout=60,
                            why=lambda: f"no 'published v...' among the run's log lines: {server.log_lines(done[0]['id'])}")
        assert len(lines) == 1, lines
        version = lines[0].split()[1].rstrip(":")
        assert version in versions(loc), (version, versions(loc))
        pairs = read_release(loc, version)["counts"]["pairs"]
        assert lines[0].startswith(f"published {version}: {pairs} pairs in "), lines
        release_art = server.artifacts(done[0]["id"]).get("release")
        assert release_art and f"# release {version}" in release_art["data"], release_art

        # 2. the server's scheduler creates a run of the nightly deployment, and it completes
        server.wait(lambda: [r for r in server.runs("nightly") if r["auto_scheduled"] and r["state_type"] == "COMPLETED"])

        # 3. a clip added to the source: the next scheduled release holds exactly its pairs as new
        edited = datetime.now(timezone.utc)
        data = yaml.safe_load(config.read_text())
        data["clips"].append(_clip(2))
        config.write_text(yaml.safe_dump(data))

        def new_release():
            for v in versions(loc):
                m = read_release(loc, v)
                if datetime.fromisoformat(m["created"]) > edited and m["counts"]["added"]:
                    return v
            return None

        v = server.wait(new_release)
        changes = yaml.safe_load((releases / v / "changelog.json").read_text())
        pairs = read_pairs(loc, v)
        assert sorted(changes["added"]) == sorted(pairs.loc[pairs["clip"] == "synthetic-0002", "id"])
        assert changes["removed"] == [] and changes["changed"] == []
        m = read_release(loc, v)
        assert m["counts"]["shards_reused"] == m["counts"]["shards"] - 1  # only the new clip's shard was written

        # 4. SIGTERM (systemctl stop, a pod's termination) while the worker runs a flow: it takes no new
        # run, lets that one finish, then leaves with exit status 0
        server.wait(lambda: not [r for r in server.runs("nightly") if r["state_type"] in ("PENDING", "RUNNING")])
        seen = {r["id"] for r in server.runs("release")}
        server.run([*PREFECT, "deployment", "run", "release-from-config/release"], cwd=REPO)
        claimed = server.wait(lambda: [r for r in server.runs("release") if r["id"] not in seen
                                       and r["state_type"] in ("PENDING", "RUNNING")], poll=0.2)
        os.kill(worker.pid, signal.SIGTERM)
        assert worker.wait(300) == 0
        (final,) = [r for r in server.runs("release") if r["id"] == claimed[0]["id"]]
        assert final["state_type"] == "COMPLETED", final["state"]
        log = Path(server.log.name).read_text()
        assert "waiting for 1 flow run(s) in progress" in log and "handedit worker: stopped" in log
        assert not [r for r in server.runs("nightly") + server.runs("release")
                    if r["state_type"] in ("PENDING", "RUNNING")]  # nothing new was taken while it stopped
        # every run above is a row of the PostgreSQL database, not of a SQLite file
        assert db.count("flow_run") >= len(server.runs("release")) + len(server.runs("nightly")) + 1
        assert not list((tmp_path / "prefect-home").glob("*.db"))
    finally:
        server.stop()
        db.stop()


def test_the_worker_names_an_unreachable_api(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")} | {
        "PREFECT_HOME": str(tmp_path), "PREFECT_API_URL": f"http://127.0.0.1:{_port()}/api"}
    out = subprocess.run([sys.executable, "-m", "handedit.flows.cli", "worker", "--pool", POOL], env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1 and "Traceback" not in out.stderr
    assert "does not answer" in out.stderr and "PREFECT_API_URL" in out.stderr


def test_a_stopping_worker_takes_no_new_run_and_waits_for_its_runs():
    """The drain on Prefect's own limiter: while two runs are in progress no new run gets a
    token (however much capacity the limit had), and it returns when the last one is done."""
    import anyio

    from handedit.flows.commands.worker import drain

    async def scenario() -> list[str]:
        limiter, lines = anyio.CapacityLimiter(1_000_000), []
        runs = [object(), object()]
        for r in runs:
            limiter.acquire_on_behalf_of_nowait(r)
        stopping = asyncio.ensure_future(drain(limiter, lines.append))
        await asyncio.sleep(0.05)
        try:
            limiter.acquire_on_behalf_of_nowait(object())  # the worker's next poll
            lines.append("a new run started")
        except anyio.WouldBlock:
            pass
        limiter.release_on_behalf_of(runs[0])
        await asyncio.sleep(0.05)
        assert not stopping.done()
        limiter.release_on_behalf_of(runs[1])
        await asyncio.wait_for(stopping, 5)
        return lines

    lines = asyncio.run(scenario())
    assert lines == ["handedit worker: stopping: waiting for 2 flow run(s) in progress",
                     "handedit worker: stopping: waiting for 1 flow run(s) in progress"]
