"""restore_background: the scene behind the hand (or hand-arm) for one chunk.

Reads a window of frames around the chunk (``RestoreConfig.window`` each side) so the
domain function can propagate real background pixels from neighbouring frames, and
``RestoreConfig.clip_sources`` frames spread over the rest of the clip for what the window
never saw (a hand that holds still), before inpainting the rest.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from handedit.reasons import combine, gate
from handedit.storage import Unit
from handedit.storage.layout import ArraySpec, MASK, MASK_DIMS, RGB, RGB_DIMS, SCOPE_MASK, STATUS
from handedit.tasks.common import ChunkJob, StageOutput
from handedit.tasks.stage import At, Inputs, Stage
from handedit.vision.restore_background import RestoreConfig, restore_background as restore


def _window(start: int, stop: int, n_frames: int, window: int) -> tuple[int, int]:
    return max(0, start - window), min(n_frames, stop + window)


def _rest(start: int, stop: int, n_frames: int, cfg: RestoreConfig) -> list[int]:
    """Frames of the clip more than twice the window from the chunk's (those restoration takes
    for what the window never saw), ``clip_sources`` of them spread evenly (the classical
    method only: a learned video inpainter takes the window as a video)."""
    far = 2 * cfg.window
    outside = np.r_[0:max(0, start - far), min(n_frames, stop + far):n_frames]
    if cfg.method != "classical" or not cfg.clip_sources or not len(outside):
        return []
    pick = np.linspace(0, len(outside) - 1, min(cfg.clip_sources, len(outside))).round().astype(int)
    return sorted({int(outside[k]) for k in pick})


def _runs(frames: list[int]) -> list[tuple[int, int]]:
    """[a, b) runs of consecutive frame numbers: each read once."""
    runs: list[list[int]] = []
    for f in frames:
        if runs and runs[-1][1] == f:
            runs[-1][1] = f + 1
        else:
            runs.append([f, f + 1])
    return [(a, b) for a, b in runs]


def _masks(scope: str, rest: bool) -> list[str]:
    # both scopes align on the background around the hands: the hand masks are the alignment features;
    # the rest of the clip gives no pixel of its arms (a sleeve is not the background behind a hand)
    return sorted({SCOPE_MASK[scope], SCOPE_MASK["hand"], "status", *([SCOPE_MASK["hand_arm"]] if rest else [])})


def reads(at: At) -> list:
    lo, hi = _window(at.start, at.stop, at.plan.n_frames, at.config.window)
    rest = _runs(_rest(at.start, at.stop, at.plan.n_frames, at.config))
    clip, out = at.plan.clip, {}
    for a, b in [(lo, hi), *rest]:
        wide = replace(at, start=a, stop=b)
        out.update(dict.fromkeys([*wide.each(Unit("ingest", clip), ("frames",)),
                                  *wide.each(Unit("segment", clip), _masks(at.unit.scope, bool(rest)))]))
    return list(out)


def body(inp: Inputs, job: ChunkJob) -> StageOutput:
    cfg = RestoreConfig(**job.params)
    lo, hi = _window(job.start, job.stop, job.plan.n_frames, cfg.window)
    clip, mask_name, features = job.unit.clip, SCOPE_MASK[job.unit.scope], SCOPE_MASK["hand"]
    rest = _runs(_rest(job.start, job.stop, job.plan.n_frames, cfg))
    spans = sorted([(lo, hi), *rest])
    src = [inp.read(Unit("ingest", clip), ["frames"], a, b)["frames"] for a, b in spans]
    seg = [inp.read(Unit("segment", clip), _masks(job.unit.scope, bool(rest)), a, b) for a, b in spans]
    frames = np.concatenate(src) if len(src) > 1 else src[0]
    times = np.concatenate([np.arange(a, b) for a, b in spans])
    usable = np.concatenate([gate(s["status"]) for s in seg])  # frames whose masks can be trusted, as sources or targets
    targets = np.searchsorted(times, np.arange(job.start, job.stop))
    # every hand is removed (the union of the per-hand masks); composite pastes back hands it does not replace
    arms = SCOPE_MASK["hand_arm"] if rest else mask_name
    removed = {name: np.concatenate([s[name].any(axis=1) for s in seg]) for name in {mask_name, features, arms}}
    result = restore(frames, removed[mask_name], targets, cfg, frame_ok=usable, feature_masks=removed[features], times=times,
                     arm_masks=removed[arms])
    arrays = {"background": result.background, "filled_from_video": result.filled_from_video, "hole": result.hole}
    return StageOutput(arrays, combine(result.status, usable[targets]), method=result.method)


WRITES = (
    ArraySpec("background", RGB, "uint8", RGB_DIMS, image=True),
    ArraySpec("filled_from_video", (), "float32", ()),
    ArraySpec("hole", MASK, "bool", MASK_DIMS, image=True, fill=False),  # the restored pixels
    STATUS,
)
STAGE = Stage("restore_background", "scope", RestoreConfig, reads, body, writes=WRITES)
