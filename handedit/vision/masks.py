"""Disk dilation of masks, inside their box.

Why: the vision stages grow small masks (a hand, a hole) by disks tens of pixels wide. A
dilation's cost grows with the frame and with the disk: nothing changes farther than the
disk's radius from the mask, so the work stays in the mask's box grown by that radius, and
a disk wider than ``EXACT_MAX`` px is a Euclidean ball from one distance transform (linear
in the box, whatever the radius) rather than cv2's elliptic kernel, which it matches up to
boundary pixels.
"""

from __future__ import annotations

import cv2
import numpy as np

from handedit.metrics.similarity import bbox


EXACT_MAX = 8  # px: up to this radius, exactly cv2.dilate with disk(r)


def disk(r: float) -> np.ndarray:
    """Elliptic structuring element of radius ``round(r)`` (at least 1)."""
    r = max(1, int(round(r)))
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def grow(mask: np.ndarray, r: float) -> np.ndarray:
    """``mask`` dilated by a disk of radius ``round(r)`` (at least 1), as bool."""
    k = disk(r)
    rad = k.shape[0] // 2
    out = np.zeros(np.shape(mask), bool)
    win = bbox(mask, rad)
    if win is None:
        return out
    m8 = np.ascontiguousarray(mask[win], np.uint8)
    if rad <= EXACT_MAX:
        out[win] = cv2.dilate(m8, k).astype(bool)
    else:
        out[win] = cv2.distanceTransform(1 - m8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) <= rad
    return out
