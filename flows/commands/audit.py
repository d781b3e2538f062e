"""``handedit audit``: how often a person agrees with QC (``handedit.audit``).

    handedit audit sample RUN --n N [--name NAME] [--kept-share 0.5] [--seed S]
    handedit audit import RUN --name NAME FILE        verdicts made elsewhere (JSON Lines)
    handedit audit report RUN [--name NAME] [--json]
    handedit audit serve RUN [--name NAME] [--port P]  the review page on 127.0.0.1

``sample`` freezes a stratified sample of kept and rejected frame x embodiment pairs in the
run (``audit/<name>/``); ``import`` adds reviewers' verdicts, one JSON object per line
(``{"item", "verdict": "keep"|"reject", "cause", "reviewer"}``); ``report`` prints the share
of kept pairs reviewers accept with its Wilson 95 % interval, their agreement with QC and with
each other, and the failure breakdown by the reviewers' causes beside QC's, per embodiment
and track.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def _fmt(x, pct: bool = True) -> str:
    return "-" if x is None else (f"{100 * x:.1f} %" if pct else f"{x:.3f}")


def _open(args) -> tuple:
    from handedit.storage import Location
    from handedit.storage.audit import read_sample

    loc = Location(args.run)
    try:
        found = read_sample(loc, args.name)
    except ValueError as exc:
        raise SystemExit(f"error: {exc}")
    if found is None:
        raise SystemExit(f"error: no audit '{args.name}' in {loc.url}: run `handedit audit sample {args.run} --n N "
                         f"--name {args.name}` first")
    return loc, *found


def cmd_sample(args) -> int:
    from handedit.audit import sample
    from handedit.storage import Location, open_store
    from handedit.storage.audit import pairs, write_sample

    loc = Location(args.run)
    if not loc.store_exists():
        print(f"error: no store in {loc.url}; run `handedit curate --out {args.run}` first", file=sys.stderr)
        return 2
    universe = pairs(open_store(args.run))
    if not len(universe):
        print(f"error: {loc.url} has no curated pairs to sample", file=sys.stderr)
        return 2
    items = sample(universe, args.n, args.kept_share, args.seed)
    meta = {"name": args.name, "n": args.n, "kept_share": args.kept_share, "seed": args.seed,
            "universe": {"pairs": int(len(universe)), "kept": int(universe["kept"].sum())}}
    try:
        made = write_sample(loc, args.name, items, meta)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not made:
        print(f"error: audit '{args.name}' already has a sample in {loc.url} (its verdicts refer to it); "
              f"choose another --name", file=sys.stderr)
        return 2
    k = int(items["kept"].sum())
    print(f"audit '{args.name}': {len(items)} items ({k} kept, {len(items) - k} rejected) of {len(universe)} pairs, "
          f"seed {args.seed} -> {loc.path('audit', args.name)}")
    return 0


def cmd_import(args) -> int:
    from handedit.audit import parse_verdict
    from handedit.storage.audit import add_verdict

    loc, _, items = _open(args)
    known = set(items["id"])
    path = Path(args.file)
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        print(f"error: cannot read {path}: {exc.strerror}", file=sys.stderr)
        return 2
    checked, errors = [], []
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            checked.append(parse_verdict(json.loads(line), known))
        except json.JSONDecodeError as exc:
            errors.append(f"{path}:{n}: not JSON ({exc.msg})")
        except ValueError as exc:
            errors.append(f"{path}:{n}: {exc}")
    if errors:  # all or nothing: a file with a bad line adds no verdict
        print("error: no verdict imported:\n  " + "\n  ".join(errors[:20])
              + (f"\n  ... and {len(errors) - 20} more" if len(errors) > 20 else ""), file=sys.stderr)
        return 2
    for v in checked:
        add_verdict(loc, args.name, v)
    print(f"audit '{args.name}': {len(checked)} verdict(s) imported from {path}")
    return 0


def cmd_report(args) -> int:
    from handedit.audit import latest, report
    from handedit.storage.audit import read_verdicts

    loc, meta, items = _open(args)
    rep = {"name": args.name, "seed": meta.get("seed"), "created": meta.get("created"),
           **report(items, latest(read_verdicts(loc, args.name)))}
    if args.json:
        print(json.dumps(rep, default=float))
        return 0
    print(f"audit '{args.name}' of {loc.url}: {rep['n_reviewed']} of {rep['n_items']} items reviewed")
    head = f"{'embodiment':<22}{'track':<10}{'kept reviewed':>14}{'accepted':>11}{'95 % interval':>20}" \
           f"{'rejected also':>15}{'QC kappa':>10}{'reviewers kappa':>17}"
    print(head)
    for r in [*rep["per_embodiment"], {**rep, "embodiment": "all", "track": ""}]:
        lo, hi = r["precision_ci"]
        ci = f"{100 * lo:.1f}-{100 * hi:.1f} %" if r["n_kept_reviewed"] else "-"
        print(f"{r['embodiment']:<22}{r['track']:<10}{r['n_kept_reviewed']:>14}{_fmt(r['precision']):>11}{ci:>20}"
              f"{_fmt(r['rejection_agreement']):>15}{_fmt(r['qc_kappa'], False):>10}{_fmt(r['inter_reviewer_kappa'], False):>17}")
    print("\nprimary cause of rejected pairs   reviewers      QC")
    for b in rep["breakdown"]:
        print(f"  {b['cause']:<31}{b['reviewers']:>4} {_fmt(b['reviewers_share']):>8}{b['qc']:>5} {_fmt(b['qc_share']):>8}")
    return 0


def cmd_serve(args) -> int:
    import uvicorn

    from handedit.dashboards.audit_app import make_app

    try:
        app = make_app(args.run, args.name)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"audit '{args.name}': review at http://{args.host}:{args.port}/ (Ctrl-C stops; verdicts are saved as given)",
          flush=True)
    uvicorn.run(app, host=args.host, port=args.port, log_level="warning")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("audit", help="sample pairs, import reviewers' verdicts, report how often they agree with QC")
    sub = p.add_subparsers(dest="audit_cmd", required=True)
    s = sub.add_parser("sample", help="freeze a stratified sample of kept and rejected pairs in the run")
    s.add_argument("run", help="run folder (or .zarr store)")
    s.add_argument("--n", type=int, required=True, help="items to sample")
    s.add_argument("--name", default="audit", help="the audit's name (default: audit)")
    s.add_argument("--kept-share", type=float, default=0.5, help="share of kept pairs in the sample (default 0.5)")
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=cmd_sample)
    i = sub.add_parser("import", help="add verdicts made elsewhere: JSON Lines, one object per item")
    i.add_argument("run")
    i.add_argument("--name", default="audit")
    i.add_argument("file")
    i.set_defaults(func=cmd_import)
    r = sub.add_parser("report", help="precision of QC's kept pairs (Wilson 95 %), agreement, failure breakdown")
    r.add_argument("run")
    r.add_argument("--name", default="audit")
    r.add_argument("--json", action="store_true", help="one JSON object (schema in the README)")
    r.set_defaults(func=cmd_report)
    v = sub.add_parser("serve", help="the review page: keep / reject with a primary cause, by keyboard or mouse")
    v.add_argument("run")
    v.add_argument("--name", default="audit")
    v.add_argument("--port", type=int, default=8790)
    v.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only)")
    v.set_defaults(func=cmd_serve)


__all__ = ["register"]

