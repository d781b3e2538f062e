"""Headless Chromium for the tests that look at pages: the DOM after scripts ran, and screenshots.

A screenshot is written where the test asks and, when ``HANDEDIT_SCREENSHOTS`` names a folder,
copied there under its name: the README's pictures are retaken by

    HANDEDIT_SCREENSHOTS=docs .venv/bin/python -m pytest tests/test_dask_dashboard.py \
        tests/test_deployments_live.py tests/test_release.py tests/test_audit.py tests/test_benchmark.py
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from contextlib import contextmanager
from pathlib import Path

# no background traffic: this machine's closed network refuses it, many connections at a time
FLAGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def browser() -> str:
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    assert found, "chromium is not installed: `bash deploy/setup.sh --test` installs it (Debian package chromium)"
    return found


def _run(url: str, extra: list[str], budget_ms: int, size: tuple[int, int]) -> subprocess.CompletedProcess:
    return subprocess.run([browser(), *FLAGS, f"--virtual-time-budget={budget_ms}", f"--window-size={size[0]},{size[1]}",
                           *extra, url], capture_output=True, text=True, timeout=120)


def dom(url: str, budget_ms: int = 10_000, size: tuple[int, int] = (1280, 2400)) -> str:
    """The page's DOM once its scripts have run for ``budget_ms`` of virtual time."""
    return _run(url, ["--dump-dom"], budget_ms, size).stdout


class Tab:
    """One headless Chromium tab driven over the DevTools protocol, in real time: pages that fill
    themselves over a websocket (Dask's bokeh dashboard, Prefect's UI) are drawn before the
    picture is taken, where ``--screenshot``'s virtual time takes it blank."""

    def __init__(self, size: tuple[int, int] = (1280, 800)):
        from websockets.sync.client import connect

        self.home = Path(tempfile.mkdtemp(prefix="handedit-chromium-"))
        self.proc = subprocess.Popen([browser(), *FLAGS, "--remote-debugging-port=0", f"--user-data-dir={self.home}",
                                      f"--window-size={size[0]},{size[1]}", "about:blank"],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port_file, deadline = self.home / "DevToolsActivePort", time.time() + 60
        while not (port_file.is_file() and port_file.read_text().strip()):
            assert time.time() < deadline and self.proc.poll() is None, "chromium did not start its DevTools endpoint"
            time.sleep(0.1)
        port = port_file.read_text().split()[0]
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=30) as r:
            page = next(t for t in json.load(r) if t["type"] == "page")
        self.ws, self.n = connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=30), 0
        self.call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1], deviceScaleFactor=1, mobile=False)

    def call(self, method: str, **params) -> dict:
        self.n += 1
        self.ws.send(json.dumps({"id": self.n, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv(timeout=60))
            if msg.get("id") == self.n:
                assert "error" not in msg, (method, msg["error"])
                return msg["result"]

    def open(self, url: str, wait_s: float) -> "Tab":
        self.call("Page.navigate", url=url)
        time.sleep(wait_s)
        return self

    def text(self) -> str:
        """The page's visible text now."""
        return self.call("Runtime.evaluate", expression="document.body.innerText", returnByValue=True)["result"]["value"]

    def png(self, path: Path) -> Path:
        """A PNG of the tab at ``path`` (and in ``$HANDEDIT_SCREENSHOTS``, if set)."""
        path.write_bytes(base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"]))
        keep_screenshot(path)
        return path

    def close(self) -> None:
        self.ws.close()
        self.proc.terminate()
        self.proc.wait(30)
        shutil.rmtree(self.home, ignore_errors=True)

    def __enter__(self) -> "Tab":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def screenshot(url: str, path: Path, wait_s: float = 3.0, size: tuple[int, int] = (1280, 800)) -> Path:
    """A PNG of the page ``wait_s`` seconds after it was opened (kept as ``Tab.png`` keeps it)."""
    with Tab(size) as tab:
        tab.open(url, wait_s).png(path)
    assert path.stat().st_size > 10_000, f"the screenshot of {url} is blank"
    return path


@contextmanager
def served(args: list[str]):
    """``handedit ARGS --port P`` (a page server) on a free 127.0.0.1 port, as a real process:
    yields its URL once it answers; stopped afterwards."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = subprocess.Popen([sys.executable, "-m", "handedit.flows.cli", *args, "--port", str(port)],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    url = f"http://127.0.0.1:{port}/"
    try:
        deadline = time.time() + 60
        while True:
            try:
                urllib.request.urlopen(url, timeout=2)
                break
            except OSError:
                assert time.time() < deadline and server.poll() is None, server.stdout.read() if server.poll() else "no answer"
                time.sleep(0.3)
        yield url
    finally:
        server.terminate()
        server.wait(30)


def keep_screenshot(path: Path) -> None:
    """Copy a picture taken by another driver (Playwright) where ``HANDEDIT_SCREENSHOTS`` says."""
    keep = os.environ.get("HANDEDIT_SCREENSHOTS")
    if keep:
        Path(keep).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, Path(keep) / path.name)
