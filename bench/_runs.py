"""A curated run's store for a bench to read, or a clear exit saying how to make one."""

from __future__ import annotations

import sys


def open_run(path: str, bench: str, make: str):
    """The Zarr root of the run at ``path`` (its folder or store); on a missing or unreadable
    store, exit with the reason and ``make``, the command that writes one."""
    from handedit.storage import StoreError, open_store

    try:
        return open_store(path)
    except StoreError as e:
        sys.exit(f"{bench}: {e} ({make} makes one)")
