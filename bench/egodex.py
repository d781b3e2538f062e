"""The shared EgoDex episodes through the curate flow: cost per stage, kept fraction, registration.

    .venv/bin/python bench/egodex.py [--root ../shared/data/egodex] [--frames 0:48 | --full]
        [--resize 960x540] [--embodiment allegro --embodiment xarm_ability] [--workers 2] [--figure out.png]
        [--out runs/egodex]          # keep the run (default: a temporary folder)
    .venv/bin/python bench/egodex.py --store runs/egodex    # measure an existing run (before/after)
    .venv/bin/python bench/egodex.py --roster --frames 0:32 --out runs/roster   # every available embodiment
    .venv/bin/python bench/egodex.py --roster --frames 0:32 --repeats 3 --out runs/roster3   # medians of 3 fresh runs
    .venv/bin/python bench/egodex.py --roster --store runs/roster3/run-1 --store runs/roster3/run-2   # again, from stores

Runs ``handedit curate --source egodex`` on a local 2-worker Dask cluster and prints, from
the chunk provenance records: ms per source frame for each per-clip stage, ms per frame
and embodiment for the others (each task's own wall time, at the working resolution);
the kept fraction per clip x embodiment x hand; the registration offsets (px at 1080p);
and how well the robots cover the human hands they replace (kept frames): the share of a
replaced hand's mask under its robot, and the share left unchanged (still the human).
The hand-arm measures (``arm_report``), from EgoDex's own 3-D arm annotations: the forearm
coverage (the share of the projected forearm capsule, wrist to elbow, 4 cm radius, inside
the hand-arm mask: a sleeve left beside the robot arm scores low), per clip and side,
pixel-weighted over the frames the hand is in view, also at 3 and 2 cm (the forearm's core:
a slim forearm leaves table inside the 4 cm capsule), beside the mask's half-width across the
forearm (``half_widths``: a bare forearm of 3 cm covers about 3/4 of the 4 cm capsule), how far its centre lies from
the annotated axis, and how far its edge lies from the colour edge beside it (a sleeve left out of the mask reads
centimetres there, a mask that follows the arm's visible edge millimetres); the kept hand-arm frames with more than
25 % of a robot outside the human arm's corridor (the hand-arm mask plus the capsule, grown
by 5 % of the image width); composite's two hand-arm screens (frame-sides rejected for OFF_ARM and
for HAND_HIDDEN, a robot arm over where the human hand was seen); and the RESIDUE rejections per clip: restoration's (frames) and
composite's, which judges residue where no robot covers it (frame-sides per embodiment).
Restoration's share of each hole taken from real pixels (``filled_from_video``, weighted by
the hole's area), per clip and scope, over all frames and the first 24 (where the shared
clips' hands hold still). ``--figure`` writes source | masks | restored background | pseudo-GT (two robots) for a few
frames, one sheet per embodiment (``NAME-<embodiment>.png`` when there are several), made
from the run (the EgoDex licence forbids committing it).

``--roster`` curates with every available embodiment and adds each one's ms per frame for
the per-embodiment stages, then, as its last line, the projected CPU-hours for 200M pairs
with the paper's mix (13 hand-only, 13 hand-arm; each track's mean over the embodiments
measured, the per-source stages spread over a source frame's 26 pairs). Task wall times
with one thread per worker stand in for CPU time. Each task's setup (the renderers, IK solvers
and retargeters a worker builds once per embodiment and keeps: ``ChunkRecord.setup_seconds``)
is left out of the per-frame costs and printed apart, with the projection as this bench made it
before (setup paid in every window): at dataset scale a worker builds them once for hundreds of
thousands of frames; a 32-frame window pays them in full. One process that retargeted and rendered
the whole roster (24 embodiments at 960x540) on the shared clips built nothing on a second pass
and held about 5 GB (``bench/setup_cost.py``).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections import defaultdict
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "error")
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "180")

REPO = Path(__file__).resolve().parents[1]
import sys  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/figure.py


def timings(recorded: dict, setup: bool = True) -> dict[tuple[str, str | None], tuple[float, int]]:
    """(stage, embodiment or None) -> (task seconds, frames), from ``record_times``. ``setup=False``:
    without each task's setup (``ChunkRecord.setup_seconds``, ``handedit.setup_meter``), the
    machinery a worker builds once per embodiment and keeps for every later clip."""
    return {k: (secs - (0.0 if setup else built), frames) for k, (secs, frames, built, _) in recorded.items()}


def setup_times(recorded: dict) -> dict[tuple[str, str | None], tuple[float, int]]:
    """(stage, embodiment or None) -> (setup seconds, tasks that built something), from ``record_times``."""
    return {k: (built, n) for k, (_, _, built, n) in recorded.items() if n}


def record_times(root) -> dict[tuple[str, str | None], tuple[float, int, float, int]]:
    """(stage, embodiment or None) -> (task seconds, frames, setup seconds, tasks that built),
    summed over every chunk's provenance record: one pass over the records for every cost below."""
    from handedit.storage.ledger import iter_units
    from handedit.storage.provenance import read_records

    out: dict[tuple[str, str | None], tuple[float, int, float, int]] = defaultdict(lambda: (0.0, 0, 0.0, 0))
    for unit in iter_units(root):
        for rec in read_records(root, unit).values():
            secs, frames, built, n = out[unit.stage, unit.embodiment]
            out[unit.stage, unit.embodiment] = (secs + rec.seconds, frames + rec.stop - rec.start,
                                                built + rec.setup_seconds, n + (rec.setup_seconds > 0.01))
    return dict(out)


