"""``handedit bank build``: the embodiment reference bank (canonical renders + frozen descriptions).

    handedit bank build --out bank.zarr [--views 4] [--size 512] [--embodiment ID ...]

Without ``--embodiment`` every embodiment whose assets are available is built and the
missing ones are listed; naming an unavailable one is an error that says what to provide.
"""

from __future__ import annotations

import argparse
import os
import sys


def cmd_build(args: argparse.Namespace) -> int:
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    from handedit.embodiments import EmbodimentError, asset_status, get_embodiment, list_embodiments
    from handedit.render.bank import BankConfig, render_bank_views
    from handedit.storage.bank import BankEntry, write_bank_entry

    cfg = BankConfig(views=args.views, width=args.width or args.size, height=args.height or args.size,
                     seed=args.seed, decimate=args.decimate)
    if args.embodiment:
        try:
            embs = [get_embodiment(i) for i in args.embodiment]
        except EmbodimentError as e:
            print(f"handedit bank build: {e}", file=sys.stderr)
            return 2
        for e in embs:
            ok, why = asset_status(e)
            if not ok:
                print(f"handedit bank build: {why}", file=sys.stderr)
                return 2
    else:
        embs = []
        for e in list_embodiments():
            ok, why = asset_status(e)
            if ok:
                embs.append(e)
            else:
                print(f"skipped {e.id}: assets missing", file=sys.stderr)
    for e in embs:
        try:
            r = render_bank_views(e.id, cfg)
        except EmbodimentError as exc:
            print(f"handedit bank build: {exc}", file=sys.stderr)
            return 2
        write_bank_entry(args.out, BankEntry(e.id, e.name, e.track, e.description, r.rgb, r.mask,
                                             r.camera_from_root, r.qpos, r.K), cfg.rig())
        print(f"{e.id}: {cfg.views} views {cfg.width}x{cfg.height}, robot pixels {r.mask.mean():.1%}")
    print(f"reference bank: {args.out} ({len(embs)} embodiments)")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("bank", help="the embodiment reference bank")
    sub = p.add_subparsers(dest="bank_cmd", required=True)
    b = sub.add_parser("build", help="render canonical views of each embodiment into a Zarr store")
    b.add_argument("--out", required=True, help="bank store path (e.g. bank.zarr)")
    b.add_argument("--views", type=int, default=4)
    b.add_argument("--size", type=int, default=512, help="square image size (see --width/--height)")
    b.add_argument("--width", type=int, default=None)
    b.add_argument("--height", type=int, default=None)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--decimate", type=float, default=None)
    b.add_argument("--embodiment", action="append", help="embodiment id (repeatable); default: all available")
    b.set_defaults(func=cmd_build)
