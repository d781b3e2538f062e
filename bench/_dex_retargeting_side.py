"""dex-retargeting's side of ``bench/retarget.py --against-dex-retargeting`` (run by the venv that
has dex-retargeting 0.5.0; this project's code is not imported here).

    DEX_PYTHON bench/_dex_retargeting_side.py KEYPOINTS.npz URDF_DIR

KEYPOINTS.npz holds ``keypoints_<i>`` (T_i,21,3) camera-frame MANO joints in metres, one
per clip, and ``root0`` (C,4,4), each clip's first-frame robot root pose (the same start the project's
solver gets). Position retargeting with its shipped offline Allegro config (a free 6-DoF
root, fingertips and the PIP-level links as targets), warm-started per clip from root0,
then sequential as its examples run it. Prints one JSON line: ms per frame (start-up
excluded) and the fingertip residual per frame (mm), the four tip links against the MANO
tips.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import yaml


def main() -> int:
    import dex_retargeting
    from dex_retargeting.retargeting_config import RetargetingConfig
    from pytransform3d import rotations

    data = np.load(sys.argv[1])
    urdf_dir = Path(sys.argv[2])
    cfg_file = Path(dex_retargeting.__file__).parent / "configs/offline/allegro_hand_right.yml"
    cfg = yaml.safe_load(cfg_file.read_text())["retargeting"]
    cfg["urdf_path"] = str(urdf_dir / "hands/allegro_hand/allegro_hand_right_glb.urdf")  # same kinematics, GLB visuals
    tips = [(name, idx) for name, idx in zip(cfg["target_link_names"], cfg["target_link_human_indices"]) if name.endswith("_tip")]
    errors, seconds, frames = [], 0.0, 0
    t_build = time.perf_counter()
    rt = RetargetingConfig.from_dict(cfg).build()
    build_s = time.perf_counter() - t_build
    robot = rt.optimizer.robot
    tip_ids = [robot.get_link_index(name) for name, _ in tips]
    indices = np.asarray(cfg["target_link_human_indices"])
    for i, root0 in enumerate(data["root0"]):
        kp = data[f"keypoints_{i}"]  # clips of any length (real trajectories differ)
        rt.reset()
        rt.warm_start(root0[:3, 3], rotations.quaternion_from_matrix(root0[:3, :3]))
        for k in kp:
            t0 = time.perf_counter()
            q = rt.retarget(k[indices])
            seconds += time.perf_counter() - t0
            frames += 1
            robot.compute_forward_kinematics(q)
            got = np.array([robot.get_link_pose(i)[:3, 3] for i in tip_ids])
            errors.append(1000 * np.linalg.norm(got - k[[idx for _, idx in tips]], axis=1).mean())
    print(json.dumps({"ms_per_frame": 1000 * seconds / frames, "tip_mm": errors, "build_s": build_s, "frames": frames}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
