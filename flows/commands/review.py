"""``handedit review``: the operator's sequence-level choice of a virtual base (hand-arm track).

    handedit review DIR                                   every hand-arm sequence: top-3, choice, policy
    handedit review DIR --clip C --embodiment E           its 27 candidates' scores
    handedit review DIR --clip C --embodiment E --previews OUT   the top-3's replay videos and stills
    handedit review DIR --clip C --embodiment E --choose K       pick top-3 candidate K
    handedit review DIR --clip C --embodiment E --drop           no plausible candidate: drop the sequence

Each hand of a bimanual clip has its own arm and base: ``--side left|right`` picks one
(default: the clip's only hand).

The default policy (``auto_top1``) already picked the best-ranked candidate and says so
in provenance (``selected_by``). A decision is stored in the sequence's retarget unit
(its ``reviews`` attribute, per hand) and that unit's records are cleared, so the next
``handedit curate`` run re-solves that sequence with the chosen base (or rejects it,
REVIEW_DROPPED) and re-runs only what reads it. Run it while no curate run writes to the
store.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from handedit.storage.layout import REVIEWS_ATTR


def _summaries(root, clip: str | None = None, emb: str | None = None,
               side: str | None = None) -> dict[tuple[str, str, str], dict]:
    from handedit.storage import Unit, read_records
    from handedit.storage.summary import curated_clips

    out = {}
    for c in ([clip] if clip else curated_clips(root)):
        group = f"clips/{c}/embodiments"
        for e in (sorted(root[group].group_keys()) if group in root else []):
            if emb and e != emb:
                continue
            recs = read_records(root, Unit("retarget", c, embodiment=e))
            per_side = next((r.extra.get("virtual_base") for r in recs.values() if r.extra.get("virtual_base")), None) or {}
            for s, vb in sorted(per_side.items()):
                if side is None or s == side:
                    out[(c, e, s)] = vb
    return out


def _fmt(c: dict) -> str:
    ee = "-" if c["ee_error_mm"] is None else f"{c['ee_error_mm']:.1f}"
    return (f"  #{c['index']:>2} lat {c['lateral']:+.2f} fwd {c['forward']:+.2f} yaw {c['yaw_deg']:+.0f}  "
            f"{c['reason_name']:<14} crit {c['critical_success']:.2f} reach {c['reachability']:.2f} ee {ee} mm "
            f"margin {c['joint_margin']:.2f} step {c['continuity']:.2f} rank {c['rank']}  {c['detail']}")


def cmd_review(args: argparse.Namespace) -> int:
    from handedit.flows.cli import store_path
    from handedit.storage import Unit, open_store
    from handedit.storage.store import now_iso, set_attrs

    from handedit.storage import Location

    path = store_path(args.dir)
    if not Location(args.dir).store_exists():
        print(f"error: no store at {path}; run `handedit curate --out {args.dir}` first", file=sys.stderr)
        return 2
    deciding = args.choose is not None or args.drop
    if (deciding or args.previews) and not (args.clip and args.embodiment):
        print("error: --choose/--drop/--previews need --clip and --embodiment", file=sys.stderr)
        return 2
    root = open_store(args.dir, mode="r+" if deciding else "r")
    found = _summaries(root, args.clip, args.embodiment, args.side)
    if (deciding or args.previews) and len(found) > 1:
        sides = sorted({k[2] for k in found})
        print(f"error: {args.clip}/{args.embodiment} has one arm per hand ({', '.join(sides)}); pass --side", file=sys.stderr)
        return 2
    def reviews_of(c: str, e: str) -> dict:
        unit = Unit("retarget", c, embodiment=e)
        return dict(root[unit.path].attrs.get(REVIEWS_ATTR) or {}) if unit.path in root else {}

    if not found:
        print(f"error: no hand-arm sequence with virtual-base candidates in {path}"
              + (f" for {args.clip}/{args.embodiment}" if args.clip else ""), file=sys.stderr)
        return 2
    if not deciding:
        for (c, e, sd), vb in found.items():
            top = vb["ranking"][:3]
            review = reviews_of(c, e).get(sd)
            print(f"{c} / {e} / {sd}: chosen {vb['chosen']} ({vb['selected_by']}), top-3 {top}, L_r {vb['reach_m']:.3f} m"
                  + (f"  review: {review}" if review else "")
                  + (f"  REJECTED: {vb['detail']}" if vb["chosen"] is None else ""))
            cands = vb["candidates"] if args.clip else [vb["candidates"][i] for i in top]
            for cand in cands:
                print(_fmt(cand))
            for note in vb.get("notes", []):
                print(f"  note: {note}")
        if args.previews:
            return _write_previews(root, args, found)
        return 0
    (c, e, sd), vb = next(iter(found.items()))
    if args.drop:
        choice = -1
    else:
        if args.choose not in vb["ranking"][:3]:
            print(f"error: candidate {args.choose} is not one of the top-3 valid candidates {vb['ranking'][:3]} "
                  f"of {c}/{e}/{sd}", file=sys.stderr)
            return 2
        choice = args.choose
    reviews = reviews_of(c, e)
    reviews[sd] = {"choice": choice, "by": "operator", "at": now_iso()}
    # the decisions are an input of the sequence's retarget key: the next curate run re-solves it
    set_attrs(root, Unit("retarget", c, embodiment=e).path, {REVIEWS_ATTR: reviews})
    from handedit.storage.shards import invalidate

    invalidate(Location(args.dir), [c])
    print(f"{c}/{e}/{sd}: {'dropped' if choice == -1 else f'candidate {choice}'}; re-run `handedit curate` to apply")
    return 0


def _write_previews(root, args, found) -> int:
    """For each top candidate, its replay video (``*_cand<K>.mp4``: the egocentric render over the
    source frame beside the third-person render, every stored frame) and PNG stills of the first,
    middle and last stored frame (egocentric over the source; third-person as rendered)."""
    import cv2
    import numpy as np

    from handedit.retarget.preview import preview_frames, replay, write_video
    from handedit.storage import Unit
    from handedit.storage.layout import preview_path
    from handedit.storage.store import read_array, read_previews

    (c, e, sd), vb = next(iter(found.items()))
    unit = Unit("retarget", c, embodiment=e)
    if preview_path(unit, sd) not in root:
        print(f"error: this run stored no previews for {c}/{e}/{sd}: under `review: auto_top1` they are rendered only "
              "when asked for. Set `retarget: {virtual_base: {previews: true}}` in the run config (or `review: manual`) "
              "and re-run `handedit curate` (its retarget stage runs again).", file=sys.stderr)
        return 2
    pv = read_previews(root, unit, sd)
    if len(pv["candidates"]) == 0:
        print(f"error: no previews stored for {c}/{e}/{sd} (no valid candidate, or not curated yet)", file=sys.stderr)
        return 2
    out = Path(args.previews)
    out.mkdir(parents=True, exist_ok=True)
    frames_rgb = root[Unit("ingest", c).path]["frames"]
    source = np.stack([read_array(frames_rgb, f) for f in pv["frames"]])
    stills = preview_frames(len(pv["frames"]))  # positions among the stored frames
    for i, cand in enumerate(pv["candidates"]):
        views = replay(source, pv["ego"][i], pv["third"][i])
        write_video(out / f"{c}_{e}_{sd}_cand{cand}.mp4", views, args.fps)
        w = source.shape[2]
        for j in stills:
            f = pv["frames"][j]
            cv2.imwrite(str(out / f"{c}_{e}_{sd}_cand{cand}_ego_f{f:05d}.png"), cv2.cvtColor(views[j, :, :w], cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(out / f"{c}_{e}_{sd}_cand{cand}_third_f{f:05d}.png"), cv2.cvtColor(pv["third"][i, j], cv2.COLOR_RGBA2BGRA))
    kind = "replay" if len(pv["frames"]) > 3 else "first, middle and last frame (`review: manual` stores a replay)"
    print(f"previews of candidates {[int(k) for k in pv['candidates']]}, {len(pv['frames'])} frames ({kind}) -> {out}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("review", help="choose (or drop) the virtual base of hand-arm sequences")
    p.add_argument("dir", help="run folder (or .zarr store)")
    p.add_argument("--clip")
    p.add_argument("--embodiment")
    p.add_argument("--side", choices=["left", "right"], help="which hand's arm (bimanual clips)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--choose", type=int, help="candidate index among the top-3")
    g.add_argument("--drop", action="store_true", help="no plausible candidate: exclude the sequence")
    p.add_argument("--previews", help="folder for the top-3's replay videos (egocentric over the source | third-person) "
                   "and PNG stills")
    p.add_argument("--fps", type=float, default=6.0, help="frame rate of the replay videos (default 6)")
    p.set_defaults(func=cmd_review)