def stage_costs(times: dict) -> dict[str, float]:
    """ms per frame (per-clip stages, each scope's frames counted) or per frame and embodiment (the others)."""
    secs, frames = defaultdict(float), defaultdict(int)
    for (stage, _), (s, n) in times.items():
        secs[stage] += s
        frames[stage] += n
    return {s: 1000 * secs[s] / frames[s] for s in secs if frames[s]}


def available_embodiments() -> list[str]:
    from handedit.embodiments import asset_status, list_embodiments

    return [e.id for e in list_embodiments() if asset_status(e)[0]]


def source_costs(times: dict, n_source_frames: int) -> dict[str, float]:
    """stage -> ms per source frame of the per-clip stages, every scope included (restoration
    runs once per scope: the hand scope, and the hand-arm scope when a hand-arm is curated)."""
    secs = defaultdict(float)
    for (stage, emb), (s, _) in times.items():
        if emb is None:
            secs[stage] += s
    return {s: 1000 * v / n_source_frames for s, v in secs.items()} if n_source_frames else {}


def embodiment_costs(times: dict) -> dict[str, dict[str, float]]:
    """embodiment -> stage -> ms per frame (the per-embodiment stages)."""
    out: dict[str, dict[str, float]] = defaultdict(dict)
    for (stage, emb), (s, n) in times.items():
        if emb is not None and n:
            out[emb][stage] = 1000 * s / n
    return dict(out)


# The paper's roster: 13 hand-only and 13 hand-arm embodiments; a pair is one source frame
# edited into one embodiment, so a source frame's shared work is spread over the 26 pairs
ROSTER_MIX = {"hand": 13, "hand_arm": 13}
PAIRS = 200e6


def roster_projection(shared_ms: float, per_embodiment: dict[str, float], tracks: dict[str, str]) -> dict:
    """Cost per pair with the roster's mix: the shared per-source work over the 26 pairs of a
    source frame, plus each track's mean per-embodiment cost (over the embodiments measured)."""
    by_track = {t: [ms for e, ms in per_embodiment.items() if tracks[e] == t] for t in ROSTER_MIX}
    n = sum(ROSTER_MIX.values())
    mean = {t: sum(v) / len(v) for t, v in by_track.items() if v}
    per_pair_ms = shared_ms / n + sum(ROSTER_MIX[t] * mean[t] for t in mean) / sum(ROSTER_MIX[t] for t in mean)
    return {"track_ms": mean, "per_pair_ms": per_pair_ms, "cpu_hours": PAIRS * per_pair_ms / 1000 / 3600}


