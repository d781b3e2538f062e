"""Render-speed benchmark: ms/frame at 640x480 per embodiment, full vs decimated meshes, and the
silhouette IoU between the two (goal: <= 60 ms/frame at IoU >= 0.98).

    .venv/bin/python bench/render.py --roster --robots-dir ../shared/assets/robots [--decimate 0.2] [--profile leap,ur5_shadow]
    .venv/bin/python bench/render.py --robots-dir ../shared/assets/robots [--grid /tmp/render_grid.png]  # raw asset files

``--roster`` measures every embodiment of the roster whose assets resolve (hand-arm ones as
their composed URDF) plus the packaged (example-robot-data) Allegro; without it, the raw asset
files of the manifest (arms included). ``--profile`` splits a frame of the named robots into
Python (FK + scene poses), GL draw, and read-back, and times the cheaper passes (depth/mask
only, 320x240). IoU is the smallest over the frames; every frame uses a different random pose.

The camera is a 60 deg head camera; hands have their bounding-box centre 0.4 m ahead, arms and
hand-arms are framed to fit 60 % of the image; one fixed oblique view; configurations are random
within joint limits (seeded). Timings are wall-clock medians per frame on whatever this machine
runs (Mesa llvmpipe here), so the load average is printed with them.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from handedit.camera import Intrinsics  # noqa: E402
from handedit.render import RenderResult, RobotRenderer, frame_points, rotation_from_euler  # noqa: E402
from handedit.render.model import joint_limits  # noqa: E402

W, H = 640, 480
HFOV_DEG = 60.0  # head-camera field of view: a hand 0.4 m ahead covers ~5-15 % of the frame
HAND_DISTANCE_M = 0.4


def packaged_allegro() -> Path | None:
    import site

    for sp in site.getsitepackages():
        p = Path(sp) / "cmeel.prefix/share/example-robot-data/robots/allegro_hand_description/urdf/allegro_right_hand.urdf"
        if p.is_file():
            return p
    return None


def robot_urdfs(robots_dir: Path | None, kinds: set[str]) -> dict[str, tuple[Path, str]]:
    """name -> (URDF, kind) for the dex-urdf assets (if given) and the packaged Allegro."""
    out: dict[str, tuple[Path, str]] = {}
    if robots_dir is not None:
        manifest = json.loads((robots_dir / "manifest.json").read_text())
        out.update({k: (robots_dir / v["urdf"], v["kind"]) for k, v in manifest.items() if v["kind"] in kinds})
    pkg = packaged_allegro()
    if pkg is not None and "hand" in kinds:
        out["allegro_pkg"] = (pkg, "hand")
    return out


def roster_urdfs(robots_dir: Path | None) -> dict[str, tuple[Path, str]]:
    """embodiment id -> (URDF, kind) for every roster embodiment whose assets resolve."""
    from handedit.embodiments import asset_status, list_embodiments, resolve_urdf

    if robots_dir is not None:
        os.environ["HANDEDIT_ASSET_DIRS"] = str(robots_dir.resolve())
    out = {}
    for e in list_embodiments():
        ok, _ = asset_status(e)
        if ok:
            out[e.id] = (resolve_urdf(e), "hand" if e.arm is None else "hand-arm")
        else:
            print(f"{e.id:<22} assets missing")
    pkg = packaged_allegro()
    if pkg is not None:
        out["allegro_pkg"] = (pkg, "hand")
    return out


VIEWS = [(0.4, 0.3, 0.2), (np.pi / 2, 0.0, 0.0), (-np.pi / 2, 0.5, 0.0)]  # euler xyz, radians


def scenario(
    r: RobotRenderer, n: int, seed: int = 0, views=VIEWS[:1], distance: float | None = HAND_DISTANCE_M
) -> tuple[np.ndarray, np.ndarray, Intrinsics]:
    """n random in-limit configurations seen by a 60 deg head camera, cycling ``views``, with the
    robot's bounding-box centre ``distance`` m ahead (None: as close as fits 60 % of the image)."""
    intr = Intrinsics.default_for(W, H, hfov_deg=HFOV_DEG)
    lo, hi = joint_limits(r.urdf)
    rng = np.random.default_rng(seed)
    q = rng.uniform(lo, hi, size=(n, len(lo)))
    rots = [rotation_from_euler(*v) for v in views]
    poses = np.stack(
        [frame_points(r.points(qi), rots[i % len(rots)], intr, fill=0.6, distance=distance) for i, qi in enumerate(q)]
    )
    return q, poses, intr


