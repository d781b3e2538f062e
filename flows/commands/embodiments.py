"""``handedit embodiments``: the roster (one robot file per hand, arm and hand-arm).

    handedit embodiments list [--json]        every embodiment: track, DoF, assets, its robot file
    handedit embodiments show KEY [--file]    a robot's file (its path with --file: copy it to start a new one)
    handedit embodiments check FILE [--sheet PNG]   validate a robot file and try it: URDF, joints,
                                              a preview sheet, the synthetic hand's residual, the
                                              fitted wrist-to-root transform
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


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
                     "assets": where if ok else "missing", "detail": "" if ok else where, "file": e.files[0] if e.files else ""})
    return rows


def cmd_list(args: argparse.Namespace) -> int:
    rows = _rows()
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    from handedit.embodiments.robot_files import BUILTIN

    print(f"{'id':<22}{'name':<24}{'track':<10}{'dof':>4}  {'file':<34}assets")
    for r in rows:
        dof = "-" if r["dof"] is None else str(r["dof"])
        f = r["file"]
        f = str(Path(f).relative_to(BUILTIN.parent.parent.parent)) if f.startswith(str(BUILTIN)) else f
        print(f"{r['id']:<22}{r['name']:<24}{r['track']:<10}{dof:>4}  {f:<34}{r['assets']}")
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


def cmd_show(args: argparse.Namespace) -> int:
    from handedit.embodiments import EmbodimentError
    from handedit.embodiments.robot_files import current_files

    files = current_files()
    if args.key not in files:
        try:
            from handedit.embodiments import get_embodiment

            get_embodiment(args.key)
        except EmbodimentError as exc:
            print(f"handedit embodiments show: {exc}", file=sys.stderr)
            return 2
    path, _ = files[args.key]
    print(path if args.file else path.read_text(), end="\n" if args.file else "")
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    from handedit.embodiments import EmbodimentError
    from handedit.embodiments.check import check_robot_file

    try:
        report = check_robot_file(Path(args.file), sheet=Path(args.sheet) if args.sheet else None, residual=not args.no_retarget)
    except EmbodimentError as exc:
        print(f"handedit embodiments check: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    print(report["text"])
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("embodiments", help="the target robot roster")
    sub = p.add_subparsers(dest="embodiments_cmd", required=True)
    ls = sub.add_parser("list", help="all embodiments with track, DoF and asset status")
    ls.add_argument("--json", action="store_true", help="machine-readable output")
    ls.set_defaults(func=cmd_list)
    sh = sub.add_parser("show", help="print a robot's file (or only its path: --file)")
    sh.add_argument("key", help="an embodiment's (or an arm's) key")
    sh.add_argument("--file", action="store_true", help="only the path of the file (copy it to start a new robot)")
    sh.set_defaults(func=cmd_show)
    ck = sub.add_parser("check", help="validate a robot file and try it (URDF, joints, preview, residual, wrist fit)")
    ck.add_argument("file", help="a robot file (YAML); its folder joins the roster for this check")
    ck.add_argument("--sheet", help="where to write the preview sheet (PNG; default <key>-check.png here)")
    ck.add_argument("--no-retarget", action="store_true", help="skip retargeting the synthetic hand (the slow part)")
    ck.add_argument("--json", action="store_true", help="machine-readable output")
    ck.set_defaults(func=cmd_check)
