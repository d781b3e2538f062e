"""A Dask cluster across hosts (issue 37): each host is a network namespace on a bridge made by
the test (``ip netns`` and veth pairs; root, as in CI). The scheduler and two workers run on
their own hosts, started by their own CLIs; the store is on moto's S3 server on another; the
Prefect server on this one, reached over the bridge; each driver on a host of its own.

- The demo on the multi-host cluster, one worker host's link cut mid-run: the run completes
  on the other worker and its store equals a LocalCluster run's (timed side by side).
- Two drivers on two hosts against the same S3 store split the shards and lose nothing.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from _servers import prefect_server

HANDEDIT = [sys.executable, "-m", "handedit.flows.cli"]


def _free_net() -> str:
    """A /24 no interface or route of this machine uses yet: a bridge left by an earlier run that
    was killed (or the machine's own network) would otherwise take the hosts' traffic."""
    try:
        used = subprocess.run(["ip", "-o", "addr"], capture_output=True, text=True, timeout=30).stdout
        used += subprocess.run(["ip", "route"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        used = ""
    for k in range(os.getpid() % 200, os.getpid() % 200 + 250):
        net = f"10.78.{k % 250}"
        if f"{net}." not in used:
            return net
    return "10.78.0"


NET = _free_net()
BRIDGE = f"he{os.getpid() % 100000}"
S3, SCHED, W1, W2, D1, D2 = (f"{NET}.{i}" for i in (5, 2, 3, 4, 6, 7))


def _ip(*args: str, ns: str | None = None) -> None:
    cmd = [*(["ip", "netns", "exec", ns] if ns else []), "ip", *args]
    subprocess.run(cmd, check=True, capture_output=True, timeout=30)


class Lan:
    """A bridge here (``NET``.1) and hosts on it, each a namespace with one veth pair."""

    def __init__(self):
        self.hosts: dict[str, tuple[str, str]] = {}  # ip -> (namespace, bridge-side link)
        _ip("link", "add", BRIDGE, "type", "bridge")
        _ip("addr", "add", f"{NET}.1/24", "dev", BRIDGE)
        _ip("link", "set", BRIDGE, "up")

    def add(self, ip: str) -> str:
        n = ip.rsplit(".", 1)[1]
        ns, here, there = f"{BRIDGE}-{n}", f"{BRIDGE}h{n}", f"{BRIDGE}n{n}"
        subprocess.run(["ip", "netns", "add", ns], check=True, capture_output=True)
        _ip("link", "add", here, "type", "veth", "peer", "name", there)
        _ip("link", "set", there, "netns", ns)
        _ip("link", "set", here, "master", BRIDGE)
        _ip("link", "set", here, "up")
        _ip("addr", "add", f"{ip}/24", "dev", there, ns=ns)
        _ip("link", "set", there, "up", ns=ns)
        _ip("link", "set", "lo", "up", ns=ns)
        self.hosts[ip] = (ns, here)
        return ns

    def cut(self, ip: str) -> None:
        _ip("link", "set", self.hosts[ip][1], "down")

    def run(self, ip: str, cmd: list[str], env: dict, **kw) -> subprocess.Popen:
        return subprocess.Popen(["ip", "netns", "exec", self.hosts[ip][0], *cmd], env=env, **kw)

    def close(self) -> None:
        for ns, here in self.hosts.values():
            subprocess.run(["ip", "link", "del", here], capture_output=True)
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        subprocess.run(["ip", "link", "del", BRIDGE], capture_output=True)


def _wait(check, what: str, timeout: float = 120.0, proc: subprocess.Popen | None = None, log: Path | None = None) -> None:
    """Until ``check()`` is true; fails with the service's own output when its process ended or
    the time ran out (a CI run once said only that moto "did not come up")."""
    deadline, last = time.time() + timeout, None
    while time.time() < deadline:
        try:
            if check():
                return
        except Exception as e:  # noqa: BLE001 - not up yet
            last = e
        if proc is not None and proc.poll() is not None:
            break
        time.sleep(0.5)
    state = "" if proc is None else (f"; its process ended (rc {proc.returncode})" if proc.poll() is not None else "; its process runs")
    tail = log.read_text(errors="replace")[-3000:] if log is not None and log.exists() else ""
    routes = subprocess.run(["ip", "route"], capture_output=True, text=True).stdout
    pytest.fail(f"{what} did not come up in {timeout:.0f} s{state}; last error: {last!r}\nroutes:\n{routes}\nits output:\n{tail}")


@pytest.fixture(scope="module")
def lan(tmp_path_factory):
    """The hosts and their services: S3 (moto), the Prefect server (here), the scheduler."""
    if os.geteuid() != 0:
        pytest.fail("the test's hosts are network namespaces: `ip netns` needs root (CI runs as root)")
    net = Lan()
    procs = []
    try:
        for ip in (S3, SCHED, W1, W2, D1, D2):
            net.add(ip)
        env = {**os.environ, "AWS_ACCESS_KEY_ID": "test", "AWS_SECRET_ACCESS_KEY": "test", "AWS_DEFAULT_REGION": "us-east-1",
               "AWS_ENDPOINT_URL": f"http://{S3}:5000"}
        env.pop("PREFECT_API_URL", None)
        moto_log = tmp_path_factory.mktemp("moto") / "moto.log"
        with open(moto_log, "w") as log:
            moto = net.run(S3, [sys.executable, "-m", "moto.server", "-H", S3, "-p", "5000"], env,
                           stdout=log, stderr=subprocess.STDOUT)
        procs.append(moto)
        server, env["PREFECT_API_URL"] = prefect_server(f"{NET}.1", tmp_path_factory.mktemp("prefect-home"), env, 240)
        procs.append(server)
        import boto3
        from botocore.config import Config

        # short timeouts, no retries: one unanswered attempt must not outlast the whole wait
        s3 = boto3.client("s3", endpoint_url=env["AWS_ENDPOINT_URL"], aws_access_key_id="test", aws_secret_access_key="test",
                          region_name="us-east-1", config=Config(connect_timeout=3, read_timeout=30, retries={"max_attempts": 1}))
        _wait(lambda: s3.create_bucket(Bucket="handedit"), "moto's S3", 180, moto, moto_log)
        sched_env = {**env, "DASK_DISTRIBUTED__SCHEDULER__WORKER_TTL": "15s"}  # a silent worker is gone after 15 s
        procs.append(net.run(SCHED, [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", SCHED, "--port", "8786",
                                     "--dashboard-address", f"{SCHED}:0"], sched_env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        yield net, env, procs
    finally:
        for p in procs:
            p.kill()
            p.wait(timeout=30)
        net.close()


def _workers(net: Lan, env: dict) -> list[subprocess.Popen]:
    from distributed import Client

    out = [net.run(ip, [sys.executable, "-m", "distributed.cli.dask_worker", f"tcp://{SCHED}:8786", "--nthreads", "1",
                        "--nworkers", "1", "--no-dashboard", "--host", ip], env,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for ip in (W1, W2)]
    with Client(f"tcp://{SCHED}:8786", timeout=60) as c:
        c.wait_for_workers(2, timeout=120)
    return out


def _curate(out: str, *extra: str) -> list[str]:
    return [*HANDEDIT, "curate", "--demo", "--clips", "4", "--frames", "16", "--width", "160", "--height", "120",
            "--frames-per-chunk", "8", "--shard-size", "1", "--out", out, "--no-progress", *extra]


def _same_store(a: str, b: str, env: dict) -> None:
    code = ("import sys, numpy as np\n"
            "from handedit.storage import Location, open_store\n"
            "from test_scale_flow import arrays\n"
            "da, db = arrays(open_store(Location(sys.argv[1]))), arrays(open_store(Location(sys.argv[2])))\n"
            "assert set(da) == set(db), sorted(set(da) ^ set(db))[:5]\n"
            "bad = [k for k in da if da[k].dtype != db[k].dtype or da[k].tobytes() != db[k].tobytes()]\n"
            "assert not bad, bad[:10]\n"
            "print(len(da), 'arrays equal')\n")
    done = subprocess.run([sys.executable, "-c", code, a, b], env={**env, "PYTHONPATH": str(Path(__file__).parent)},
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]


def test_a_worker_host_cut_off_mid_run_loses_nothing(lan):
    net, env, _ = lan
    workers = _workers(net, env)
    try:
        t0 = time.perf_counter()  # the demo on a LocalCluster on the driver's host: the reference store
        local = net.run(D1, _curate("s3://handedit/local", "--workers", "2"), env,
                        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        out, err = local.communicate(timeout=900)
        assert local.returncode == 0, out[-2000:] + err[-3000:]
        local_s = time.perf_counter() - t0
        # the same demo on the multi-host cluster, one worker host cut off mid-run: one run proves both
        # multi-host == LocalCluster and nothing lost (CI time)
        t0 = time.perf_counter()
        run = net.run(D1, _curate("s3://handedit/cut", "--address", f"tcp://{SCHED}:8786"), env,
                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        import s3fs

        fs = s3fs.S3FileSystem(key="test", secret="test", client_kwargs={"endpoint_url": env["AWS_ENDPOINT_URL"]})
        def working() -> bool:
            if run.poll() is not None:
                out, err = run.communicate()
                pytest.fail(f"the second run ended before the cut (rc {run.returncode}): {out[-2000:]}{err[-3000:]}")
            fs.invalidate_cache()
            return bool(fs.glob("handedit/cut/handedit.zarr.records/clips/*/registration/*.json"))

        _wait(working, "the second run's work", 300)
        net.cut(W1)  # its host is gone from the network, mid-run
        stdout, stderr = run.communicate(timeout=900)
        assert run.returncode == 0, stdout[-2000:] + stderr[-3000:]
        print(f"\ndemo: LocalCluster {local_s:.1f} s, multi-host cluster (one host cut) {time.perf_counter() - t0:.1f} s")
    finally:
        for w in workers:
            w.kill()
            w.wait(timeout=30)
    _same_store("s3://handedit/local", "s3://handedit/cut", env)


def test_two_drivers_on_two_hosts_split_the_shards(lan):
    """Each driver with its own LocalCluster on its host; the store and the Prefect API are shared."""
    net, env, _ = lan
    runs = [net.run(ip, _curate("s3://handedit/two", "--workers", "1"), env, stdout=subprocess.PIPE,
                    stderr=subprocess.PIPE, text=True) for ip in (D1, D2)]
    outs = [r.communicate(timeout=900) for r in runs]
    for r, (o, e) in zip(runs, outs):
        assert r.returncode == 0, o[-2000:] + e[-3000:]
    ran = [int(next(l for l in o.splitlines() if l.startswith("shards:")).split()[1]) for o, _ in outs]
    assert sum(ran) >= 4 and min(ran) >= 1, ran  # both worked, every shard was run
    _same_store("s3://handedit/local", "s3://handedit/two", env)
    assert np.all(np.array(ran) <= 4)
