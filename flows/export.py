"""The ``export-lerobot`` flow: one embodiment of a curated run as a LeRobot v3.0 dataset.

    plan     (driver)  every clip curated with the embodiment is an episode: its joints, poses
                       and kept frames from the store's small arrays, its content key from the
                       chunk records (``storage.episodes``); an earlier export in ``out``
                       lends the videos of episodes whose key did not change
    encode   (tasks)   one ``encode-episode`` task per new or changed episode on the Dask cluster
    publish  (driver)  data tables, episodes, tasks, statistics and info into the staging
                       folder beside ``out``, which then replaces ``out`` whole

Nothing is half-written: every file goes to ``.<name>.partial-<id>`` beside ``out`` (reused
videos as hard links), and ``out`` is swapped for it only when it is complete; a failure
removes the staging folder and leaves ``out`` as it was.
"""

from __future__ import annotations

import os
import shutil
import time
import uuid
from pathlib import Path

import numpy as np
from prefect import flow, get_run_logger
from pydantic import BaseModel, ConfigDict, Field

from handedit.flows.config import ClusterConfig
from handedit.storage import Location, open_store
from handedit.storage.store import jsonable, now_iso
from handedit.export import lerobot as lr

EXPORT_SCHEMA = 1


class ExportError(ValueError):
    """An export that cannot be made as asked (what, and what to do instead)."""


class LeRobotExportConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    source: str = Field(description="the curated run (folder or URL)")
    embodiment: str = Field(description="the embodiment whose episodes to export")
    out: str = Field(description="the dataset folder (local): created, or updated in place")
    include_source: bool = Field(False, description="also the human source video (observation.images.source)")
    fps: float | None = Field(None, gt=0, description="frames per second (default: the clips' own)")
    codec: str = Field("libsvtav1", description="video codec: libsvtav1 (LeRobot's default) or libx264")
    crf: int = Field(30, ge=0, le=63)
    clips: list[str] = Field(default_factory=list, description="only these clips (default: every curated one)")
    cluster: ClusterConfig = ClusterConfig()

    def options(self) -> dict:
        """What changes every episode's files: a change re-encodes everything."""
        return {"schema": EXPORT_SCHEMA, "include_source": self.include_source, "fps": self.fps, "codec": self.codec,
                "crf": self.crf}


def _audit_rejected(loc: Location, embodiment: str) -> dict[str, set[int]]:
    from handedit.storage.audit import release_view

    rejected, _ = release_view(loc)
    out: dict[str, set[int]] = {}
    for item in rejected:
        clip, emb, t = item.rsplit("/", 2)
        if emb == embodiment:
            out.setdefault(clip, set()).add(int(t))
    return out


def plan_episodes(cfg: LeRobotExportConfig) -> tuple[Location, list, list[str]]:
    """The run's episodes for ``cfg.embodiment`` (one clear error for each way there are none)."""
    from handedit.embodiments import get_embodiment
    from handedit.storage.episodes import has_embodiment, read_episode
    from handedit.storage.integrity import require_complete
    from handedit.storage.summary import curated_clips

    get_embodiment(cfg.embodiment)  # an unknown key: EmbodimentError naming the known ones
    loc = Location(cfg.source)
    root = open_store(loc)
    clips = curated_clips(root)
    unknown = sorted(set(cfg.clips) - set(clips))
    if unknown:
        raise ExportError(f"{loc.url}: no curated clip {', '.join(unknown[:5])}; its clips are {', '.join(clips[:10])}"
                          + (" ..." if len(clips) > 10 else ""))
    selected = [c for c in clips if not cfg.clips or c in cfg.clips]
    require_complete(loc, selected, "export lerobot")
    have = [c for c in selected if has_embodiment(root, c, cfg.embodiment)]
    if not have:
        embs = sorted({e for c in selected if f"clips/{c}/embodiments" in root
                       for e in root[f"clips/{c}/embodiments"].group_keys()})
        raise ExportError(f"{loc.url} has no clip curated with {cfg.embodiment!r} (its embodiments: "
                          f"{', '.join(embs) or 'none'}); curate it with `--embodiment {cfg.embodiment}` first, or "
                          f"export one of those")
    audit = _audit_rejected(loc, cfg.embodiment)
    episodes = [read_episode(root, c, cfg.embodiment, cfg.options(), audit.get(c, set())) for c in have]
    empty = [e.clip for e in episodes if not e.valid.any()]
    episodes = [e for e in episodes if e.valid.any()]
    if not episodes:
        raise ExportError(f"{loc.url}: none of the {len(have)} clip(s) curated with {cfg.embodiment!r} has a kept frame "
                          f"({', '.join(empty[:5])}): nothing to export; see `handedit ledger {loc.url}` for why")
    shapes = {(e.height, e.width) for e in episodes}
    if len(shapes) > 1:
        raise ExportError(f"{loc.url}: the clips have different frame sizes {sorted(shapes)}; a LeRobot dataset has one "
                          f"size per camera: export clips of one size at a time (--clip), or curate with one --resize")
    rates = {e.fps for e in episodes}
    if cfg.fps is None and len(rates) > 1:
        raise ExportError(f"{loc.url}: the clips have different frame rates {sorted(rates)}; give --fps")
    names = {tuple(e.joint_names) for e in episodes}
    if len(names) > 1:
        raise ExportError(f"{loc.url}: the {cfg.embodiment} clips were retargeted with different joint sets (a code "
                          f"or asset change between runs); curate them again with one version")
    return loc, episodes, empty


