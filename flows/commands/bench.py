"""``handedit bench``: the HandEdit benchmark.

    handedit bench build --store RUN/handedit.zarr --out BENCH [--bank bank.zarr] [-n 1000]
    handedit bench run --bench BENCH --editor http --name gpt-image-2 --model gpt-image-2 [--base-url URL]
    handedit bench run --bench BENCH --editor cmd --name qwen --command 'python edit.py {src} {ref} {prompt_file} {out}'
    handedit bench run --bench BENCH --editor cmd --name Pseudo-GT --command 'cp {gt} {out}'   (the paper's grey reference row)
    handedit bench evaluate --bench BENCH --name gpt-image-2 [--models DIR] [--judge-url URL]
    handedit bench evaluate --manifest toolkit.jsonl --out RESULTS --name X   (toolkit manifests)
    handedit bench export --bench BENCH --name X --out toolkit.jsonl
    handedit bench report --bench BENCH
    handedit bench rate --bench BENCH [--port P]                        (the paper's blinded rating page)
    handedit bench human-report --bench BENCH [--ratings ratings.jsonl] (the paper's human evaluation)

Keys come from the environment (HANDEDIT_EDITOR_API_KEY, HANDEDIT_VLM_API_KEY, or
OPENAI_API_KEY), never from the command line.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path


def cmd_build(args: argparse.Namespace) -> int:
    from handedit.flows.benchmark import build_testset
    from handedit.storage import StoreError

    if bool(args.store) == bool(args.release):
        print("handedit bench build: give --store RUN or --release RELEASES/VERSION", file=sys.stderr)
        return 2
    refs = None
    if args.references == "toolkit":
        refs = args.reference_dir or os.environ.get("HANDEDIT_TOOLKIT_REFERENCES")
        if not refs:
            print("handedit bench build: --references toolkit needs --reference-dir DIR (the toolkit's reference/ "
                  "folder, e.g. ../shared/benchmark/handedit-toolkit/reference) or $HANDEDIT_TOOLKIT_REFERENCES",
                  file=sys.stderr)
            return 2
    try:
        if args.release:
            from handedit.flows.benchmark import build_testset_from_release

            meta = build_testset_from_release(args.release, args.out, args.n, args.embodiment, args.bank, args.seed,
                                              pseudo_gt=args.pseudo_gt, toolkit_references=refs)
        else:
            meta = build_testset(args.store, args.out, args.n, args.embodiment, args.bank, args.seed,
                                 pseudo_gt=args.pseudo_gt, toolkit_references=refs)
    except (StoreError, ValueError, FileNotFoundError) as exc:
        print(f"handedit bench build: {exc}", file=sys.stderr)
        return 2
    for scope, embs in ((s, e) for s, e in meta["tracks"].items() if e):
        n = sum(1 for i in meta["items"] if i["scope"] == scope)
        print(f"{scope}: {n} items over {len(embs)} embodiment(s) {embs}")
    print(f"test set: {args.out} (manifest {Path(args.out) / 'manifest.jsonl'})")
    return 0


def _editor(args: argparse.Namespace):
    from handedit.benchmark.editors import CommandEditor, HttpEditorConfig, HttpImageEditor

    if args.editor == "http":
        return HttpImageEditor(HttpEditorConfig.from_env(base_url=args.base_url, model=args.model, timeout_s=args.timeout))
    if not args.command:
        raise SystemExit("handedit bench run --editor cmd needs --command TEMPLATE (with {src} {ref} {prompt_file} {out})")
    return CommandEditor(args.command, model=args.model or args.name)


def cmd_run(args: argparse.Namespace) -> int:
    from handedit.flows.benchmark import run_editor
    from handedit.benchmark.editors import EditorError
    from handedit.storage.benchmark import BenchIOError

    try:
        summary = run_editor(args.bench, args.name, _editor(args), concurrency=args.concurrency,
                             max_tries=args.tries, limit=args.limit, price=args.price_per_image)
    except (EditorError, BenchIOError) as exc:
        print(f"handedit bench run: {exc}", file=sys.stderr)
        return 2
    cost = "unknown price" if summary.cost_usd is None else f"${summary.cost_usd:.2f} accounted"
    print(f"{summary.editor} ({summary.model}): ran {summary.ran}, ok {summary.ok}, failed {summary.failed}, "
          f"skipped (done before) {summary.skipped}; {cost}; {summary.seconds:.1f}s")
    for f in summary.failures[:10]:
        print(f"  {f['id']}: {f['error']}")
    if summary.wrong_size:
        print(f"{len(summary.wrong_size)} prediction(s) not at the source's size (flagged wrong_size in records.jsonl; "
              f"scoring resizes them):")
        for w in summary.wrong_size[:10]:
            print(f"  {w['id']}: {w['size']} for a {w['source']} source")
    return 1 if summary.failed else 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from handedit.flows.benchmark import export_manifest
    from handedit.flows.config import ClusterConfig
    from handedit.flows.evaluate import EvaluateConfig, run_evaluate
    from handedit.metrics.vlm import JudgeConfig
    from handedit.storage.benchmark import BenchDir

    if args.manifest:
        manifest, out = Path(args.manifest), Path(args.out or Path(args.manifest).with_suffix(""))
    elif args.bench:
        bench = BenchDir(Path(args.bench))
        out = bench.results(args.name)
        manifest = export_manifest(args.bench, args.name, out / "manifest.jsonl")
    else:
        raise SystemExit("handedit bench evaluate: give --bench DIR (with --name) or --manifest FILE")
    cache = (Path(args.bench) / "vlm_cache") if args.bench else out / "vlm_cache"
    judge = JudgeConfig.from_env(base_url=args.judge_url, model=args.judge_model, cache_dir=cache,
                                 protocol=args.judge_protocol or args.protocol)
    relative = args.paths_relative_to or ("cwd" if args.manifest else "manifest")
    cfg = EvaluateConfig(manifest=manifest, out=out, editor=args.name, model_dir=args.models or os.environ.get("HANDEDIT_MODEL_DIR"),
                         paths_relative_to=relative,
                         judge=judge, chunk_size=args.chunk_size, protocol=args.protocol, roi_dilate_px=args.roi_dilate_px,
                         cluster=ClusterConfig(address=args.address, n_workers=args.workers))
    summary = run_evaluate(cfg)
    if cfg.protocol == "toolkit":
        return _print_toolkit(summary, out)
    for scope, t in summary["tracks"].items():
        judged = f", {t['n_judge_failed']} judge failure(s) (no VLM score)" if t.get("n_judge_failed") else ""
        print(f"{scope}: {t['n_scored']}/{t['n_items']} scored{judged}")
        print("  " + json.dumps({k: (round(v, 4) if v is not None else None) for k, v in t["metrics"].items()}))
    if summary["skipped"]:
        print(f"skipped metrics: {', '.join(summary['skipped'])}", file=sys.stderr)
    for e in summary["errors"][:10]:
        print(f"  {e['id']}: {e['error']}", file=sys.stderr)
    for e in summary.get("judge_failures", [])[:10]:
        print(f"  judge failed on {e['id']}: {e['error']}", file=sys.stderr)
    print(f"results: {out}")
    return 0


def _print_toolkit(summary: dict, out: Path) -> int:
    meta = summary["_meta"]
    for key, g in summary.items():
        if key == "_meta":
            continue
        shown = {m: g.get(f"{m}_mean") for m in ("Full-PSNR", "ROI-SSIM", "BG-LPIPS", "Removal", "Fidelity", "Interaction", "VLM")}
        shown.update({m: g.get(m) for m in ("Full-FID", "ROI-FID")})
        print(f"{key or '(no dataset/task)'}: n={g['n']}  " + json.dumps({k: (round(v, 4) if isinstance(v, float) and v == v else None)
                                                                           for k, v in shown.items()}))
    if meta["skipped"]:
        print(f"left empty (encoder or judge missing): {', '.join(meta['skipped'])}", file=sys.stderr)
    for e in meta["errors"][:10]:
        print(f"  {e['id']}: {e['error']}", file=sys.stderr)
    if meta.get("n_judge_failures"):
        print(f"{meta['n_judge_failures']} judge failure(s) (no VLM score):", file=sys.stderr)
    for e in meta.get("judge_failures", [])[:10]:
        print(f"  judge failed on {e['id']}: {e['error']}", file=sys.stderr)
    print(f"results (toolkit protocol): {out}/per_sample.jsonl, summary.json, leaderboard.md")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from handedit.flows.benchmark import export_manifest

    print(export_manifest(args.bench, args.name, args.out, absolute=args.absolute))
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from handedit.flows.benchmark import write_report
    from handedit.storage.benchmark import BenchIOError

    try:
        written = write_report(args.bench, args.name)
    except BenchIOError as exc:
        print(f"handedit bench report: {exc}", file=sys.stderr)
        return 2
    for files in written.values():
        for f in files:
            print(f)
    return 0


def cmd_human_report(args: argparse.Namespace) -> int:
    """Raters' scores (JSON Lines) -> the paper's agreement table, into the bench report."""
    import pandas as pd

    from handedit.benchmark.human_eval import human_report, markdown, parse_rating
    from handedit.flows.benchmark import evaluated_metrics, load_manifest
    from handedit.storage.benchmark import BenchDir, BenchIOError, iter_jsonl, read_ratings, write_json, write_text

    out = BenchDir(Path(args.bench))
    try:
        items, _ = load_manifest(out.manifest)
        tracks = {it.id: it.replacement_scope for it in items}
        editors = {p.name for p in (out.root / "predictions").iterdir() if p.is_dir()} if (out.root / "predictions").is_dir() else set()
        rows, errors = [], []
        for obj in read_ratings(out.root):  # given on `bench rate`'s page, checked there
            rows += parse_rating({k: v for k, v in obj.items() if k != "time"}, tracks, editors)
        for no, obj, err in (iter_jsonl(args.ratings) if args.ratings else ()):
            if err:
                errors.append(err)
                continue
            try:
                rows += parse_rating(obj, tracks, editors)
            except ValueError as exc:
                errors.append(f"{args.ratings}:{no}: {exc}")
    except BenchIOError as exc:
        print(f"handedit bench human-report: {exc}", file=sys.stderr)
        return 2
    if errors:
        print("handedit bench human-report: no rating read:\n  " + "\n  ".join(errors[:20])
              + (f"\n  ... and {len(errors) - 20} more" if len(errors) > 20 else ""), file=sys.stderr)
        return 2
    if not rows:
        print(f"handedit bench human-report: no rating: rate on `handedit bench rate --bench {args.bench}` or give "
              f"--ratings FILE", file=sys.stderr)
        return 2
    ratings = pd.DataFrame(rows)
    # one rater's last scores of an output on an axis count (a re-rating replaces the first)
    ratings = ratings.drop_duplicates(["track", "editor", "item", "rater", "axis"], keep="last")
    rep = human_report(ratings, evaluated_metrics(out.root))
    write_json(out.report / "human.json", rep)
    text = markdown(rep)
    write_text(out.report / "human.md", text)
    print(text, end="")
    print(f"-> {out.report / 'human.json'}, {out.report / 'human.md'} (`handedit bench report` adds it to tables.md)")
    return 0


def cmd_rate(args: argparse.Namespace) -> int:
    import uvicorn

    from handedit.dashboards.rating_app import make_app

    try:
        app = make_app(args.bench, args.seed)
    except ValueError as exc:
        print(f"handedit bench rate: {exc}", file=sys.stderr)
        return 2
    print(f"rate at http://{args.host}:{args.port}/ (Ctrl-C stops; ratings are saved as given)", flush=True)
    uvicorn.run(app, host=args.host, port=args.port, log_level="warning")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("bench", help="the HandEdit benchmark: build, run editors, evaluate, report")
    sub = p.add_subparsers(dest="bench_cmd", required=True)

    b = sub.add_parser("build", help="test set (two tracks) + toolkit manifest from a curated store")
    b.add_argument("--store", help="a curated run")
    b.add_argument("--release", help="a published release instead, e.g. runs/releases/v0002")
    b.add_argument("--out", required=True, help="benchmark folder")
    b.add_argument("--bank", help="reference bank (handedit bank build)")
    b.add_argument("-n", type=int, default=1000, help="source images per track")
    b.add_argument("--embodiment", action="append", help="restrict to these embodiments (repeatable)")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--pseudo-gt", choices=("harmonized", "composite"), default="harmonized",
                   help="harmonized composite (the paper) or unharmonized (the toolkit README's main benchmark)")
    b.add_argument("--references", choices=("bank", "toolkit"), default="bank",
                   help="reference views: the project's rendered bank (--bank) or the authors' 26 toolkit renders")
    b.add_argument("--reference-dir", help="with --references toolkit: the toolkit's reference/ folder")
    b.set_defaults(func=cmd_build)

    r = sub.add_parser("run", help="run an editor over a test set (resumable)")
    r.add_argument("--bench", required=True)
    r.add_argument("--editor", choices=("http", "cmd"), required=True)
    r.add_argument("--name", required=True, help="name of this editor's predictions and report row")
    r.add_argument("--model", help="model id (HTTP: sent to the API; also prices the run)")
    r.add_argument("--base-url", help="OpenAI-compatible base URL (default env HANDEDIT_EDITOR_BASE_URL)")
    r.add_argument("--command", help="command template for --editor cmd")
    r.add_argument("--concurrency", type=int, default=4)
    r.add_argument("--tries", type=int, default=3)
    r.add_argument("--timeout", type=float, default=300.0, help="seconds per HTTP try (--editor http)")
    r.add_argument("--limit", type=int)
    r.add_argument("--price-per-image", type=float, help="USD, when the model is not in the paper's roster")
    r.set_defaults(func=cmd_run)

    e = sub.add_parser("evaluate", help="score predictions with the full metric suite (Prefect flow on Dask)")
    e.add_argument("--bench")
    e.add_argument("--manifest", help="a toolkit JSONL manifest instead of --bench")
    e.add_argument("--out", help="results folder with --manifest")
    e.add_argument("--paths-relative-to", choices=("cwd", "manifest"),
                   help="relative paths of --manifest: the working directory (default, as the toolkit) or its folder")
    e.add_argument("--name", required=True)
    e.add_argument("--models", help="encoder ONNX folder (default env HANDEDIT_MODEL_DIR)")
    e.add_argument("--judge-url", help="OpenAI-compatible chat base URL (default env HANDEDIT_VLM_BASE_URL)")
    e.add_argument("--judge-model", help="default env HANDEDIT_VLM_MODEL or gpt-4o")
    e.add_argument("--chunk-size", type=int, default=16)
    e.add_argument("--roi-dilate-px", type=int, default=0, help="toolkit protocol: grow the ROI by a disc of this radius")
    e.add_argument("--judge-protocol", choices=("toolkit", "paper"),
                   help="the VLM judge's protocol (default: the same as --protocol)")
    e.add_argument("--protocol", choices=("toolkit", "paper"), default="toolkit",
                   help="toolkit (default): every metric as the authors' toolkit computes it, its output files; "
                        "paper: this project's reading of the paper's equations")
    e.add_argument("--address", help="Dask scheduler address")
    e.add_argument("--workers", type=int, default=2)
    e.set_defaults(func=cmd_evaluate)

    x = sub.add_parser("export", help="write the toolkit manifest with an editor's pred_path")
    x.add_argument("--bench", required=True)
    x.add_argument("--name")
    x.add_argument("--out", required=True)
    x.add_argument("--absolute", action="store_true", help="absolute paths (what the toolkit's builder writes)")
    x.set_defaults(func=cmd_export)

    rp = sub.add_parser("report", help="per-track tables (md, tex, csv) and radar charts")
    rp.add_argument("--bench", required=True)
    rp.add_argument("--name", action="append", help="editors to include (default: all evaluated)")
    rp.set_defaults(func=cmd_report)
    hr = sub.add_parser("human-report", help="the paper's human evaluation: raters' agreement and metric-human kappa")
    hr.add_argument("--bench", required=True)
    hr.add_argument("--ratings", help='ratings made elsewhere, JSON Lines: {"item", "editor", "rater", "target", '
                    '"scene_interaction", "realism"} with scores 1-5 (with those given on `bench rate`)')
    hr.set_defaults(func=cmd_human_report)
    ra = sub.add_parser("rate", help="the paper's blinded rating page: score editors' outputs on three axes")
    ra.add_argument("--bench", required=True)
    ra.add_argument("--port", type=int, default=8791)
    ra.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only)")
    ra.add_argument("--seed", type=int, default=0, help="the fixed shuffle of the outputs")
    ra.set_defaults(func=cmd_rate)
