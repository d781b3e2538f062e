"""``handedit sources list``: the clip sources, what each needs and what it provides."""

from __future__ import annotations

import argparse


def cmd_list(args: argparse.Namespace) -> int:
    from handedit.sources import SOURCES, TREES

    for name, row in SOURCES.items():
        how = f"--source {name} --root DIR" if name in TREES else ("--demo" if name == "synthetic" else "--video FILE")
        print(f"{name:<10} {how}\n           needs:    {row['needs']}\n           provides: {row['provides']}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("sources", help="the clip sources (datasets, videos, synthetic)")
    sub = p.add_subparsers(dest="sources_cmd", required=True)
    sub.add_parser("list", help="each source: the command, what it needs, what it provides").set_defaults(func=cmd_list)
