"""The ``handedit`` command.

    handedit curate --demo --out runs/demo        synthetic clips, local Dask cluster
    handedit curate --video clip.mp4 [--keypoints kp.npz] --out DIR
    handedit curate --source egodex --root DIR [--task T] [--max-clips N] [--frames A:B] --out DIR
    handedit curate --config run.yaml              a full CurateConfig (deployments use this)
    handedit ledger DIR                            the rejection ledger as a table
    handedit status DIR                            frames per stage and status
    handedit dashboard DIR                         the release/QA page (HTML)

It lives beside the flows (not in ``handedit/``) because it builds Prefect runs; the
domain library stays free of Prefect.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path



def prefect_defaults() -> None:
    """No telemetry; INFO logs reach the Prefect UI (counts, links, the verdict) while the
    terminal shows warnings and errors only, unless the user asked otherwise."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "INFO")
    os.environ.setdefault("PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL", "WARNING")
    # Without PREFECT_API_URL a temporary local API is started; its default 20 s start-up
    # budget is too short on a loaded 2-core machine.
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "180")
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")


def store_path(out: str | Path) -> str:
    """``--out DIR`` names a run folder (or URL); the store is DIR/handedit.zarr (or DIR itself
    if it ends in .zarr): ``handedit.storage.Location``."""
    from handedit.storage import Location

    return Location(out).store_url


def _build_config(args: argparse.Namespace):
    from handedit.flows.config import ClusterConfig, CurateConfig
    from handedit.sources import VideoSpec
    from handedit.sources.synthetic import make_clip_specs

    if args.config:
        from handedit.flows.curate import load_config

        config = load_config(args.config, args.cluster, args.out)
        update = {**({"take_over": True} if args.take_over else {}),
                  **({"fail_below_kept": args.fail_below_kept} if args.fail_below_kept is not None else {})}
        return config.model_copy(update=update) if update else config
    if not args.out:
        raise SystemExit("handedit curate: --out DIR is required (or --config FILE with an 'out' field)")
    clips: list = []
    sources: list = []
    resize = _size(args.resize) if args.resize else None
    window = ":" in str(args.frames)
    if args.demo:
        if args.clips < 1:
            raise SystemExit(f"handedit curate: --clips {args.clips}: give 1 or more synthetic clips")
        n = 48 if window else _count(args.frames)
        clips += make_clip_specs(args.clips, seed=args.seed, n_frames=n, width=args.width, height=args.height)
    for video in args.video or []:
        clips.append(VideoSpec(path=Path(video), keypoints_path=Path(args.keypoints) if args.keypoints else None,
                               max_frames=args.max_frames, resize=resize, hfov_deg=args.fov,
                               intrinsics=_intrinsics(args.intrinsics) if args.intrinsics else None))
    if args.source:
        from handedit.sources import TREES

        if not args.root:
            raise SystemExit(f"handedit curate: --source {args.source} needs --root DIR (the dataset's top folder)")
        tree = TREES[args.source]
        extra = {"mano_dir": Path(args.mano_dir)} if args.mano_dir and "mano_dir" in tree.model_fields else {}
        if args.mano_dir and not extra:
            raise SystemExit(f"handedit curate: --source {args.source} does not use MANO; drop --mano-dir")
        sources.append(tree(root=Path(args.root), tasks=args.task or [], max_clips=args.max_clips,
                            frames=_window(args.frames) if window else None, resize=resize, **extra))
    if not clips and not sources:
        raise SystemExit("handedit curate: give --demo, --video FILE, --source NAME --root DIR or --config FILE")
    cluster = ClusterConfig(address=args.address, n_workers=args.workers)
    if args.cluster:
        import yaml

        spec = yaml.safe_load(Path(args.cluster).read_text()) or {}
        cluster = ClusterConfig.model_validate(spec.get("cluster", spec))
    extra = {"qc": {"keep": args.keep}} if args.keep else {}
    if args.fail_below_kept is not None:
        extra["fail_below_kept"] = args.fail_below_kept
    if args.estimate_hands or args.hand_pose_model:
        extra["estimate_hands"] = {**({"mode": args.estimate_hands} if args.estimate_hands else {}),
                                   **({"model_path": args.hand_pose_model} if args.hand_pose_model else {})}
    return CurateConfig(out=args.out, clips=clips, sources=sources, embodiments=args.embodiment or ["allegro"],
                        frames_per_chunk=args.frames_per_chunk, shard_size=args.shard_size, take_over=args.take_over,
                        cluster=cluster, **extra)


