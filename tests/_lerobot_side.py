"""Run by the official LeRobot's venv (``deploy/lerobot-env.sh``): load an exported dataset with
``LeRobotDataset`` and hand back what the test compares with the store.

    python _lerobot_side.py DATASET_ROOT OUT_DIR INDEX [INDEX ...]

Writes OUT_DIR/meta.json (counts, features, tasks of the items) and OUT_DIR/<key>.npy per
item key (stacked over the given indices; images as uint8 HWC, as the store holds them).
"""

import json
import sys
from pathlib import Path

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

root, out, indices = sys.argv[1], Path(sys.argv[2]), [int(i) for i in sys.argv[3:]]
ds = LeRobotDataset("local/handedit-export", root=root)
items = [ds[i] for i in indices]
meta = {"num_episodes": ds.num_episodes, "num_frames": ds.num_frames, "fps": ds.fps,
        "features": {k: {"dtype": v["dtype"], "shape": list(v["shape"]), "names": v.get("names")}
                     for k, v in ds.features.items()},
        "tasks": [it["task"] for it in items], "camera_keys": list(ds.meta.camera_keys),
        "stats_keys": sorted(ds.meta.stats)}
out.mkdir(parents=True, exist_ok=True)
for key in items[0]:
    if key == "task":
        continue
    arr = np.stack([np.asarray(it[key]) for it in items])
    if key in ds.meta.camera_keys:  # float CHW in [0, 1] -> uint8 HWC
        arr = np.round(arr.transpose(0, 2, 3, 1) * 255).astype(np.uint8)
    np.save(out / f"{key}.npy", arr)
(out / "meta.json").write_text(json.dumps(meta))
