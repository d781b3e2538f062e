"""``handedit release``: publish the next version of a dataset release.

    handedit release --from runs/demo [--from runs/other] --out runs/releases
                     [--embodiment ID ...] [--shard-mb 1024] [--videos] [--address tcp://...]

Prints the version, its pairs and shards (how many reused from the parent) and the
changelog counts; the release's datasheet and changelog are Markdown files beside it.
"""

from __future__ import annotations

import argparse


def cmd_release(args: argparse.Namespace) -> int:
    from handedit.flows.config import ClusterConfig
    from handedit.flows.release import ReleaseConfig, run_release
    from handedit.storage import Location

    cfg = ReleaseConfig(sources=args.sources, out=args.out, embodiments=args.embodiment or [],
                        target_shard_bytes=int(args.shard_mb * (1 << 20)), videos=args.videos,
                        cluster=ClusterConfig(address=args.address, n_workers=args.workers))
    m = run_release(cfg)
    c = m["counts"]
    loc = Location(args.out)
    print(f"published {m['version']} (parent {m['parent'] or '-'}): {c['pairs']} pairs in {c['shards']} shard(s), "
          f"{c['shards_reused']} reused from the parent")
    if args.videos:
        print(f"videos: {c['videos']} clip x embodiment video pairs, {c['videos_reused']} reused from earlier releases")
    print(f"changes: {c['added']} added, {c['removed']} removed, {c['changed']} changed")
    print(f"manifest:  {loc.path(m['version'], 'manifest.json')}")
    print(f"datasheet: {loc.path(m['version'], 'datasheet.md')}")
    print(f"changelog: {loc.path(m['version'], 'changelog.md')}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("release", help="publish the next immutable version of a dataset release")
    p.add_argument("--from", dest="sources", action="append", required=True, help="a curated run (repeatable)")
    p.add_argument("--out", required=True, help="the releases folder or URL")
    p.add_argument("--embodiment", action="append", help="only these embodiments (repeatable)")
    p.add_argument("--videos", action="store_true", help="also frame-aligned MP4s of the source, pseudo-GT and robot "
                   "mask per clip x embodiment, beside the shards")
    p.add_argument("--shard-mb", type=float, default=1024.0, help="target WebDataset shard size (MiB)")
    p.add_argument("--address", help="Dask scheduler address (default: a local cluster)")
    p.add_argument("--workers", type=int, default=2)
    p.set_defaults(func=cmd_release)
