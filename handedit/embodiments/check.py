"""``handedit embodiments check FILE``: everything a new robot file has to pass, in one report.

The file validates; its URDF resolves and loads (DoF, joint limits, mimic joints); a preview
sheet shows it in a few poses on both sides (left: the mirrored URDF); the synthetic hand is
retargeted onto it (the fingertip residual ``bench/retarget.py`` reports); and for a hand the
wrist-to-root transform is fitted from its palm geometry (``handedit.retarget.palm``), printed
ready to paste, with how far the file's own value is from it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from handedit.embodiments.robot_files import RobotFileError, current_files, parse_file, robot_dirs_added

SHEET_SEEDS = (0, 1, 2)  # the neutral pose and two seeded in-limit poses
SHEET_SIZE = 320


def roster_key(path: Path) -> tuple[str, list[str]]:
    """``path``'s key, and the folder that makes the file part of the roster ([] when it already
    is); an error naming both files when another file has that key."""
    path = path.resolve()
    key = path.stem
    files = current_files()
    if key in files and files[key][0].resolve() != path:
        raise RobotFileError(f"robot key {key!r} is defined twice: {files[key][0]} and {path}; rename {path.name}")
    return key, ([] if key in files else [str(path.parent)])


def wrist_fit(key: str, shipped: np.ndarray) -> dict:
    from handedit.retarget.palm import calibrate_wrist_from_root

    fitted = calibrate_wrist_from_root(key)
    d_mm = float(np.linalg.norm(fitted[:3, 3] - shipped[:3, 3]) * 1000)
    c = np.clip((np.trace(fitted[:3, :3].T @ shipped[:3, :3]) - 1) / 2, -1, 1)
    return {"fitted": np.round(fitted, 5).tolist(), "from_file_mm": d_mm, "from_file_deg": float(np.degrees(np.arccos(c)))}


def preview_sheet(key: str, out: Path) -> Path:
    """Both sides (rows: right, left) in ``SHEET_SEEDS`` poses (columns), one canonical view each."""
    import cv2

    from handedit.render.cache import embodiment_renderer
    from handedit.render.views import canonical_views

    rows = []
    for side in ("right", "left"):
        r = embodiment_renderer(key, SHEET_SIZE, SHEET_SIZE, None, None, side)
        tiles = []
        for seed in SHEET_SEEDS:
            rig = canonical_views(r, 1, seed=seed)
            img = r.render(rig.qpos, rig.camera_from_root, rig.intrinsics).rgba[0, ..., :3]
            tile = np.where(img.sum(-1, keepdims=True) > 0, img, 235).astype(np.uint8)
            cv2.putText(tile, f"{side} pose {seed}", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (40, 40, 40), 1, cv2.LINE_AA)
            tiles.append(tile)
        rows.append(np.concatenate(tiles, axis=1))
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), cv2.cvtColor(np.concatenate(rows, axis=0), cv2.COLOR_RGB2BGR))
    return out


def check_robot_file(path: Path, sheet: Path | None = None, residual: bool = True) -> dict:
    """The checks of ``handedit embodiments check``, with the file's folder in the roster while
    they run (and only then: a process that checks a file keeps no folder of it)."""
    f = parse_file(path)
    key, dirs = roster_key(path)
    with robot_dirs_added(dirs):  # a clash the new folder brings fails here, naming both files
        return _check(path, f, key, sheet, residual)


def _check(path: Path, f, key: str, sheet: Path | None, residual: bool) -> dict:
    from handedit.embodiments import get_embodiment, resolve_urdf
    from handedit.embodiments.kinematics import get_kinematics
    from handedit.embodiments.linkage import poly_mimics

    lines = [f"{path}: a valid {f.kind} file, key {key!r} ({f.name})"]
    report: dict = {"file": str(path), "key": key, "kind": f.kind}
    if f.kind == "arm":
        from handedit.embodiments.roster import arm_spec

        lines.append(f"arm URDF candidates: {', '.join(a.path for a in arm_spec(key).assets)}; a hand-arm file names it "
                     f"with `arm: {key}`")
        report["text"] = "\n".join(lines)
        return report
    emb = get_embodiment(key)
    urdf = resolve_urdf(emb)
    kin = get_kinematics(urdf)
    mimic = kin.mimic_joints()
    polys = poly_mimics(urdf)
    report.update(urdf=str(urdf), dof=kin.dof, joints=list(kin.joint_names), mimic=sorted(mimic), linkage_mimic=sorted(polys))
    lines.append(f"URDF: {urdf}")
    lines.append(f"DoF: {kin.dof} actuated joints (qpos order); {len(mimic)} mimic joint(s)"
                 + (f", {len(polys)} solved from linkages" if polys else ""))
    for n, lo, hi in zip(kin.joint_names, kin.lower, kin.upper):
        lines.append(f"  {n:<36} [{lo:+.3f}, {hi:+.3f}]")
    for n, (src, m, o) in sorted(mimic.items()):
        lines.append(f"  mimic {n} = {m:g} * {src} + {o:g}")
    out = sheet or Path(f"{key}-check.png")
    report["sheet"] = str(preview_sheet(key, out))
    lines.append(f"preview sheet (right and left side, {len(SHEET_SEEDS)} poses): {out}")
    hand_key = key if f.kind == "hand" else f.hand
    if residual:
        from handedit.retarget.quality import synthetic_residual

        res = synthetic_residual(hand_key)
        report["residual"] = res
        lines.append(f"synthetic hand retargeted onto {hand_key} ({res['frames']} frames, as bench/retarget.py): fingertip "
                     f"residual mean {res['tip_mean']:.2f} mm (p95 {res['tip_p95']:.2f}), wrist {res['wrist_mean']:.2f} mm, "
                     f"{res['violations']} joint-limit violations, {res['rejected']} frames over the 50 mm QC threshold")
    if f.kind == "hand":
        from handedit.embodiments import resolve_asset

        asset = resolve_asset(emb).asset
        fit = wrist_fit(key, asset.wrist_from_root_matrix)
        report["wrist_fit"] = fit
        rows = "\n".join(f"  - [{', '.join(np.format_float_positional(v, trim='-') for v in row)}]" for row in fit["fitted"])
        lines.append(f"wrist_from_root fitted from the palm geometry ({fit['from_file_mm']:.1f} mm and "
                     f"{fit['from_file_deg']:.1f} deg from the file's); to paste under the URDF entry:\n"
                     f"  wrist_from_root:\n{rows}")
    report["text"] = "\n".join(lines)
    return report
