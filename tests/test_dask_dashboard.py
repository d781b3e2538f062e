"""The Dask dashboard as installed: bokeh is a dependency, so the pages a curate run links to
are served (not "Dask needs bokeh"), they render in headless Chromium, the Progress panel
counts the run's tasks per embodiment and for the clips (Dask keys named by
``handedit.flows.runner``, not Prefect's one wrapper function), and the run's time is metered
per stage (the Fine Performance Metrics page's activities) inside the ``curate/<embodiment>``
spans. Screenshots of the Progress panel mid-run and of the metrics page are taken (see
``tests/_browser.py`` for keeping them)."""

from __future__ import annotations

import threading
import time
import urllib.request

from _browser import dom, screenshot

from handedit.flows.cli import main
from handedit.flows.runner import task_key

EMBODIMENTS = ("allegro", "panda_allegro")  # both available without asset folders


def test_task_keys_group_by_embodiment():
    from dask.utils import key_split

    assert key_split(task_key("curate-embodiment", {"emb_id": "xarm_ability"}, "ab" * 16)) == "xarm_ability"
    assert key_split(task_key("curate-clip", {"clip_id": "egodex-a-b"}, "0f" * 16)) == "curate_clip"


def test_dashboard_pages_progress_and_per_stage_metrics(tmp_path, capsys, prefect_api, dask_cluster):
    from distributed import Client

    args = ["curate", "--demo", "--out", str(tmp_path / "run"), "--clips", "2", "--frames", "16", "--width", "160",
            "--height", "120", "--frames-per-chunk", "8", "--address", dask_cluster.scheduler_address, "--no-progress"]
    for emb in EMBODIMENTS:
        args += ["--embodiment", emb]
    result: list[int] = []
    run = threading.Thread(target=lambda: result.append(main(args)))
    base = dask_cluster.dashboard_link.rsplit("/", 1)[0]

    def groups(dask_scheduler):
        """Task groups in the scheduler now, by key prefix: what the Progress panel draws."""
        out: dict = {}
        for ts in dask_scheduler.tasks.values():
            out.setdefault(ts.prefix.name, []).append(ts.state)
        return out

    with Client(dask_cluster) as client:
        run.start()
        deadline, live = time.time() + 300, {}
        while time.time() < deadline and run.is_alive():
            live = client.run_on_scheduler(groups)
            if any("processing" in live.get(e, ()) for e in EMBODIMENTS):
                break
            time.sleep(0.2)
        assert any("processing" in live.get(e, ()) for e in EMBODIMENTS), f"no embodiment task ran mid-run: {live}"
        screenshot(f"{base}/individual-progress", tmp_path / "dask_progress.png", wait_s=2.0, size=(900, 300))
        run.join(600)
        assert result == [0]

        def seen(dask_scheduler):
            # ("execute", task prefix, activity, unit): each stage's chunk work is metered under its name
            acts = {k[2] for k in dask_scheduler.cumulative_worker_metrics if isinstance(k, tuple) and k[0] == "execute"}
            names = {s.name for s in dask_scheduler.extensions["spans"].spans.values()}
            return sorted(acts), sorted(map(tuple, names)), sorted(dask_scheduler.task_prefixes)

        activities, spans, prefixes = client.run_on_scheduler(seen)
    # the Progress panel's bars: one per embodiment and one for the clips, none for Prefect's wrapper
    assert set(EMBODIMENTS) | {"curate_clip"} <= set(prefixes), prefixes
    assert "wrapper_func" not in prefixes, prefixes

    text = capsys.readouterr().out
    link = next(line.split()[-1] for line in text.splitlines() if line.startswith("dask dashboard:"))
    assert link.startswith("http://127.0.0.1:") and link.endswith("/status") and link.rsplit("/", 1)[0] == base
    for page in ("status", "individual-fine-performance-metrics", "individual-progress"):
        with urllib.request.urlopen(f"{base}/{page}", timeout=30) as r:
            html = r.read().decode()
        assert r.status == 200 and "needs bokeh" not in html and "Bokeh" in html, page
    shown = dom(f"{base}/individual-fine-performance-metrics", budget_ms=8000)
    assert "bk-" in shown or "data-root-id" in shown, shown[:500]  # bokeh built the page's document in the browser
    screenshot(f"{base}/individual-fine-performance-metrics", tmp_path / "dask_fine_metrics.png", wait_s=4.0,
               size=(1280, 420))
    for stage in ("segment", "restore_background", "retarget", "render", "composite", "harmonize", "qc"):
        assert stage in activities, activities
    assert ("curate", "clip") in spans and all(("curate", e) in spans for e in EMBODIMENTS), spans
