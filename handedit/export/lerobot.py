"""The LeRobot dataset format, v3.0 (``lerobot.datasets``, codebase "v3.0"), written without
LeRobot: its features, per-frame tables, statistics and metadata files.

    meta/info.json                        features, fps, paths; ``handedit``: robot, camera, export
    meta/stats.json                       per feature: min, max, mean, std, count, q01 ... q99
    meta/tasks.parquet                    task text (the index) -> task_index
    meta/episodes/chunk-C/file-F.parquet  one row per episode: length, where its rows and
                                          videos are, its statistics (``stats/...``), and
                                          ``handedit/...``: clip, content key, camera, virtual base
    data/chunk-C/file-F.parquet           one row per frame
    videos/<key>/chunk-C/file-F.mp4       one file per episode and camera

One episode per data file and per video file (LeRobot lets each episode name its files):
re-exporting after more curation rewrites only the episodes whose content changed, and a
video is never re-encoded because another episode was added.

A frame QC rejected stays in its episode with ``valid = false``, so time stays continuous;
its joints hold the nearest valid frame's values (a policy's normaliser must not see NaN).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

CODEBASE_VERSION = "v3.0"
CHUNKS_SIZE = 1000  # files per chunk folder (LeRobot's default)
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EGO, SOURCE = "observation.images.egocentric", "observation.images.source"
STATE, ACTION, WRIST, VALID, HAND_VALID = "observation.state", "action", "observation.wrist_pose", "valid", "hand_valid"
INDEX_FEATURES = {name: {"dtype": dtype, "shape": [1], "names": None} for name, dtype in (
    ("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"), ("index", "int64"),
    ("task_index", "int64"))}
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
IMAGE_STAT_FRAMES = 100  # frames an episode's image statistics sample (LeRobot samples too)
IMAGE_STAT_SIDE = 150  # ... each downsampled to about this many pixels on its short side


def chunk_file(i: int) -> dict[str, int]:
    return {"chunk_index": i // CHUNKS_SIZE, "file_index": i % CHUNKS_SIZE}


def data_path(episode: int) -> str:
    return DATA_PATH.format(**chunk_file(episode))


def video_path(key: str, episode: int) -> str:
    return VIDEO_PATH.format(video_key=key, **chunk_file(episode))


def episodes_path(part: int) -> str:
    return EPISODES_PATH.format(**chunk_file(part))


@dataclass(frozen=True)
class Layout:
    """The joint and pose columns of a dataset: every side any episode has, in this order."""

    sides: tuple[str, ...]
    joints: tuple[str, ...]

    def state_names(self) -> list[str]:
        return [f"{s}_{j}" for s in self.sides for j in self.joints]

    def pose_names(self) -> list[str]:
        from handedit.export.robot import POSE_NAMES

        return [f"{s}_{c}" for s in self.sides for c in POSE_NAMES]


def features(layout: Layout, height: int, width: int, fps: float, video_keys: list[str], video_info: dict) -> dict:
    names = layout.state_names()
    out = {key: {"dtype": "video", "shape": [height, width, 3], "names": ["height", "width", "channels"],
                 "info": video_info} for key in video_keys}
    out.update({
        STATE: {"dtype": "float32", "shape": [len(names)], "names": names},
        ACTION: {"dtype": "float32", "shape": [len(names)], "names": names},
        WRIST: {"dtype": "float32", "shape": [len(layout.pose_names())], "names": layout.pose_names()},
        VALID: {"dtype": "bool", "shape": [1], "names": None},
        HAND_VALID: {"dtype": "bool", "shape": [len(layout.sides)], "names": list(layout.sides)},
    })
    out.update(INDEX_FEATURES)
    return out


def hold(values: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``values`` (T, ...) with rows where ``ok`` is False replaced by the nearest earlier ok
    row (the first ok row before it); zeros when no row is ok."""
    out = np.zeros_like(values, dtype=np.float32)
    good = np.flatnonzero(ok)
    if not len(good):
        return out
    idx = np.maximum.accumulate(np.where(ok, np.arange(len(ok)), -1))
    idx[idx < 0] = good[0]
    return values[idx].astype(np.float32)