def _previous(out: Path, cfg: LeRobotExportConfig) -> dict[str, dict]:
    """clip -> its row in the export already in ``out`` (empty: none, or made with other options)."""
    info_path = out / "meta" / "info.json"
    if not out.exists():
        return {}
    if not info_path.is_file():
        if any(out.iterdir()):
            raise ExportError(f"{out} is not empty and holds no LeRobot dataset (no meta/info.json); export into a new "
                              f"or empty folder")
        return {}
    import json

    info = json.loads(info_path.read_text())
    made = (info.get("handedit") or {})
    if (made.get("robot") or {}).get("embodiment") != cfg.embodiment:
        raise ExportError(f"{out} holds the export of {(made.get('robot') or {}).get('embodiment') or 'another dataset'}, "
                          f"not {cfg.embodiment}: export each embodiment into its own folder")
    if made.get("export") != cfg.options():
        return {}  # other options: every episode is written again
    return {str(r["handedit/clip"]): r for r in lr.read_episodes(out)}


def preflight(cfg: LeRobotExportConfig) -> None:
    """Every refusal that needs no task, before a flow or cluster starts (one message each)."""
    if "://" in cfg.out:
        raise ExportError(f"--out {cfg.out}: a LeRobot dataset is written to a local folder (upload it afterwards)")
    from handedit.export.video import VideoSpec

    VideoSpec(cfg.codec, cfg.crf)
    _previous(Path(cfg.out).expanduser().resolve(), cfg)
    plan_episodes(cfg)


