"""The Dask dashboard as installed: bokeh is a dependency, so the pages a curate run links to
are served (not "Dask needs bokeh"), they render in headless Chromium, and the run's time is
metered per stage (the Fine Performance Metrics page's activities) inside the
``curate/<embodiment>`` spans."""

from __future__ import annotations

import shutil
import subprocess
import urllib.request

from handedit.flows.cli import main


def _dom(url: str) -> str:
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    assert browser, "chromium is not installed: `bash deploy/setup.sh --test` installs it (Debian package chromium)"
    out = subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=8000",
                          "--dump-dom", url], capture_output=True, text=True, timeout=120)
    return out.stdout


def test_dashboard_pages_and_per_stage_metrics(tmp_path, capsys, prefect_api, dask_cluster):
    from distributed import Client

    assert main(["curate", "--demo", "--out", str(tmp_path / "run"), "--clips", "1", "--frames", "8", "--width", "160",
                 "--height", "120", "--frames-per-chunk", "8", "--address", dask_cluster.scheduler_address,
                 "--no-progress"]) == 0
    text = capsys.readouterr().out
    link = next(line.split()[-1] for line in text.splitlines() if line.startswith("dask dashboard:"))
    assert link.startswith("http://127.0.0.1:") and link.endswith("/status")
    base = link.rsplit("/", 1)[0]
    for page in ("status", "individual-fine-performance-metrics", "individual-progress"):
        with urllib.request.urlopen(f"{base}/{page}", timeout=30) as r:
            html = r.read().decode()
        assert r.status == 200 and "needs bokeh" not in html and "Bokeh" in html, page
    dom = _dom(f"{base}/individual-fine-performance-metrics")
    assert "bk-" in dom or "data-root-id" in dom, dom[:500]  # bokeh built the page's document in the browser

    def metered(dask_scheduler):
        # ("execute", task prefix, activity, unit): each stage's chunk work is metered under its name
        acts = {k[2] for k in dask_scheduler.cumulative_worker_metrics if isinstance(k, tuple) and k[0] == "execute"}
        names = {s.name for s in dask_scheduler.extensions["spans"].spans.values()}
        return sorted(acts), sorted(map(tuple, names))

    with Client(dask_cluster) as client:
        activities, spans = client.run_on_scheduler(metered)
    for stage in ("segment", "restore_background", "retarget", "render", "composite", "harmonize", "qc"):
        assert stage in activities, activities
    assert ("curate", "clip") in spans and ("curate", "allegro") in spans, spans