def roster_costs(root) -> dict:
    """One run's figures for ``print_roster``: ms per source frame of the shared stages and per
    frame x embodiment of the others (setup left out), each stage's setup per build, and the
    projection with and without the setup paid in the run's windows."""
    from handedit.embodiments import get_embodiment
    from handedit.storage import Unit

    n_source = sum(root[Unit("ingest", c).path]["status"].shape[0] for c in root["clips"].group_keys())
    recorded = record_times(root)
    times, with_setup = timings(recorded, setup=False), timings(recorded)
    shared, per = source_costs(times, n_source), embodiment_costs(times)
    stages = [s for s in ("retarget", "render", "composite", "harmonize", "qc") if any(s in v for v in per.values())]
    tracks = {e: get_embodiment(e).track for e in per}
    total = {e: sum(per[e].get(s, 0.0) for s in stages) for e in per}
    whole = {e: sum(v.get(s, 0.0) for s in stages) for e, v in embodiment_costs(with_setup).items()}
    built: dict[str, list[float]] = defaultdict(lambda: [0.0, 0])
    for (stage, _), (secs, n) in setup_times(recorded).items():
        built[stage][0] += secs
        built[stage][1] += n
    return {"shared": shared, "per": per, "stages": stages, "tracks": tracks, "total": total,
            "setup": {s: secs / n for s, (secs, n) in built.items()},
            "proj": roster_projection(sum(shared.values()), total, tracks),
            "paid": roster_projection(sum(source_costs(with_setup, n_source).values()), whole, tracks)}


def print_roster(roots: list) -> None:
    """Per embodiment: ms per frame of each per-embodiment stage, setup apart; the projection's
    last line, at dataset scale (a worker builds each embodiment's renderer and solvers once).
    With several runs (``--repeats``), each figure is the median over the runs and the
    projection is the median of the runs' own, every run's beside it."""
    import numpy as np

    runs = [roster_costs(r) for r in roots]
    first = runs[0]
    stages, tracks = first["stages"], first["tracks"]

    def med(get) -> float:
        vals = [v for v in (get(r) for r in runs) if v is not None]
        return float(np.median(vals)) if vals else float("nan")

    of = f" (median of {len(runs)} runs)" if len(runs) > 1 else ""
    shared = {s: med(lambda r: r["shared"].get(s)) for s in first["shared"]}
    print(f"\nper source frame (shared by every embodiment), ms{of}: " +
          ", ".join(f"{s} {ms:.1f}" for s, ms in shared.items()) + f"; total {med(lambda r: sum(r['shared'].values())):.1f}")
    print(f"\nper frame and embodiment, ms{of}:\n  {'embodiment':<22}{'track':<10}" + "".join(f"{s:>11}" for s in stages)
          + f"{'total':>10}")
    for e in sorted(first["per"], key=lambda e: (tracks[e], e)):
        print(f"  {e:<22}{tracks[e]:<10}" + "".join(f"{med(lambda r: r['per'].get(e, {}).get(s)):>11.1f}" for s in stages)
              + f"{med(lambda r: r['total'].get(e)):>10.1f}")
    print(f"\nsetup, once per worker process and embodiment (renderers, IK solvers, retargeters: left out of the ms per frame "
          f"above), s per build{of}: " + ", ".join(f"{s} {med(lambda r: r['setup'].get(s)):.2f}" for s in first["setup"]))
    def each(key: str) -> str:
        return ", ".join(f"{r[key]['cpu_hours']:,.0f}" for r in runs)

    print(f"with each task's setup paid in the bench's windows instead (how this bench measured before): "
          f"{med(lambda r: r['paid']['per_pair_ms']):.1f} ms per pair, {med(lambda r: r['paid']['cpu_hours']):,.0f} CPU-hours"
          + (f" (runs: {each('paid')})" if len(runs) > 1 else ""))
    print("\nper pair with the roster's mix (13 hand-only, 13 hand-arm; each track's mean over the embodiments "
          f"measured; the shared work over 26 pairs){of}: " +
          ", ".join(f"{t} {med(lambda r: r['proj']['track_ms'].get(t)):.1f} ms" for t in first["proj"]["track_ms"])
          + f"; {med(lambda r: r['proj']['per_pair_ms']):.1f} ms per pair" + (f"; runs: {each('proj')} CPU-hours" if len(runs) > 1 else ""))
    print(f"projected: {med(lambda r: r['proj']['cpu_hours']):,.0f} CPU-hours for 200M pairs")


