"""Thin Prefect tasks: one declaration per stage (``tasks/<stage>.py``: what it reads and
its body), walked chunk by chunk by the two tasks of ``tasks.clip``.

Each stage reads its declared inputs, calls ``handedit``, and returns its chunk's arrays
and statuses; the walk writes them with their provenance record. The math lives in
``handedit``; retries live in ``tasks.clip``.
"""

from handedit.tasks import (composite, estimate_hands, harmonize, ingest, qc, registration, render, restore_background,
                            retarget, segment)

# Pipeline order. A new stage is one module here and its domain code.
STAGES = tuple(m.STAGE for m in (ingest, estimate_hands, registration, segment, restore_background,
                                 retarget, render, composite, harmonize, qc))

__all__ = ["STAGES"]