def frame_columns(layout: Layout, sides: list[str], valid: np.ndarray, hand_ok: np.ndarray, qpos: np.ndarray,
                  wrist: np.ndarray) -> dict[str, np.ndarray]:
    """One episode's per-frame features: ``qpos`` (T, S, dof) and ``wrist`` (T, S, 7) in the
    clip's hand order ``sides``, ``hand_ok`` (T, S) whether each side is usable, ``valid`` (T,)
    QC's keep. Sides the clip lacks are zeros and never valid."""
    T = len(valid)
    dof, S = len(layout.joints), len(layout.sides)
    state = np.zeros((T, S, dof), np.float32)
    pose = np.zeros((T, S, 7), np.float32)
    present = np.zeros((T, S), bool)
    for k, side in enumerate(sides):
        j = layout.sides.index(side)
        ok = hand_ok[:, k] & np.all(np.isfinite(qpos[:, k]), axis=1) & np.all(np.isfinite(wrist[:, k]), axis=1)
        state[:, j], pose[:, j], present[:, j] = hold(qpos[:, k], ok), hold(wrist[:, k], ok), ok
    state = state.reshape(T, S * dof)
    action = np.concatenate([state[1:], state[-1:]]) if T else state  # the next frame's state; the last holds
    return {STATE: state, ACTION: action, WRIST: pose.reshape(T, S * 7), VALID: np.asarray(valid, bool),
            HAND_VALID: present}


# -- statistics ------------------------------------------------------------------------------

def numeric_stats(x: np.ndarray) -> dict[str, np.ndarray]:
    """LeRobot's per-feature statistics over frames (axis 0); bools count as 0/1 but keep
    bool min/max, as LeRobot writes them."""
    x = np.asarray(x)
    if x.ndim == 1:
        x = x[:, None]
    f = x.astype(np.float64)
    out = {"min": x.min(0), "max": x.max(0), "mean": f.mean(0), "std": f.std(0), "count": np.array([len(x)])}
    out.update({f"q{int(round(q * 100)):02d}": np.quantile(f, q, axis=0) for q in QUANTILES})
    return out