def coverage(root, clip: str, emb: str) -> tuple[float, float]:
    """(share of replaced hands' mask pixels under their robot, share left unchanged) on kept frames."""
    import numpy as np

    from handedit.reasons import Reason
    from handedit.storage import Unit

    qc = root[Unit("qc", clip, embodiment=emb).path]
    kept = np.flatnonzero(qc["status"][:] == Reason.OK)
    if not kept.size:
        return float("nan"), float("nan")
    hs = qc["hand_status"][:]
    human = root[Unit("segment", clip).path]["hand_mask"]
    comp = root[Unit("composite", clip, embodiment=emb).path]
    src = root[Unit("ingest", clip).path]["frames"]
    under = left = total = 0
    for t in kept:
        robot, img, f, h = comp["robot_mask"][t], comp["image"][t], src[t], human[t]
        for k in np.flatnonzero(hs[t] == Reason.OK):
            m = h[k]
            total += m.sum()
            under += (m & robot[k]).sum()
            left += (m & (np.abs(img.astype(int) - f).max(-1) <= 2)).sum()
    return under / max(total, 1), left / max(total, 1)


# The measure is the 4 cm capsule; the narrower ones are the forearm's core: a slim
# forearm (or an annotated elbow a little beside the visible one) leaves table inside 4 cm.
COVERAGE_RADII_M = (0.04, 0.03, 0.02)
HALF_WIDTH_AT_M = (0.06, 0.08, 0.10, 0.12, 0.14)  # along the forearm from the wrist: past the hand, before the elbow leaves


EDGE_SEARCH_M = (0.015, 0.07)  # a forearm's colour edge is looked for this far out from the mask's cross-section centre
EDGE_WITHIN_M = 0.005  # a mask edge this close to the colour edge follows it


def _step(prof, lo: int) -> int:
    """Where a profile (n,3) from the forearm's axis outward splits best into two colours
    (the largest between-class variance, Otsu's criterion, with the split at >= ``lo``): a
    sleeve's folds and seams are edges too, but not where the arm meets the table."""
    import numpy as np

    n = len(prof)
    c = np.cumsum(prof, axis=0)
    j = np.arange(max(lo, 1), n - 2)
    inner, outer = c[j - 1] / j[:, None], (c[-1] - c[j - 1]) / (n - j)[:, None]
    return int(j[np.argmax(j * (n - j) * ((inner - outer) ** 2).sum(1))])


def half_widths(mask, wrist, elbow, intr, lab=None) -> list[tuple[float, float, float]]:
    """The hand-arm mask's half-width across the forearm (m) a few cm up from the wrist: the
    arm's own radius where the mask follows it, so the coverage at a radius above it reads
    roughly their ratio (a bare forearm of 3 cm cannot fill a 4 cm capsule) rather than a miss;
    with each, how far the mask's cross-section centre lies from the annotated forearm's axis
    (m): an axis beside the visible arm leaves table inside the capsule on one side; and, given
    the frame in Lab (``lab``), how far the mask's edge lies from the colour edge (``_step``)
    at least 1.5 cm out on the same side, looked for out to 7 cm or past the mask's edge (m,
    mean of the sides that end in view): near 0 where the mask follows
    the arm's visible edge (sleeve or skin), whatever the capsule's radius."""
    import cv2
    import numpy as np

    from handedit.camera import project

    h, w = mask.shape
    d = (elbow - wrist) / max(float(np.linalg.norm(elbow - wrist)), 1e-9)
    out = []
    for s in HALF_WIDTH_AT_M:
        p = wrist + s * d
        if p[2] < 0.15:  # too close to the lens for a width
            continue
        (u0, v0), (u1, v1) = project(np.stack([p, p + 0.01 * d]), intr)
        ax = np.array([u1 - u0, v1 - v0]) / max(float(np.hypot(u1 - u0, v1 - v0)), 1e-9)
        n = np.array([-ax[1], ax[0]])
        if not (0 <= u0 < w and 0 <= v0 < h) or not mask[int(v0), int(u0)]:
            continue
        reach, border = [], []
        for sign in (1, -1):  # walk out of the mask on both sides of the axis
            k = 1
            while True:
                u, v = u0 + sign * k * n[0], v0 + sign * k * n[1]
                if not (0 <= u < w and 0 <= v < h) or not mask[int(v), int(u)]:
                    border.append(not (0 <= u < w and 0 <= v < h))
                    break
                k += 1
            reach.append(k - 1)
        edge = any(border)
        m_per_px = p[2] / intr.fx  # the offset only where both sides end inside the view
        gap = float("nan")
        if lab is not None:
            lo, hi = (int(round(x / m_per_px)) for x in EDGE_SEARCH_M)
            gaps = []
            for sign, r, out_of_view in zip((1, -1), reach, border):
                ks = np.arange(0, max(hi, r + lo) + 1)  # past the mask's edge, however wide the sleeve
                us, vs = u0 + sign * ks * n[0], v0 + sign * ks * n[1]
                if out_of_view or us.min() < 0 or vs.min() < 0 or us.max() > w - 1 or vs.max() > h - 1:
                    continue  # the side leaves the view
                prof = cv2.remap(lab, us.astype(np.float32)[None], vs.astype(np.float32)[None], cv2.INTER_LINEAR)[0]
                gaps.append(abs(r - _step(prof, lo)) * m_per_px)
            gap = float(np.mean(gaps)) if gaps else float("nan")
        out.append((sum(reach) / 2 * m_per_px, float("nan") if edge else abs(reach[0] - reach[1]) / 2 * m_per_px, gap))
    return out


