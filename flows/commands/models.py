"""``handedit models fetch``: MediaPipe's hand models for estimate_hands (see handedit.models.fetch)."""

from __future__ import annotations

import argparse
from pathlib import Path


def cmd_fetch(args: argparse.Namespace) -> int:
    from handedit.models.fetch import ModelFetchError, default_model_dir, fetch

    try:
        result = fetch(Path(args.dest) if args.dest else None, Path(args.wheel) if args.wheel else None)
    except ModelFetchError as exc:
        print(f"handedit models fetch: {exc}")
        return 2
    print(result.summary())
    if result.dest.resolve() != default_model_dir().resolve():
        print(f"Not the default folder: export HANDEDIT_HAND_MODEL_DIR={result.dest} (or set estimate_hands.model_dir).")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("models", help="model files the stages run (hand pose estimation)")
    sub = p.add_subparsers(dest="models_cmd", required=True)
    f = sub.add_parser("fetch", help="MediaPipe's hand models (Apache-2.0) out of the mediapipe 0.10.21 wheel, sha256-checked")
    f.add_argument("--dest", help="target folder (default: the user cache estimate_hands reads without any setting)")
    f.add_argument("--wheel", help="a mediapipe 0.10.21 wheel already on disk (no download)")
    f.set_defaults(func=cmd_fetch)
