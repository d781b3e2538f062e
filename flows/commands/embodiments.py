"""``handedit embodiments list``: the 26 target embodiments, their track, DoF and asset status."""

from __future__ import annotations

import argparse
import json


def _rows(check_dof: bool = True) -> list[dict]:
    from handedit.embodiments import EmbodimentError, asset_status, list_embodiments
    from handedit.embodiments.kinematics import get_kinematics
    from handedit.embodiments.roster import resolve_urdf

    rows = []
    for e in list_embodiments():
        ok, where = asset_status(e)
        dof = None
        if ok and check_dof:
            try:
                dof = get_kinematics(resolve_urdf(e)).dof
            except EmbodimentError as exc:  # found but broken: report, don't crash the listing
                ok, where = False, str(exc)
        rows.append({"id": e.id, "name": e.name, "track": e.track, "dof": dof, "available": ok,
                     "assets": where if ok else "missing", "detail": "" if ok else where})
    return rows


def cmd_list(args: argparse.Namespace) -> int:
    rows = _rows()
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    print(f"{'id':<22}{'name':<24}{'track':<10}{'dof':>4}  assets")
    for r in rows:
        dof = "-" if r["dof"] is None else str(r["dof"])
        print(f"{r['id']:<22}{r['name']:<24}{r['track']:<10}{dof:>4}  {r['assets']}")
    n_ok = sum(r["available"] for r in rows)
    print(f"\n{n_ok}/{len(rows)} embodiments available.", end="")
    missing = [r for r in rows if not r["available"]]
    if missing:
        print(" Missing assets:")
        for r in missing:
            print(f"  {r['id']}: {r['detail']}")
    else:
        print()
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("embodiments", help="the target robot roster")
    sub = p.add_subparsers(dest="embodiments_cmd", required=True)
    ls = sub.add_parser("list", help="all embodiments with track, DoF and asset status")
    ls.add_argument("--json", action="store_true", help="machine-readable output")
    ls.set_defaults(func=cmd_list)
