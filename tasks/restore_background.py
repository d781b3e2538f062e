"""restore_background: the scene behind the hand (or hand-arm) for one chunk.

Reads a window of frames around the chunk (``RestoreConfig.window`` each side) so the
domain function can propagate real background pixels from neighbouring frames before
inpainting the rest.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from handedit.reasons import combine, gate
from handedit.storage import Unit
from handedit.storage.layout import SCOPE_MASK
from handedit.tasks.common import ChunkJob, StageOutput
from handedit.tasks.stage import At, Inputs, Stage
from handedit.vision.restore_background import RestoreConfig, restore_background as restore


def _window(start: int, stop: int, n_frames: int, window: int) -> tuple[int, int]:
    return max(0, start - window), min(n_frames, stop + window)


def _masks(scope: str) -> list[str]:
    # both scopes align on the background around the hands: the hand masks are the alignment features
    return sorted({SCOPE_MASK[scope], SCOPE_MASK["hand"], "status"})


def reads(at: At) -> list:
    lo, hi = _window(at.start, at.stop, at.plan.n_frames, at.config.window)
    wide = replace(at, start=lo, stop=hi)
    clip = at.plan.clip
    return [*wide.each(Unit("ingest", clip), ("frames",)), *wide.each(Unit("segment", clip), _masks(at.unit.scope))]


def body(inp: Inputs, job: ChunkJob) -> StageOutput:
    cfg = RestoreConfig(**job.params)
    lo, hi = _window(job.start, job.stop, job.plan.n_frames, cfg.window)
    clip, mask_name, features = job.unit.clip, SCOPE_MASK[job.unit.scope], SCOPE_MASK["hand"]
    src = inp.read(Unit("ingest", clip), ["frames"], lo, hi)
    seg = inp.read(Unit("segment", clip), _masks(job.unit.scope), lo, hi)
    usable = gate(seg["status"])  # frames whose masks can be trusted, as sources or targets
    targets = np.arange(job.start - lo, job.stop - lo)
    # every hand is removed (the union of the per-hand masks); composite pastes back hands it does not replace
    removed = {name: seg[name].any(axis=1) for name in {mask_name, features}}  # one array when the scope is "hand"
    result = restore(src["frames"], removed[mask_name], targets, cfg, frame_ok=usable, feature_masks=removed[features])
    arrays = {"background": result.background, "filled_from_video": result.filled_from_video, "hole": result.hole}
    return StageOutput(arrays, combine(result.status, usable[targets]), method=result.method)


STAGE = Stage("restore_background", "scope", RestoreConfig, reads, body)