def arm_report(root) -> dict:
    """Forearm coverage per clip x side, off-arm kept frames per clip x hand-arm embodiment,
    RESIDUE rejections per clip, and the share of each restored hole taken from real pixels
    (see the module doc)."""
    import cv2
    import numpy as np

    from handedit.camera import Intrinsics
    from handedit.reasons import Reason
    from handedit.embodiments.roster import get_embodiment
    from handedit.storage import Unit
    from handedit.storage.layout import clip_path
    from handedit.vision.arm import coverage, forearm_capsule, limbs, off_arm_shares

    out = {"coverage": {}, "off_arm": {}, "screens": {}, "residue": {}, "residue_composite": {}, "from_video": {}}
    for c in sorted(root["clips"].group_keys()):
        for scope in ("hand", "hand_arm"):  # how much of each hole real pixels restored (the rest is inpainted)
            rb = Unit("restore_background", c, scope=scope)
            if rb.path in root and "hole" in root[rb.path]:
                hole = root[rb.path]["hole"][:]
                area = hole.reshape(len(hole), -1).sum(1).astype(float)
                share = root[rb.path]["filled_from_video"][:] * area
                out["from_video"][(c, scope)] = (share.sum() / max(area.sum(), 1.0), share[:24].sum() / max(area[:24].sum(), 1.0))
        ing, reg, seg = (root[Unit(s, c).path] for s in ("ingest", "registration", "segment"))
        if "arm_keypoints" not in reg:
            continue
        intr = Intrinsics(**ing.attrs["info"]["intrinsics"])
        kp, arm, arm_ok = reg["keypoints"][:], reg["arm_keypoints"][:], ing["arm_valid"][:]
        hs, handarm = reg["hand_status"][:], seg["handarm_mask"][:]  # read once: every side and embodiment uses it
        shape = (intr.height, intr.width)
        sides = list(ing.attrs["hands"])
        inside = [defaultdict(int) for _ in sides]
        total = [defaultdict(int) for _ in sides]
        widths: list[list] = [[] for _ in sides]
        measured = (hs == Reason.OK) & arm_ok[:, :, 0]  # (T, sides)
        for t in np.flatnonzero(measured.any(axis=1)):  # each frame read and put in Lab once, for both sides
            lab = cv2.cvtColor(cv2.GaussianBlur(ing["frames"][t], (5, 5), 0), cv2.COLOR_RGB2LAB).astype(np.float32)
            for k in np.flatnonzero(measured[t]):
                widths[k] += half_widths(handarm[t, k], kp[t, k, 0], arm[t, k, 0], intr, lab)
                for r in COVERAGE_RADII_M:
                    cap = forearm_capsule(kp[t, k, 0], arm[t, k, 0], intr, shape, radius_m=r)
                    if coverage(handarm[t, k], cap) is None:
                        break  # the forearm is out of view (judged at the widest radius: the frames stay the same)
                    inside[k][r] += int((handarm[t, k] & cap).sum())
                    total[k][r] += int(cap.sum())
        for k, side in enumerate(sides):
            cov = {r: inside[k][r] / total[k][r] if total[k][r] else float("nan") for r in COVERAGE_RADII_M}
            w = widths[k]
            cov["half_width"] = float(np.median([x[0] for x in w])) if w else float("nan")
            offsets = [x[1] for x in w if np.isfinite(x[1])]
            cov["axis_offset"] = float(np.median(offsets)) if offsets else float("nan")
            gaps = np.array([x[2] for x in w if np.isfinite(x[2])])
            cov["edge_gap"] = float(np.median(gaps)) if len(gaps) else float("nan")
            cov["edge_within"] = float(np.mean(gaps < EDGE_WITHIN_M)) if len(gaps) else float("nan")
            out["coverage"][(c, side)] = cov
        out["residue"][c] = int(sum((root[Unit("restore_background", c, scope=s).path]["status"][:] == Reason.RESIDUE).sum()
                                    for s in ("hand", "hand_arm") if Unit("restore_background", c, scope=s).path in root))
        L = limbs(kp, arm, arm_ok)
        embs = root[f"{clip_path(c)}/embodiments"] if f"{clip_path(c)}/embodiments" in root else None
        for emb in sorted(embs.group_keys()) if embs is not None else []:
            comp = Unit("composite", c, embodiment=emb)
            if comp.path in root:
                out["residue_composite"][(c, emb)] = int((root[comp.path]["hand_status"][:] == Reason.RESIDUE).sum())
            if get_embodiment(emb).track != "hand_arm":
                continue
            own = root[comp.path]["hand_status"][:]
            out["screens"][(c, emb)] = (int((own == Reason.OFF_ARM).sum()), int((own == Reason.HAND_HIDDEN).sum()))
            qc = root[Unit("qc", c, embodiment=emb).path]
            kept = (qc["status"][:] == Reason.OK)[:, None] & (qc["hand_status"][:] == Reason.OK)
            shares = off_arm_shares(root[comp.path]["robot_mask"][:], handarm, L, intr, kept)
            out["off_arm"][(c, emb)] = (int((shares > 0.25).sum()), int(kept.sum()))
    return out


