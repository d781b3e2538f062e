"""``handedit export lerobot``: a curated run's episodes of one embodiment as a LeRobot dataset.

    handedit export lerobot --from runs/demo --embodiment allegro --out exports/allegro
                            [--include-source] [--fps F] [--codec libx264] [--clip ID ...]

Run it again after more curation: only new or changed episodes are encoded (see
``handedit.flows.export``).
"""

from __future__ import annotations

import argparse
import sys


def cmd_export_lerobot(args: argparse.Namespace) -> int:
    from handedit.embodiments import EmbodimentError
    from handedit.flows.config import ClusterConfig
    from handedit.flows.export import ExportError, LeRobotExportConfig, run_export

    try:
        cfg = LeRobotExportConfig(source=args.source, embodiment=args.embodiment, out=args.out,
                                  include_source=args.include_source, fps=args.fps, codec=args.codec, crf=args.crf,
                                  clips=args.clip or [], cluster=ClusterConfig(address=args.address, n_workers=args.workers))
        res = run_export(cfg)
    except (ExportError, EmbodimentError, ValueError) as exc:
        print(f"handedit export lerobot: {exc}", file=sys.stderr)
        return 2
    print(f"exported {res['episodes']} episode(s), {res['frames']} frames ({res['kept_frames']} kept) to {res['out']}: "
          f"{res['encoded']} encoded, {res['reused']} unchanged" + (f", {len(res['removed'])} removed" if res["removed"] else "")
          + f" in {res['seconds']} s")
    if res["skipped"]:
        print(f"left out {len(res['skipped'])} clip(s) without a kept frame: {', '.join(res['skipped'][:5])}")
    print(f"load it: LeRobotDataset('local/{args.embodiment}', root='{res['out']}')")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("export", help="export a curated run in another format (lerobot)")
    sub = p.add_subparsers(dest="format", required=True)
    lr = sub.add_parser("lerobot", help="one embodiment's episodes as a LeRobot v3.0 dataset")
    lr.add_argument("--from", dest="source", required=True, help="the curated run (folder or URL)")
    lr.add_argument("--embodiment", required=True, help="the embodiment to export (one dataset per embodiment)")
    lr.add_argument("--out", required=True, help="the dataset folder (created, or updated in place)")
    lr.add_argument("--include-source", action="store_true", help="also the human source video (observation.images.source)")
    lr.add_argument("--fps", type=float, help="frames per second (default: the clips' own)")
    lr.add_argument("--codec", default="libsvtav1", choices=["libsvtav1", "libx264"], help="video codec (default: LeRobot's AV1)")
    lr.add_argument("--crf", type=int, default=30, help="video quality (lower: better, larger; default 30 as LeRobot)")
    lr.add_argument("--clip", action="append", help="only this clip (repeatable)")
    lr.add_argument("--address", help="Dask scheduler address (default: a local cluster)")
    lr.add_argument("--workers", type=int, default=2)
    lr.set_defaults(func=cmd_export_lerobot)
