"""A run's progress in frame x embodiment pairs: planned (estimated until every clip is
opened), done, rate and ETA, as the CLI bar and the Prefect artifact show it."""

from __future__ import annotations

from handedit.flows.progress import Progress


def test_planned_pairs_are_estimated_from_the_clips_opened_so_far():
    p = Progress("run", embodiments=2)
    assert p.planned_pairs() is None and "0 of ? " in p.describe()
    p.listed(4)
    p.finished({"clip": "a", "frames": 10}, embodiment=False)
    assert p.planned_pairs() == (10 + 3 * 10) * 2  # three clips not opened yet count as the mean
    p.finished({"clip": "a", "frames": 10}, embodiment=True)
    assert p.pairs_done == 10 and p.share() == 10 / 80 and "10 of ~80" in p.describe()
    assert p.eta_s() is not None and p.eta_s() > 0
    for clip, n in (("b", 20), ("c", 30), ("d", 40)):
        p.finished({"clip": clip, "frames": n}, embodiment=False)
    p.listed(0, done=True)
    assert p.planned_pairs() == 200 and "10 of 200 " in p.describe()  # exact once every clip is planned
    p.finished({"clip": "ignored", "frames": 0}, embodiment=True)  # a failed task adds nothing
    assert p.pairs_done == 10