def print_arm_report(rep: dict) -> None:
    radii = "  ".join(f"{100 * r:.0f} cm" for r in COVERAGE_RADII_M)
    print(f"\nforearm coverage (share of the forearm capsule inside the hand-arm mask), per clip and hand, capsule radius {radii};"
          "\nand the mask's half-width across the forearm, 6-14 cm from the wrist, how far its centre lies from the "
          "annotated forearm's axis, and how far its edge lies from the colour edge (medians, cm; "
          f"then the share of edges within {100 * EDGE_WITHIN_M:.1f} cm):")
    for (c, side), v in rep["coverage"].items():
        print(f"  {c:<34} {side:<6} " + "  ".join(f"{v[r]:5.2f}" for r in COVERAGE_RADII_M)
              + f"   half-width {100 * v['half_width']:4.1f}   axis offset {100 * v['axis_offset']:4.1f}"
              + f"   edge gap {100 * v['edge_gap']:4.2f}  {v['edge_within']:4.2f}")
    print("\nkept hand-arm frame-sides with > 25 % of the robot outside the arm corridor:")
    for (c, e), (bad, n) in rep["off_arm"].items():
        print(f"  {c:<34} {e:<14} {bad:>4} of {n}")
    print("\ncomposite's hand-arm screens, rejected frame-sides per clip x embodiment: OFF_ARM  HAND_HIDDEN")
    for (c, e), (off, hidden) in rep["screens"].items():
        print(f"  {c:<34} {e:<14} {off:>4} {hidden:>4}")
    print("\nrestored from real pixels (filled_from_video, weighted by hole area), per clip and scope: all frames / the first 24")
    for (c, scope), (share, first) in rep["from_video"].items():
        print(f"  {c:<34} {scope:<8} {share:6.3f} {first:6.3f}")
    print("\nRESIDUE rejections (restore_background, both scopes), per clip:")
    for c, n in rep["residue"].items():
        print(f"  {c:<34} {n:>4}")
    print("\nRESIDUE rejections in composite (restored pixels no robot covers), frame-sides per clip x embodiment:")
    for (c, e), n in rep["residue_composite"].items():
        print(f"  {c:<34} {e:<14} {n:>4}")


