"""The MANO model as the MANO-based adapters load it: a missing file is a SourceError (a
clip-level rejection naming the file and where to get it)."""

from __future__ import annotations

from handedit.hands.mano import ManoError, ManoModel
from handedit.sources.base import SourceError


def mano_model(mano_dir, side: str) -> ManoModel:
    try:
        return ManoModel.find(mano_dir, side)
    except ManoError as exc:
        raise SourceError(str(exc)) from None


def mano_digest(mano_dir) -> str:
    """Identifies the model files a clip's keypoints come from (part of its fingerprint)."""
    import hashlib

    m = mano_model(mano_dir, "right")
    return hashlib.sha256(m.v_template.tobytes() + m.J_regressor.tobytes()).hexdigest()[:16]
