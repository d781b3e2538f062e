"""``handedit assets fetch``: download the roster's public robots (see handedit.embodiments.fetch)."""

from __future__ import annotations

import argparse


def cmd_fetch(args: argparse.Namespace) -> int:
    from handedit.embodiments.fetch import BASE_URL, default_dest, fetch
    from handedit.embodiments.roster import asset_dirs

    try:
        report = fetch(args.dest, args.robot or None, base_url=args.base_url or BASE_URL, timeout=args.timeout)
    except ValueError as exc:
        print(f"handedit assets fetch: {exc}")
        return 2
    for r in report.results:
        robots = ", ".join(r.robots) or "(shared meshes)"
        line = f"{r.status:<8} {r.folder:<24} {robots:<28} licence: {r.license}"
        print(line + (f"\n         {r.detail}" if r.detail else ""))
    failed = [r for r in report.results if r.status == "failed"]
    print(f"\n{len(report.results) - len(failed)}/{len(report.results)} robot folders in {report.dest}.")
    if report.dest.resolve() != default_dest().resolve() and report.dest.resolve() not in [d.resolve() for d in asset_dirs()]:
        print(f"Not the default folder: add it to $HANDEDIT_ASSET_DIRS (export HANDEDIT_ASSET_DIRS={report.dest}).")
    if failed:
        print(f"{len(failed)} failed: run the same command again to resume (verified files are kept).")
        return 1
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("assets", help="robot descriptions (URDF + meshes) for the roster")
    sub = p.add_subparsers(dest="assets_cmd", required=True)
    f = sub.add_parser("fetch", help="download the public robots at their pinned commits, sha256-checked")
    f.add_argument("--dest", help="target folder (default: the user cache, searched without any setting)")
    f.add_argument("--robot", action="append", help="only this manifest key (repeatable), e.g. rohand")
    f.add_argument("--base-url", help="archive server (default https://codeload.github.com; a mirror in its layout)")
    f.add_argument("--timeout", type=float, default=60.0, help="seconds per connection")
    f.set_defaults(func=cmd_fetch)
