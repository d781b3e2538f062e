"""Sub-commands of ``handedit`` beyond curate/ledger/status/dashboard.

Each module here defines ``register(subparsers)`` adding its sub-command(s) with
``set_defaults(func=...)``; ``flows.cli`` registers every module it finds, so a new
command is one new file.
"""

from __future__ import annotations

import importlib
import pkgutil


def register_all(subparsers) -> None:
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(subparsers)
