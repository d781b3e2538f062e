"""restore_background: the scene behind the hand (or hand-arm) for one chunk.

Reads a window of frames around the chunk so the domain function can propagate real
background pixels from neighbouring frames before inpainting the rest.
"""

from __future__ import annotations

import numpy as np
import zarr
from prefect import task

from handedit.reasons import combine, gate
from handedit.vision.restore_background import RestoreConfig, restore_background as restore
from handedit.storage import Unit, read_chunk
from handedit.storage.layout import SCOPE_MASK
from handedit.tasks._options import stage_options
from handedit.tasks.common import ChunkJob, StageOutput, execute


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    lo, hi = job.context["window"]
    clip, mask_name, features = job.unit.clip, SCOPE_MASK[job.unit.scope], SCOPE_MASK["hand"]
    src = read_chunk(root, Unit("ingest", clip), ["frames"], lo, hi)
    seg = read_chunk(root, Unit("segment", clip), sorted({mask_name, features, "status"}), lo, hi)
    usable = gate(seg["status"])  # frames whose masks can be trusted, as sources or targets
    targets = np.arange(job.start - lo, job.stop - lo)
    # every hand is removed (the union of the per-hand masks); composite pastes back hands it does not replace;
    # both scopes align on the background around the hands (the same homographies, fitted once)
    removed = {name: seg[name].any(axis=1) for name in {mask_name, features}}  # one array when the scope is "hand"
    result = restore(src["frames"], removed[mask_name], targets, RestoreConfig(**job.params), frame_ok=usable,
                     feature_masks=removed[features])
    arrays = {"background": result.background, "filled_from_video": result.filled_from_video, "hole": result.hole}
    return StageOutput(arrays, combine(result.status, usable[targets]), method=result.method)


@task(**stage_options("restore_background"))
def restore_background(job: ChunkJob) -> dict:
    return execute(job, body)