def time_render(r: RobotRenderer, q, poses, intr):
    """(median wall ms, median CPU ms per frame, results). Wall time is what a worker sees; CPU
    time (all threads, llvmpipe's included) is the work done, and barely moves when other
    processes share the cores, so it is the figure to compare between runs on a busy machine."""
    r.render(q[:1], poses[:1], intr)  # warm-up: first frame uploads buffers, compiles shaders
    wall, cpu, results = [], [], []
    for i in range(len(q)):
        t, c = time.perf_counter(), time.process_time()
        results.append(r.render(q[i : i + 1], poses[i : i + 1], intr))
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    res = RenderResult(np.concatenate([x.rgba for x in results]), np.concatenate([x.depth for x in results]))
    return 1000 * float(np.median(wall)), 1000 * float(np.median(cpu)), res


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def save_grid(renderers: dict[str, RobotRenderer], path: Path) -> None:
    import cv2

    tiles = []
    for name, r in renderers.items():
        q, poses, intr = scenario(r, 3, seed=1, views=VIEWS, distance=None)
        res = r.render(q, poses, intr)
        row = []
        for img in res.rgba:
            a = img[..., 3:].astype(float) / 255
            comp = (img[..., :3] * a + np.array([190, 215, 190]) * (1 - a)).astype(np.uint8)
            cv2.putText(comp, name, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (200, 0, 0), 2)
            row.append(cv2.resize(comp, (W // 2, H // 2), interpolation=cv2.INTER_AREA))
        tiles.append(np.concatenate(row, axis=1))
    cv2.imwrite(str(path), cv2.cvtColor(np.concatenate(tiles, axis=0), cv2.COLOR_RGB2BGR))
    print(f"grid written to {path}")


def profile(r: RobotRenderer, q, poses, intr, frames: int = 5) -> dict[str, float]:
    """Median ms per frame of: ``fk`` (FK + scene poses, ours), ``submit`` (pyrender's scene
    traversal and GL calls; llvmpipe runs vertex shading here, on the calling thread), ``raster``
    (waiting in glFinish for llvmpipe's rasteriser threads), ``readback`` (glReadPixels + depth
    linearisation), then the whole of a depth-only pass (mask = depth > 0) and of the same RGBA
    render at 320x240; whole-frame passes with every link drawn, not ``render``'s screen boxes and
    culled links. Instruments this renderer instance only (bench use)."""
    import pyrender
    from OpenGL.GL import glFinish

    from handedit.camera import CV_TO_GL

    gl = r._gl._renderer
    read = gl._read_main_framebuffer
    split: dict[str, list[float]] = {"fk": [], "submit": [], "raster": [], "readback": [], "depth_only": []}
    marks: dict[str, float] = {}

    def timed_read(scene, flags):
        marks["submitted"] = time.perf_counter()
        glFinish()
        marks["drawn"] = time.perf_counter()
        out = read(scene, flags)
        marks["read"] = time.perf_counter()
        return out

    gl._read_main_framebuffer = timed_read
    r._gl.region = None  # the whole frame, every link (``render`` leaves its last box and culled links set)
    for node in r._link_nodes.values():
        node.mesh.is_visible = True
    try:
        for i in range(frames):
            t0 = time.perf_counter()
            gl_from_root = CV_TO_GL @ poses[i]
            for link, T in r.link_transforms(q[i]).items():
                r.scene.set_pose(r._link_nodes[link], gl_from_root @ T)
            t1 = time.perf_counter()
            r._gl.render(r.scene, flags=pyrender.RenderFlags.RGBA)
            split["fk"].append(t1 - t0)
            split["submit"].append(marks["submitted"] - t1)
            split["raster"].append(marks["drawn"] - marks["submitted"])
            split["readback"].append(marks["read"] - marks["drawn"])
            t2 = time.perf_counter()
            r._gl.render(r.scene, flags=pyrender.RenderFlags.DEPTH_ONLY)
            split["depth_only"].append(time.perf_counter() - t2)
    finally:
        gl._read_main_framebuffer = read
    out = {k: 1000 * float(np.median(v)) for k, v in split.items()}
    small = RobotRenderer(r.urdf_path, W // 2, H // 2, decimate=r.decimate)
    si = Intrinsics(intr.fx / 2, intr.fy / 2, intr.cx / 2, intr.cy / 2, W // 2, H // 2)
    out["320x240"] = time_render(small, q[:frames], poses[:frames], si)[0]
    small.close()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robots-dir", type=Path, default=None)
    ap.add_argument("--kinds", default="hand,arm,hand-arm", help="manifest kinds to include")
    ap.add_argument("--decimate", type=float, default=0.2, help="fraction of faces kept (dense meshes only)")
    ap.add_argument("--frames", type=int, default=7)
    ap.add_argument("--grid", type=Path, default=None, help="also save a PNG grid of the hands")
    ap.add_argument("--roster", action="store_true", help="every available roster embodiment (see doc)")
    ap.add_argument("--only", default="", help="comma-separated names to measure (default: all)")
    ap.add_argument("--profile", default="", help="comma-separated names to profile (see doc)")
    args = ap.parse_args()
    print(
        f"{W}x{H}, decimate={args.decimate}, {args.frames} random in-limit poses per robot; "
        f"{os.cpu_count()} cores SHARED with other jobs: wall ms depend on the load average printed "
        "per row, cpu ms (all threads) much less"
    )

    if args.roster:
        urdfs = roster_urdfs(args.robots_dir)
    else:
        urdfs = robot_urdfs(args.robots_dir, set(args.kinds.split(",")))
    if args.only:
        urdfs = {k: v for k, v in urdfs.items() if k in args.only.split(",")}
    print(
        f"{'robot':<16}{'faces':>8}{'ms/frame':>9}{'cpu ms':>8}{'dec faces':>10}{'dec ms':>8}{'dec cpu':>8}"
        f"{'min IoU':>8}{'fill %':>7}{'load':>6}"
    )
    full_renderers = {}
    rows = []
    for name, (path, kind) in urdfs.items():
        r = RobotRenderer(path, W, H)
        if kind == "hand":
            full_renderers[name] = r
        # hands at a typical egocentric distance; arms and hand-arms framed to fit
        q, poses, intr = scenario(r, args.frames, distance=HAND_DISTANCE_M if kind == "hand" else None)
        ms, cpu, res = time_render(r, q, poses, intr)
        mask = res.mask
        row = f"{name:<16}{r.n_faces:>8}{ms:>9.1f}{cpu:>8.1f}"
        try:
            rd = RobotRenderer(path, W, H, decimate=args.decimate)
        except ImportError as exc:
            print(row + f"   decimation unavailable ({exc})")
            continue
        ms_d, cpu_d, res_d = time_render(rd, q, poses, intr)
        ious = [iou(a, b) for a, b in zip(mask, res_d.mask)]
        print(
            row + f"{rd.n_faces:>10}{ms_d:>8.1f}{cpu_d:>8.1f}{min(ious):>8.3f}{100 * mask.mean():>7.1f}"
            f"{os.getloadavg()[0]:>6.1f}",
            flush=True,
        )
        rows.append((name, ms, ms_d, min(ious)))
        if name in args.profile.split(","):
            for label, rr in (("full", r), ("decimated", rd)):
                prof = profile(rr, q, poses, intr)
                print("    profile " + f"{label:<10}" + "  ".join(f"{k} {v:.1f}" for k, v in prof.items()) + " ms")
        rd.close()
        if kind != "hand":
            r.close()
    if rows:
        ok = [n for n, _, md, i in rows if md <= 60 and i >= 0.98]
        print(f"goal (<= 60 ms/frame decimated, IoU >= 0.98) met by {len(ok)}/{len(rows)}: {', '.join(ok)}")
        print(f"worst IoU {min(i for *_, i in rows):.3f}; load average {os.getloadavg()[0]:.2f} at the end")
    if args.grid is not None:
        save_grid({k: r for k, r in full_renderers.items() if urdfs[k][1] == "hand"}, args.grid)


if __name__ == "__main__":
    main()