def _count(text: str) -> int:
    try:
        n = int(text)
        assert n >= 1
    except (ValueError, AssertionError):
        raise SystemExit(f"handedit curate: --frames {text!r}: use a frame count N >= 1 or a window A:B") from None
    return n


def _window(text: str) -> tuple[int, int]:
    from handedit.sources.egodex import parse_frames

    try:
        return parse_frames(text)
    except ValueError as exc:
        raise SystemExit(f"handedit curate: {exc}") from None


def _intrinsics(text: str) -> tuple[float, float, float, float]:
    try:
        fx, fy, cx, cy = (float(v) for v in text.split(","))
    except ValueError:
        raise SystemExit(f"handedit curate: --intrinsics {text!r}: use FX,FY,CX,CY in pixels of the file, "
                         f"e.g. 910,910,640,360") from None
    return fx, fy, cx, cy


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SystemExit(f"handedit curate: --resize {text!r}: use WIDTHxHEIGHT, e.g. 960x540") from None
    return w, h


def cmd_curate(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from handedit.flows.curate import run_curate

    from handedit.flows.config import CurateConfig, explain

    try:
        config = _build_config(args)
    except ValidationError as exc:  # one line per bad value, named by where it is (no pydantic dump)
        print(f"handedit curate: invalid configuration ({exc.title}):\n{explain(exc, CurateConfig)}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"handedit curate: invalid configuration:\n{exc}", file=sys.stderr)
        return 2
    what = " + ".join([*([f"{len(config.clips)} clip(s)"] if config.clips else []),
                       *(f"the {t.kind} tree {t.root}" for t in config.sources)])
    print(f"curating {what} x {len(config.embodiments)} embodiment(s) into {config.out} "
          f"(shards of {config.shard_size} clips)")
    c = config.cluster
    where = c.address or (f"a {c.cluster_class.rsplit('.', 1)[-1]} started for the run "
                          + (f"(adaptive: {c.adapt})" if c.adapt else f"({c.n_workers} jobs)") if c.cluster_class
                          else f"a local Dask cluster ({c.n_workers} worker processes)")
    print(f"running on {where}; the Dask dashboard link follows when the cluster is up")
    from handedit.flows.config import PreflightError
    from handedit.storage import StoreError

    try:
        summary = run_curate(config, progress=not args.no_progress)
    except (StoreError, PreflightError) as exc:  # refusals before the run, a store that cannot be used
        print(f"handedit curate: {exc}", file=sys.stderr)
        return 2
    print_summary(summary)
    if summary.get("clips", {}).get("curated", 1) == 0:
        why = "see the errors above" if summary.get("errors") else "no clip could be read (see the reasons above)"
        print(f"handedit curate: nothing was curated: {why}", file=sys.stderr)
        return 1
    result = summary.get("outcome") or {}
    if result.get("failed"):
        print("handedit curate: the run failed: " + "; ".join(result["reasons"]), file=sys.stderr)
        return 1
    return 0


def print_summary(summary: dict) -> None:
    print(f"\nstore:          {summary['store']}")
    links = summary.get("links", {})
    print(f"dask dashboard: {summary['dashboard'] or '(not available)'}")
    if (links.get("Dask dashboard") or {}).get("note"):
        print(f"                ({links['Dask dashboard']['note']})")
    print(f"prefect run:    {summary.get('prefect_run') or '(no Prefect UI: set PREFECT_API_URL to a server)'}")
    if (links.get("Prefect run") or {}).get("note"):
        print(f"                ({links['Prefect run']['note']})")
    sh = summary.get("shards", {})
    print(f"shards:         {sh.get('ran', 0)} ran, {sh.get('skipped', 0)} complete (skipped), {sh.get('held', 0)} held by "
          f"another driver, {sh.get('incomplete', 0)} left incomplete (re-run to retry)")
    for shard, who in summary.get("held_by_others", {}).items():
        print(f"  shard {shard} is held by {who}: run again later, or --take-over once that driver is gone")
    if summary["stages"]:
        print("\nchunks per stage (ran / skipped / failed):")
        for stage, c in summary["stages"].items():
            print(f"  {stage:<20} {c['ran']:>5} {c['skipped']:>8} {c['failed']:>7}")
    elif not summary.get("shards", {}).get("ran"):
        print("\nno chunk ran: every shard was complete for this configuration")
    print("\nframes per stage and status:")
    for row in summary["status"]:
        print(f"  {row['stage']:<20} {row['status']:<18} {row['frames']:>6}")
    rejections = summary["rejections"]
    print(f"\nrejections: {sum(rejections.values())}" + ("" if rejections else " (none)"))
    for key, n in sorted(rejections.items()):
        print(f"  {key:<40} {n:>6}")
    for clip, err in summary.get("clip_errors", {}).items():
        print(f"  clip {clip} not ingested: {err}")
    if summary.get("recomputed"):
        print("\nrecomputed (an input changed; chunks):")
        for why, n in sorted(summary["recomputed"].items()):
            print(f"  {why:<60} {n:>5}")
    if summary.get("recovered"):
        print(f"\nrecomputed {len(summary['recovered'])} chunk(s) whose stored data was missing or corrupt (first 10):")
        for note in summary["recovered"][:10]:
            print(f"  {note}")
    if summary["errors"]:
        print("\nstage errors (first 10):")
        for e in summary["errors"][:10]:
            print(f"  {e}")
    run_dir = summary["store"].rsplit("/", 1)[0]
    print(f"\nledger: handedit ledger {run_dir}    QA page: handedit dashboard {run_dir}")


def _open(args: argparse.Namespace):
    from handedit.storage import open_store

    return open_store(args.store)  # a StoreError is one message (``main``)


def cmd_ledger(args: argparse.Namespace) -> int:
    from handedit.storage import read_ledger

    ledger = read_ledger(_open(args))
    if args.csv:
        ledger.to_csv(sys.stdout, index=False)
    elif ledger.empty:
        print("no rejections")
    else:
        print(ledger.to_string(index=False, max_colwidth=80))
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    from handedit.storage import status_counts

    root = _open(args)
    if args.json:
        from handedit.storage.summary import run_summary

        print(json.dumps(run_summary(root, store_path(args.store)), indent=1))
        return 0
    print(status_counts(root, by_side=True).fillna("-").to_string(index=False))
    return 0


def cmd_dashboard(args: argparse.Namespace) -> int:
    from handedit.dashboards.release import write_page

    from handedit.storage import Location

    if args.release:
        from handedit.dashboards.release_page import write_release_page

        print(f"wrote {write_release_page(args.release, args.out)}")
        return 0
    if not args.store:
        raise SystemExit("handedit dashboard: give a run folder, or --release RELEASES/VERSION")

    loc = Location(args.store)
    if not args.out and not loc.is_local:
        raise SystemExit("handedit dashboard: the run is on object storage; pass --out PAGE.html (a local file)")
    out = Path(args.out) if args.out else Path(loc.root) / "qa.html"
    print(f"wrote {write_page(_open(args), out, title=loc.url)}")
    return 0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="handedit",
        description="Egocentric human-hand video -> paired robot-hand images (curation), and the HandEdit benchmark.",
    )
    sub = p.add_subparsers(dest="command", required=True)

    c = sub.add_parser("curate", help="run the curation flow (segment -> ... -> harmonize -> QC)")
    c.add_argument("--demo", action="store_true", help="synthetic clips with ground truth (the embedded default)")
    c.add_argument("--out", help="run folder or URL, e.g. runs/demo or s3://bucket/prefix (the store is OUT/handedit.zarr)")
    c.add_argument("--config", help="YAML CurateConfig")
    c.add_argument("--video", action="append", help="a video file (repeatable)")
    c.add_argument("--keypoints", help="keypoints .npy/.npz for --video (MANO order, camera frame, metres)")
    c.add_argument("--max-frames", type=int, default=None)
    c.add_argument("--fov", type=float, help="--video without calibration: its horizontal field of view in degrees "
                   "(default: a 70 degree guess)")
    c.add_argument("--intrinsics", metavar="FX,FY,CX,CY", help="--video: its calibrated intrinsics (pixels of the file)")
    c.add_argument("--estimate-hands", choices=["auto", "always", "never"], help="estimate the hands' 3-D keypoints "
                   "from the pixels: auto (default) for sources without keypoints, always, or never")
    c.add_argument("--hand-pose-model", help="ONNX hand-pose plug-in for estimate_hands (handedit.models.hand_pose)")
    from handedit.sources import TREES

    c.add_argument("--source", choices=sorted(TREES), help="a dataset tree (with --root)")
    c.add_argument("--root", help="the dataset's top folder, e.g. ../shared/data/egodex")
    c.add_argument("--task", action="append", help="only this group of the tree (repeatable): EgoDex task folder, ARCTIC or HO-Cap "
                   "subject, HOI4D camera (ZY...), OakInk2 sequence token")
    c.add_argument("--mano-dir", help="MANO-based sources: the folder holding your MANO_RIGHT.pkl and MANO_LEFT.pkl "
                   "(default $HANDEDIT_MANO_DIR; register at https://mano.is.tue.mpg.de)")
    c.add_argument("--max-clips", type=int, default=None, help="at most this many clips of the tree")
    c.add_argument("--resize", help="working resolution WIDTHxHEIGHT (intrinsics scaled), e.g. 960x540")
    c.add_argument("--keep", choices=["all_hands", "per_hand"], help="bimanual frames: keep only if every hand was "
                   "replaced (all_hands, default) or any (per_hand)")
    c.add_argument("--embodiment", action="append", help="embodiment id (repeatable; default allegro)")
    c.add_argument("--clips", type=int, default=2, help="number of synthetic clips with --demo")
    c.add_argument("--frames", default="48", metavar="N|A:B",
                   help="N: frames per synthetic clip (--demo, default 48); A:B: a window of every clip of --source, "
                        "frames A (inclusive) to B (exclusive)")
    c.add_argument("--width", type=int, default=640)
    c.add_argument("--height", type=int, default=480)
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--frames-per-chunk", type=int, default=16, help="frames per Zarr chunk (fixed per store)")
    c.add_argument("--shard-size", type=int, default=64, help="clips per shard (one flow run and one claim each)")
    c.add_argument("--take-over", action="store_true", help="claim shards another driver holds (once it is gone)")
    c.add_argument("--workers", type=int, default=2, help="local Dask worker processes")
    c.add_argument("--address", help="Dask scheduler address to run on an existing cluster")
    c.add_argument("--cluster", help="cluster spec YAML (deploy/cluster/*.yaml)")
    c.add_argument("--fail-below-kept", type=float, metavar="SHARE",
                   help="exit 1 (Prefect: Failed) when the kept share of frame x embodiment pairs is at or below SHARE "
                        "(default 0: when nothing is kept); failed chunks always fail the run")
    c.add_argument("--no-progress", action="store_true")
    c.set_defaults(func=cmd_curate)

    lg = sub.add_parser("ledger", help="print the rejection ledger of a store")
    lg.add_argument("store")
    lg.add_argument("--csv", action="store_true")
    lg.set_defaults(func=cmd_ledger)

    st = sub.add_parser("status", help="frames per stage and status")
    st.add_argument("store")
    st.add_argument("--json", action="store_true", help="the run as one JSON object (schema: handedit.storage.summary)")
    st.set_defaults(func=cmd_status)

    db = sub.add_parser("dashboard", help="write the release/QA page (HTML) of a store")
    db.add_argument("store", nargs="?")
    db.add_argument("--release", help="the page of a published release instead, e.g. runs/releases/v0002")
    db.add_argument("--out", help="default: STORE_DIR/qa.html (or RELEASE/qa.html)")
    db.set_defaults(func=cmd_dashboard)

    from handedit.flows.commands import register_all

    register_all(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    from handedit.storage import StoreError

    args = parser().parse_args(argv)
    prefect_defaults()
    from handedit.secrets import install_log_filter

    install_log_filter()  # before any record is made, so every handler (Prefect's too) gets them redacted
    try:
        return int(args.func(args) or 0)
    except StoreError as exc:  # a damaged or unusable store, named down to the file: one message
        print(f"handedit {args.command}: {exc}", file=sys.stderr)
        return 2
    except json.JSONDecodeError as exc:  # a group's or array's zarr.json below the root
        print(f"handedit {args.command}: a zarr.json in the store is damaged ({exc}); run `handedit verify DIR` to "
              f"find it and `handedit verify DIR --repair` to rebuild it on the next curate", file=sys.stderr)
        return 2
    except OSError as exc:  # disk full, read-only, permissions: which file, and what to do
        import errno

        what = f" ({exc.filename})" if exc.filename else " (the run's --out)"
        fix = ("free space there and run the same command again (committed chunks are kept)"
               if exc.errno == errno.ENOSPC else "check the path and its permissions, then run again")
        print(f"handedit {args.command}: {exc.strerror or exc}{what}: {fix}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
