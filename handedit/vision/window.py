"""The part of a frame a per-pixel stage has to touch.

Compositing, harmonization and the residue check change or read pixels only within a few
(or a few dozen) pixels of the robot or the hand, a small box of a 640x480 or 1080p frame.
Every neighbourhood operation they use (dilation, blur, distance transform) reaches at
most a known radius, so computing inside the mask's box grown by that radius gives the
full frame's result exactly.
"""

from __future__ import annotations

import numpy as np


def window(mask: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    """The slices of ``mask``'s bounding box grown by ``margin`` (clipped), None when empty."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if not len(rows):
        return None
    H, W = mask.shape
    return (slice(max(0, rows[0] - margin), min(H, rows[-1] + 1 + margin)),
            slice(max(0, cols[0] - margin), min(W, cols[-1] + 1 + margin)))
