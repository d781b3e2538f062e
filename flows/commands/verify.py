"""``handedit verify``: does the store hold every chunk its records vouch for, intact?

    handedit verify DIR               presence: every recorded chunk's objects exist (listings only)
    handedit verify DIR --deep        and every chunk re-hashes to its recorded digest
    handedit verify DIR --repair      forget the problem chunks' records and reopen their shards,
                                      so the next `handedit curate` recomputes exactly those

Exit status: 0 when nothing is wrong (or everything found was repaired), 1 when problems
remain, 2 when the store cannot be opened. ``--json`` prints the problems as one object.
"""

from __future__ import annotations

import argparse
import json
import sys


def cmd_verify(args: argparse.Namespace) -> int:
    from handedit.storage import Location, StoreError
    from handedit.storage.integrity import rebuild_root, repair, root_damaged, verify

    loc = Location(args.store)
    if args.repair and root_damaged(loc):
        try:
            attrs = rebuild_root(loc)
        except StoreError as exc:
            print(f"handedit verify: {exc}", file=sys.stderr)
            return 2
        print(f"repaired: rebuilt {loc.store_url}/zarr.json (frames_per_chunk {attrs['frames_per_chunk']})")
    try:
        problems = verify(loc, clips=args.clip or None, deep=args.deep)
    except StoreError as exc:
        print(f"handedit verify: {exc}", file=sys.stderr)
        return 2
    repaired = repair(loc, problems) if args.repair and problems else None
    if args.json:
        print(json.dumps({"store": loc.store_url, "deep": args.deep, "problems": [p.to_json() for p in problems],
                          "repaired": repaired}, indent=1))
    else:
        for p in problems:
            print(p.describe())
        check = "content and presence" if args.deep else "presence (add --deep to re-hash the content)"
        print(f"{len(problems)} problem chunk(s) in {loc.store_url}; checked {check}")
        if repaired:
            print(f"repaired: forgot {repaired['records_dropped']} record(s) in {repaired['units']} unit(s), reopened "
                  f"shard(s) {', '.join(repaired['shards']) or '-'}; run `handedit curate` with the same "
                  f"configuration to recompute them")
        elif problems:
            deep = " --deep" if args.deep else ""
            print(f"run `handedit verify {args.store}{deep} --repair`, then `handedit curate` again, to recompute them")
    return 0 if not problems or repaired else 1


def register(subparsers) -> None:
    p = subparsers.add_parser("verify", help="check that every recorded chunk is stored and intact (--repair)")
    p.add_argument("store", help="the run folder or store (local path or URL)")
    p.add_argument("--deep", action="store_true", help="re-hash every chunk against its recorded digest")
    p.add_argument("--repair", action="store_true", help="forget the problem chunks so that curate recomputes them")
    p.add_argument("--clip", action="append", help="only this clip (repeatable)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_verify)