def _place(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


@flow(name="export-lerobot")
def export_lerobot(cfg: LeRobotExportConfig) -> dict:
    from handedit.benchmark.testset import instruction
    from handedit.embodiments import get_embodiment
    from handedit.export.robot import robot_info, wrist_poses, pose_vector
    from handedit.export.video import VideoSpec
    from handedit.flows.curate import code_version
    from handedit.flows.runner import task_runner
    from handedit.storage.episodes import task_text
    from handedit.tasks.export import EpisodeJob

    logger = get_run_logger()
    t0 = time.time()
    out = Path(cfg.out).expanduser().resolve()
    spec = VideoSpec(cfg.codec, cfg.crf)
    loc, episodes, empty = plan_episodes(cfg)
    previous = _previous(out, cfg)
    emb = get_embodiment(cfg.embodiment)
    robot = robot_info(cfg.embodiment)
    paper_instruction = instruction(emb.track, emb.name, emb.description)
    fps = cfg.fps or episodes[0].fps
    fps = int(fps) if float(fps).is_integer() else float(fps)
    keys = [lr.EGO] + ([lr.SOURCE] if cfg.include_source else [])
    h, w = episodes[0].height // 2 * 2, episodes[0].width // 2 * 2
    # old episodes keep their order, new ones follow in the run's order
    order = sorted(episodes, key=lambda e: (0, int(previous[e.clip]["episode_index"])) if e.clip in previous else (1, 0))
    sides = tuple(s for s in ("left", "right") if any(s in e.sides for e in order))
    layout = lr.Layout(sides, tuple(order[0].joint_names))
    feats = lr.features(layout, h, w, fps, keys, spec.info(h, w, fps))

    staging = out.parent / f".{out.name}.partial-{uuid.uuid4().hex[:8]}"
    staging.mkdir(parents=True)
    try:
        jobs, reused_stats = [], {}
        for i, e in enumerate(order):
            old = previous.get(e.clip)
            if old is not None and old.get("handedit/key") == e.key:
                for k in keys:
                    _place(out / lr.video_path(k, int(old["episode_index"])), staging / lr.video_path(k, i))
                reused_stats[e.clip] = {k: v for k, v in lr.unflat_stats(old).items() if k in keys}
            else:
                jobs.append(EpisodeJob(loc.store_url, e.clip, e.embodiment, e.n_frames, float(fps),
                                       tuple((k, str(staging / lr.video_path(k, i))) for k in keys), spec))
        encoded = {}
        if jobs:
            with cfg.cluster.connect() as address:
                for job, res in zip(jobs, encode_episodes.with_options(task_runner=task_runner(address))(jobs)):
                    encoded[job.clip] = res
        tasks = list(dict.fromkeys(task_text(e.meta, paper_instruction) for e in order))
        rows, all_stats, start = [], [], 0
        for i, e in enumerate(order):
            task = task_text(e.meta, paper_instruction)
            wrist = pose_vector(wrist_poses(cfg.embodiment, e.qpos, e.root_pose, e.sides))
            cols = lr.frame_columns(layout, e.sides, e.valid, e.hand_ok, e.qpos, wrist)
            T = e.n_frames
            cols.update(timestamp=(np.arange(T) / fps).astype(np.float32), frame_index=np.arange(T),
                        episode_index=np.full(T, i), index=start + np.arange(T), task_index=np.full(T, tasks.index(task)))
            lr.write_data(staging / lr.data_path(i), cols, feats)
            stats = {k: lr.numeric_stats(cols[k]) for k in feats if feats[k]["dtype"] != "video"}
            stats.update(encoded[e.clip]["stats"] if e.clip in encoded else reused_stats[e.clip])
            all_stats.append(stats)
            row = {"episode_index": i, "tasks": [task], "length": T, **{f"data/{k}": v for k, v in lr.chunk_file(i).items()},
                   "dataset_from_index": start, "dataset_to_index": start + T}
            for k in keys:
                row.update({f"videos/{k}/{n}": v for n, v in lr.chunk_file(i).items()})
                row.update({f"videos/{k}/from_timestamp": 0.0, f"videos/{k}/to_timestamp": T / fps})
            row.update(lr.flat_stats(stats))
            row.update({"handedit/clip": e.clip, "handedit/key": e.key, "handedit/kept_frames": int(e.valid.sum()),
                        "handedit/sides": ",".join(e.sides), "handedit/intrinsics": _json(e.intrinsics),
                        "handedit/virtual_base": _json(e.virtual_base), "handedit/instruction": paper_instruction})
            rows.append(row)
            start += T
        lr.write_episodes(staging, rows)
        lr.write_tasks(staging, tasks)
        lr.write_json(staging / "meta" / "stats.json", lr.jsonable_stats(lr.aggregate(all_stats)))
        intr = {_json(e.intrinsics) for e in order}
        extra = jsonable({
            "export": cfg.options(), "created": now_iso(), "code_version": code_version(),
            "source": {"store": loc.store_url, "clips": len(order), "skipped_without_kept_frames": empty},
            "robot": robot, "sides": list(sides), "instruction": paper_instruction,
            "camera": {"frame": "OpenCV camera (x right, y down, z forward), metres",
                       "intrinsics": order[0].intrinsics if len(intr) == 1 else None,
                       "per_episode": "meta/episodes column handedit/intrinsics (JSON)"},
            "virtual_base": "hand-arms: meta/episodes column handedit/virtual_base (JSON: side -> the chosen base, "
                            "4x4 camera_or_world_from_base)",
            "features": {lr.STATE: "actuated joints of each side (<side>_<joint>), radians or metres",
                         lr.ACTION: "the next frame's observation.state (the last frame: its own)",
                         lr.WRIST: "camera_from_hand-root of each side: position (m) and quaternion (x, y, z, w)",
                         lr.VALID: "QC kept this frame (false: rejected, its joints hold the last kept values)",
                         lr.HAND_VALID: "this side's joints are retargeted at this frame"},
        })
        lr.write_json(staging / "meta" / "info.json", lr.info(feats, fps, cfg.embodiment, len(order), start, len(tasks), extra))
        _swap(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    removed = sorted(set(previous) - {e.clip for e in order})
    summary = {"out": str(out), "episodes": len(order), "frames": start, "kept_frames": int(sum(e.valid.sum() for e in order)),
               "encoded": len(jobs), "reused": len(order) - len(jobs), "removed": removed, "skipped": empty,
               "seconds": round(time.time() - t0, 1)}
    logger.info("exported %d episodes (%d encoded, %d reused) to %s", len(order), len(jobs), len(order) - len(jobs), out)
    return summary


def _json(obj) -> str:
    import json

    return json.dumps(jsonable(obj), sort_keys=True)


def _swap(staging: Path, out: Path) -> None:
    """``staging`` becomes ``out``; the old ``out`` is removed only after."""
    old = None
    if out.exists():
        old = out.parent / f".{out.name}.old-{uuid.uuid4().hex[:8]}"
        os.rename(out, old)
    os.rename(staging, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@flow(name="export-episodes")
def encode_episodes(jobs: list) -> list[dict]:
    """One task per episode to encode, on the run's Dask cluster."""
    from handedit.tasks.export import encode_episode_task

    return [f.result() for f in [encode_episode_task.submit(j) for j in jobs]]


def run_export(cfg: LeRobotExportConfig) -> dict:
    from handedit.flows.api import run_api

    preflight(cfg)
    with run_api():
        return export_lerobot(cfg)


__all__ = ["ExportError", "LeRobotExportConfig", "export_lerobot", "plan_episodes", "preflight", "run_export"]
