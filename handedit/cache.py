"""The user cache: composed, derived and mirrored URDFs, fetched robot assets and models,
compiled solvers. ``$HANDEDIT_CACHE_DIR`` or ``~/.cache/handedit``; every file below it is
written atomically and named by a digest of its inputs, so concurrent workers agree on it."""

from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV = "HANDEDIT_CACHE_DIR"


def cache_root() -> Path:
    return Path(os.environ.get(CACHE_ENV) or str(Path.home() / ".cache" / "handedit")).expanduser()