def image_stats(frames: np.ndarray) -> dict[str, np.ndarray]:
    """Per-channel statistics of an episode's frames (T, H, W, 3) uint8, in [0, 1], shaped
    (3, 1, 1) like LeRobot's, from up to ``IMAGE_STAT_FRAMES`` frames downsampled."""
    T, H, W = frames.shape[:3]
    pick = np.unique(np.linspace(0, T - 1, min(T, IMAGE_STAT_FRAMES)).round().astype(int))
    step = max(1, min(H, W) // IMAGE_STAT_SIDE)
    px = frames[pick, ::step, ::step].reshape(-1, 3).astype(np.float64) / 255.0
    stats = numeric_stats(px)
    return {k: (v if k == "count" else v.reshape(3, 1, 1)) for k, v in {**stats, "count": np.array([T])}.items()}


def aggregate(per_episode: list[dict[str, dict[str, np.ndarray]]]) -> dict[str, dict[str, np.ndarray]]:
    """Dataset statistics from episodes' (count-weighted mean and quantiles, pooled variance)."""
    out = {}
    for key in dict.fromkeys(k for s in per_episode for k in s):
        parts = [s[key] for s in per_episode if key in s]
        n = np.array([float(p["count"][0]) for p in parts])
        w = (n / n.sum()).reshape(-1, *[1] * np.ndim(parts[0]["mean"]))
        mean = (w * np.stack([p["mean"] for p in parts])).sum(0)
        var = (w * np.stack([p["std"] ** 2 + (p["mean"] - mean) ** 2 for p in parts])).sum(0)
        agg = {"min": np.min(np.stack([p["min"] for p in parts]), 0), "max": np.max(np.stack([p["max"] for p in parts]), 0),
               "mean": mean, "std": np.sqrt(var), "count": np.array([int(n.sum())])}
        for q in (k for k in parts[0] if k.startswith("q")):
            agg[q] = (w * np.stack([p[q] for p in parts])).sum(0)
        out[key] = agg
    return out


def jsonable_stats(stats: dict) -> dict:
    return {k: {s: np.asarray(v).tolist() for s, v in d.items()} for k, d in stats.items()}


def flat_stats(stats: dict) -> dict[str, list]:
    """An episode's statistics as its row's ``stats/<feature>/<stat>`` columns."""
    return {f"stats/{k}/{s}": np.asarray(v).tolist() for k, d in stats.items() for s, v in d.items()}


def unflat_stats(row: dict) -> dict[str, dict[str, np.ndarray]]:
    out: dict[str, dict[str, np.ndarray]] = {}
    for col, v in row.items():
        if col.startswith("stats/"):
            key, stat = col[len("stats/"):].rsplit("/", 1)
            out.setdefault(key, {})[stat] = np.asarray(_plain(v))
    return out


def _plain(v):
    """Nested lists from what pyarrow gives back for list columns (numpy object arrays)."""
    if isinstance(v, np.ndarray) and v.dtype == object:
        return [_plain(x) for x in v]
    return v.tolist() if isinstance(v, np.ndarray) else v


# -- files -----------------------------------------------------------------------------------

def write_data(path: Path, columns: dict[str, np.ndarray], feats: dict) -> None:
    """One episode's frames as a Parquet file, each feature typed as ``feats`` says (vectors as
    fixed-size lists, as ``datasets`` writes them)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    arrays, fields = [], []
    for name, ft in feats.items():
        if ft["dtype"] == "video":
            continue
        col = np.asarray(columns[name])
        typ = pa.from_numpy_dtype(np.dtype(ft["dtype"]))
        if ft["shape"] == [1]:
            arr = pa.array(col.reshape(-1).astype(ft["dtype"]), typ)
        else:
            flat = pa.array(col.reshape(-1).astype(ft["dtype"]), typ)
            arr = pa.FixedSizeListArray.from_arrays(flat, int(ft["shape"][0]))
        arrays.append(arr)
        fields.append(pa.field(name, arr.type))
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_arrays(arrays, schema=pa.schema(fields)), path)


def write_episodes(root: Path, rows: list[dict]) -> None:
    """The episodes' metadata, ``CHUNKS_SIZE`` episodes per file."""
    import pandas as pd

    for part in range(0, len(rows), CHUNKS_SIZE):
        block = [{**r, "meta/episodes/chunk_index": chunk_file(part // CHUNKS_SIZE)["chunk_index"],
                  "meta/episodes/file_index": chunk_file(part // CHUNKS_SIZE)["file_index"]}
                 for r in rows[part:part + CHUNKS_SIZE]]
        path = root / episodes_path(part // CHUNKS_SIZE)
        path.parent.mkdir(parents=True, exist_ok=True)
        pd.DataFrame(block).to_parquet(path, index=False)


def read_episodes(root: Path) -> list[dict]:
    import pandas as pd

    files = sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    rows = [r for f in files for r in pd.read_parquet(f).to_dict(orient="records")]
    return sorted(rows, key=lambda r: int(r["episode_index"]))


def write_tasks(root: Path, tasks: list[str]) -> None:
    import pandas as pd

    frame = pd.DataFrame({"task_index": np.arange(len(tasks), dtype=np.int64)}, index=pd.Index(tasks))
    frame.to_parquet(root / "meta" / "tasks.parquet")


def read_tasks(root: Path) -> list[str]:
    import pandas as pd

    path = root / "meta" / "tasks.parquet"
    if not path.is_file():
        return []
    frame = pd.read_parquet(path)
    return [t for t, _ in sorted(zip(frame.index, frame["task_index"]), key=lambda x: x[1])]


def info(feats: dict, fps: float, robot_type: str, episodes: int, frames: int, tasks: int, extra: dict) -> dict:
    return {"codebase_version": CODEBASE_VERSION, "robot_type": robot_type, "total_episodes": episodes,
            "total_frames": frames, "total_tasks": tasks, "chunks_size": CHUNKS_SIZE, "data_files_size_in_mb": 100,
            "video_files_size_in_mb": 200, "fps": fps, "splits": {"train": f"0:{episodes}"}, "data_path": DATA_PATH,
            "video_path": VIDEO_PATH if any(f["dtype"] == "video" for f in feats.values()) else None,
            "features": feats, "handedit": extra}


def write_json(path: Path, obj) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2, sort_keys=False) + "\n")
