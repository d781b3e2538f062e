"""A curate run's progress in frame x embodiment pairs: planned, done, per second, ETA.

The driver lists the clips in a background thread (a dataset tree is listed lazily, so the
total grows until the listing ends) and each shard flow reports its finished tasks (a clip
task: its frames; an embodiment task: its frames as pairs). Planned pairs are the known
clips' frames plus, for clips not opened yet, the mean so far, times the embodiments. The
CLI bar and the Prefect progress artifact (``curate-progress``) read the same numbers.
"""

from __future__ import annotations

import threading
import time

_RUNS: dict[str, "Progress"] = {}
_LOCK = threading.Lock()


class Progress:
    def __init__(self, run_id: str, embodiments: int):
        self.run_id, self.embodiments = run_id, max(1, embodiments)
        self.clips_listed, self.listing_done = 0, False
        self.clip_frames: dict[str, int] = {}
        self.pairs_done = 0
        self.started = time.monotonic()
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ reports
    def listed(self, n_clips: int, done: bool = False) -> None:
        with self._lock:
            self.clips_listed += n_clips
            self.listing_done = self.listing_done or done

    def finished(self, result: dict, embodiment: bool) -> None:
        """A clip or embodiment task's result (``tasks.clip.WalkResult`` as a dict)."""
        frames = int(result.get("frames") or 0)
        with self._lock:
            if embodiment:
                self.pairs_done += frames
            elif result.get("clip"):
                self.clip_frames[result["clip"]] = frames

    # ------------------------------------------------------------------ numbers
    def planned_pairs(self) -> int | None:
        """Pairs the run will have made (estimated until every clip was opened); None before any."""
        with self._lock:
            known = list(self.clip_frames.values())
            if not known:
                return None
            unknown = max(self.clips_listed - len(known), 0)
            return int(round((sum(known) + unknown * sum(known) / len(known)) * self.embodiments))

    def rate(self) -> float:
        return self.pairs_done / max(time.monotonic() - self.started, 1e-6)

    def eta_s(self) -> float | None:
        planned, rate = self.planned_pairs(), self.rate()
        if planned is None or rate <= 0:
            return None
        return max(planned - self.pairs_done, 0) / rate

    def share(self) -> float:
        planned = self.planned_pairs()
        return min(self.pairs_done / planned, 1.0) if planned else 0.0

    def brief(self) -> str:
        """What the bar adds to its own counts: the ETA and how much of the plan is known."""
        eta = self.eta_s()
        when = time.strftime("%H:%M:%S", time.gmtime(eta)) if eta is not None else "?"
        return f"ETA {when}, {len(self.clip_frames)} of {self.clips_listed}{'' if self.listing_done else '+'} clips planned"

    def describe(self) -> str:
        planned = self.planned_pairs()
        approx = "" if self.listing_done and len(self.clip_frames) >= self.clips_listed else "~"
        total = f"{approx}{planned}" if planned is not None else "?"
        return f"{self.pairs_done} of {total} frame x embodiment pairs, {self.rate():.1f}/s, {self.brief()}"


def start(run_id: str, embodiments: int) -> Progress:
    p = Progress(run_id, embodiments)
    with _LOCK:
        _RUNS[run_id] = p
    return p


def report(run_id: str, result: dict, embodiment: bool) -> None:
    """Called by the shard flows (same process as the driver) as each task finishes."""
    with _LOCK:
        p = _RUNS.get(run_id)
    if p is not None and isinstance(result, dict):
        p.finished(result, embodiment)


def stop(run_id: str) -> None:
    with _LOCK:
        _RUNS.pop(run_id, None)


def list_in_background(progress: Progress, shards) -> threading.Thread:
    """Count the clips of ``shards`` (an iterable of shard plans) in a daemon thread."""
    def count() -> None:
        try:
            for shard in shards:
                progress.listed(len(shard.specs))
        finally:
            progress.listed(0, done=True)

    t = threading.Thread(target=count, daemon=True, name="curate-progress-listing")
    t.start()
    return t


class ProgressArtifact:
    """The run's ``curate-progress`` artifact in Prefect, updated at most every ``every_s``."""

    def __init__(self, progress: Progress, every_s: float = 5.0):
        self.progress, self.every_s, self.last, self.id = progress, every_s, 0.0, None

    def update(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self.last < self.every_s:
            return
        self.last = now
        try:
            from prefect.artifacts import create_progress_artifact, update_progress_artifact

            pct = 100.0 * self.progress.share()
            if self.id is None:
                self.id = create_progress_artifact(pct, key="curate-progress", description=self.progress.describe())
            else:
                update_progress_artifact(self.id, pct, description=self.progress.describe())
        except Exception:  # noqa: BLE001 - progress is a view, never a reason to fail a run
            pass
