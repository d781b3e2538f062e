"""Per-frame status codes: the one reason table for every stage.

Every stage writes a ``status`` array (int16, one value per frame). ``PENDING`` means
the stage has not produced this frame, ``OK`` that it has, ``UPSTREAM`` that an earlier
stage rejected the frame (the ledger names that earlier cause only once), ``ABSENT``
(per side only) that this hand is not in view, and every code >= 100 is a rejection
whose cause the ledger records with a detail string.

The hundreds group codes by stage family, following the paper's quality-control table.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np


class Reason(IntEnum):
    PENDING = 0
    OK = 1
    UPSTREAM = 2  # an earlier stage rejected this frame
    ABSENT = 3  # per side: this hand is not in view (nothing to replace); never a rejection

    # 1xx: input / source
    NO_KEYPOINTS = 101  # the source has no (valid) hand keypoints for this frame
    CORRUPT_FRAME = 102  # frame could not be decoded
    BLANK_FRAME = 103  # frame is constant / all black
    SOURCE_UNREADABLE = 104  # the clip's source could not be opened at all (frame -1 in the ledger)
    NO_HAND_DETECTED = 105  # estimate_hands: no hand found in the frame (every side)
    LOW_HAND_CONFIDENCE = 106  # estimate_hands: the landmark model's hand presence is below the threshold
    IMPLAUSIBLE_HAND = 107  # estimate_hands: bone lengths or reprojection of the 3-D hand are not a hand's
    # 2xx: segmentation
    EMPTY_MASK = 201
    LOW_CONFIDENCE = 202  # segmenter confidence below threshold (0.75 for a model)
    # 3xx: background restoration
    RESIDUE = 301  # skin-coloured pixels left in the restored region
    GHOSTING = 302
    # 4xx: hand retargeting
    FINGERTIP_ERROR = 401  # fingertip error > 50 mm
    WRIST_ERROR = 402  # wrist error > 50 mm
    CONTACT_DISTANCE = 403  # contact distance > 20 mm
    CONTACT_LOSS = 404
    PENETRATION = 405
    JOINT_LIMIT = 406
    SOLVER_FAILED = 407
    # 5xx: IK and virtual base
    IK_INFEASIBLE = 501
    OUT_OF_REACH = 502
    COLLISION = 503
    DISCONTINUITY = 504
    NO_VALID_BASE = 505
    REVIEW_DROPPED = 506
    BODY_COLLISION = 507  # hand-arm: an arm link enters the operator's head or torso
    # 6xx: render / composite / harmonize
    EMPTY_RENDER = 601  # the robot is not visible in the image
    HUMAN_VISIBLE = 602  # human-hand pixels remain visible beside the robot in the composite
    OFF_ARM = 603  # hand-arm: too much of the robot lies outside the human arm's corridor (base plausibility)
    HAND_HIDDEN = 604  # hand-arm: a robot arm link covers where the human hand was seen, hiding the robot's hand
    # 9xx: infrastructure
    STAGE_ERROR = 901  # the stage raised after its retries; detail holds the error
    ASSETS_MISSING = 902  # embodiment assets could not be resolved

    @property
    def is_rejection(self) -> bool:
        return self.value >= 100


STATUS_DTYPE = np.int16


def describe() -> list[dict]:
    """The reason table as rows (code, name), for docs, dashboards and the CLI."""
    return [{"code": int(r), "name": r.name} for r in Reason]


def gate(*upstream: np.ndarray) -> np.ndarray:
    """Frames that every upstream stage produced OK (bool mask)."""
    ok = np.ones_like(np.asarray(upstream[0]), dtype=bool)
    for s in upstream:
        ok &= np.asarray(s) == Reason.OK
    return ok


def per_frame(hand_status: np.ndarray) -> np.ndarray:
    """Frame-level status of a per-hand stage from its (n,S) ``hand_status``: OK where any
    hand is OK; else the first hand's rejection; else UPSTREAM (no hand had anything)."""
    hs = np.asarray(hand_status)
    out = np.full(hs.shape[0], int(Reason.UPSTREAM), STATUS_DTYPE)
    rejected = hs >= 100
    first = np.argmax(rejected, axis=1)
    has = rejected.any(axis=1)
    out[has] = hs[np.flatnonzero(has), first[has]]
    out[(hs == Reason.OK).any(axis=1)] = Reason.OK
    return out


def combine_hands(own: np.ndarray, ready: np.ndarray) -> np.ndarray:
    """Per-hand ``combine``: (n,S) own codes where ``ready`` (n,S); ABSENT stays ABSENT."""
    own = np.asarray(own, dtype=STATUS_DTYPE)
    ready = np.asarray(ready, bool)
    out = own.copy()
    out[~ready & (own != Reason.ABSENT)] = Reason.UPSTREAM
    return out


def follow_hands(own: np.ndarray, upstream: np.ndarray) -> np.ndarray:
    """Per-hand codes after an upstream per-hand stage: ``own`` (n,S) where upstream was OK,
    ABSENT where it saw no hand, UPSTREAM where it rejected (or never had) the side."""
    up = np.asarray(upstream)
    out = np.full(up.shape, Reason.UPSTREAM, STATUS_DTYPE)
    out[up == Reason.ABSENT] = Reason.ABSENT
    ok = up == Reason.OK
    out[ok] = np.asarray(own, STATUS_DTYPE)[ok]
    return out


def combine(own: np.ndarray, ready: np.ndarray) -> np.ndarray:
    """A stage's status: its own code where its inputs were ready, UPSTREAM elsewhere."""
    out = np.asarray(own, dtype=STATUS_DTYPE).copy()
    out[~np.asarray(ready, dtype=bool)] = Reason.UPSTREAM
    return out