def figures(root, clips: list[str], embs: list[str], path: Path) -> None:
    """One contact sheet per embodiment (``path``, or ``path-<embodiment>`` for several)."""
    from figure import contact_sheet

    for e in embs:
        out = path if len(embs) == 1 else path.with_name(f"{path.stem}-{e}{path.suffix}")
        if contact_sheet(root, clips, e, out):
            print(f"\nfigure: {out} (source | masks: left blue, right red | restored background | pseudo-GT, {e})")


def repeated(args) -> None:
    """``--repeats N``: N runs of this bench, each in a fresh process (its own workers), then the
    roster's medians over them: on a shared machine one run's stages move 10-20 %."""
    import subprocess

    from handedit.storage import open_store

    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="handedit-egodex-"))
    out.mkdir(parents=True, exist_ok=True)
    argv = list(sys.argv[1:])
    for flag in ("--repeats", "--out", "--figure"):  # each run gets its own folder; no figures
        while flag in argv:
            k = argv.index(flag)
            del argv[k:k + 2]
    argv = [a for a in argv if not a.startswith(("--repeats=", "--out=", "--figure="))]
    stores = []
    for k in range(1, args.repeats + 1):
        run, log = out / f"run-{k}", out / f"run-{k}.log"
        with open(log, "w") as f:
            rc = subprocess.run([sys.executable, __file__, *argv, "--out", str(run)], stdout=f, stderr=subprocess.STDOUT).returncode
        last = log.read_text().strip().splitlines()[-1:] or [""]
        print(f"run {k}: {last[0]}" + ("" if rc == 0 else f" (exit {rc}: see {log})"), flush=True)
        if rc:
            sys.exit(rc)
        stores.append(run)
    print_roster([open_store(s) for s in stores])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", default=str(REPO.parent / "shared" / "data" / "egodex"))
    ap.add_argument("--frames", default="0:48", help="window A:B of every episode")
    ap.add_argument("--full", action="store_true", help="whole episodes")
    ap.add_argument("--resize", default="960x540")
    ap.add_argument("--embodiment", action="append")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--figure", help="write a contact sheet PNG here (not to be committed: CC BY-NC-ND data)")
    ap.add_argument("--out", help="keep the run in this folder (default: a temporary one)")
    ap.add_argument("--store", action="append", help="measure this existing run (its folder) instead of curating; "
                    "several: the roster's medians over them (with --roster)")
    ap.add_argument("--roster", action="store_true", help="every available embodiment; print each one's cost per "
                    "stage and, last, the projected CPU-hours for 200M pairs")
    ap.add_argument("--repeats", type=int, default=1, help="with --roster: this many runs, each in a fresh process "
                    "(OUT/run-K, its report in OUT/run-K.log); the medians are printed")
    args = ap.parse_args()
    if args.repeats > 1 and not args.store:
        return repeated(args)
    if args.store:
        from _runs import open_run
        from handedit.storage.summary import run_summary

        def run(s: str):
            return open_run(s, "bench/egodex.py", f"bench/egodex.py --out {s}")

        if len(args.store) > 1:
            if not args.roster:
                sys.exit("bench/egodex.py: several --store are compared by --roster only")
            return print_roster([run(s) for s in args.store])
        root = run(args.store[0])
        units = run_summary(root)["units"]
        for u in units:
            print(f"  {u['clip']:<34} {u['embodiment']:<14} {str(u['side']):<6} {u['kept']:>4}/{u['frames']:<4} "
                  f"{u['kept'] / max(u['frames'], 1):6.2f}")
        print_arm_report(arm_report(root))
        if args.roster:
            print_roster([root])
        if args.figure:
            clips = sorted(root["clips"].group_keys())
            embs = args.embodiment or sorted({u["embodiment"] for u in units if u["embodiment"]})
            figures(root, clips, embs, Path(args.figure))
        return
    os.environ.setdefault("HANDEDIT_ASSET_DIRS", str(REPO.parent / "shared" / "assets" / "robots"))

    import numpy as np
    from distributed import LocalCluster
    from prefect.testing.utilities import prefect_test_harness

    from handedit.flows.config import ClusterConfig, CurateConfig
    from handedit.flows.curate import run_curate
    from handedit.sources import EgoDexTree
    from handedit.sources.egodex import parse_frames
    from handedit.storage import Unit, open_store
    from handedit.storage.summary import run_summary

    embs = args.embodiment or (available_embodiments() if args.roster else ["allegro", "xarm_ability"])
    w, h = (int(v) for v in args.resize.split("x"))
    tree = EgoDexTree(root=Path(args.root), frames=None if args.full else parse_frames(args.frames), resize=(w, h))
    tmp = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="handedit-egodex-"))
    tmp.mkdir(parents=True, exist_ok=True)  # Prefect's home below it
    os.environ.setdefault("PREFECT_HOME", str(tmp / "prefect"))
    try:
        cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address="127.0.0.1:0")
    except (TimeoutError, OSError) as e:  # a machine too busy to start 2 worker processes in Dask's time
        sys.exit(f"bench/egodex.py: the local Dask cluster did not start ({type(e).__name__}: {e}). The machine is "
                 "probably too busy to start its worker processes in time: rerun when it is quieter, or with fewer "
                 "--workers.")
    with prefect_test_harness(server_startup_timeout=180), cluster:
        config = CurateConfig(out=tmp / "handedit.zarr", sources=[tree], embodiments=embs, frames_per_chunk=16,
                              cluster=ClusterConfig(address=cluster.scheduler_address))
        t0 = time.perf_counter()
        run_curate(config)
        wall = time.perf_counter() - t0
    root = open_store(config.out)
    clips = sorted(root["clips"].group_keys())
    n_frames = sum(root[Unit("ingest", c).path]["status"].shape[0] for c in clips)
    print(f"EgoDex: {len(clips)} clip(s), {n_frames} frames at {w}x{h}, embodiments {embs}, {args.workers} workers, "
          f"wall {wall:.0f} s ({n_frames * len(embs) / wall:.2f} frame-embodiments/s)")
    print("\nms per frame (task wall time; per frame and embodiment from retarget on):")
    times = timings(record_times(root))
    for stage, ms in stage_costs(times).items():
        print(f"  {stage:<20} {ms:8.1f}")
    print("\nkept fraction (QC OK with this hand's robot), per clip x embodiment x hand:")
    for u in run_summary(root)["units"]:
        print(f"  {u['clip']:<34} {u['embodiment']:<14} {str(u['side']):<6} {u['kept']:>4}/{u['frames']:<4} "
              f"{u['kept'] / max(u['frames'], 1):6.2f}")
    print("\nregistration: |offset| px at 1080p, median / 90th percentile / max, per clip and hand")
    for c in clips:
        reg = root[Unit("registration", c).path]
        off, hs = reg["offset_px"][:], reg["hand_status"][:]
        scale = 1920.0 / root[Unit("ingest", c).path].attrs["info"]["width"]
        for k, side in enumerate(root[Unit("ingest", c).path].attrs["hands"]):
            d = np.linalg.norm(off[hs[:, k] == 1, k], axis=-1) * scale
            if d.size:
                print(f"  {c:<34} {side:<6} {np.median(d):6.1f} {np.percentile(d, 90):6.1f} {d.max():6.1f}")
    print("\ncoverage on kept frames: share of the replaced hands' masks under their robot / left unchanged")
    for c in clips:
        for e in embs:
            under, left = coverage(root, c, e)
            print(f"  {c:<34} {e:<14} {under:6.2f} {left:6.3f}")
    print_arm_report(arm_report(root))
    if args.roster:
        print_roster([root])
    if args.figure:
        figures(root, clips, embs, Path(args.figure))

if __name__ == "__main__":
    main()
