"""The ``release`` flow: publish an immutable, versioned release of every kept pair.

    plan     (driver)  from each curated run: its clips in curate-shard order, every kept
                       frame x embodiment as a pair with its content key (from the chunk
                       records' digests, no pixels read), cut into shards at clip boundaries
    shards   (tasks)   one ``write-release-shard`` task per shard whose key the parent
                       release does not already hold, on the Dask cluster; with ``videos``,
                       one ``write-release-videos`` task per clip x embodiment whose videos
                       no earlier release wrote (content-keyed like shards)
    publish  (driver)  pairs.parquet, changelog, datasheet, then manifest.json, created
                       only if absent: the version becomes visible at once and only whole

Before reading anything it runs the presence check of ``handedit verify`` on every
source and refuses to publish a hole. See ``handedit.release`` for the sample format and
``handedit.storage.releases`` for the layout.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import replace
from pathlib import Path

import pandas as pd
from prefect import flow, get_run_logger
from pydantic import BaseModel, ConfigDict, Field

from handedit.embodiments import get_embodiment
from handedit.flows.api import run_url
from handedit.flows.config import ClusterConfig, dashboard_link
from handedit.reasons import Reason
from handedit.release import datasheet
from handedit.release.samples import Pair, TARGET_SHARD_BYTES, changelog, content_key, cut_parts, pairs_per_shard, shard_key
from handedit.storage import Location, StoreError, Unit, open_store, read_records
from handedit.storage.provenance import pending_review
from handedit.storage.integrity import require_complete
from handedit.storage.ledger import read_ledger, status_counts, unit_sides
from handedit.storage.releases import RELEASE_SCHEMA, latest, next_version, publish, read_pairs, read_release, video_info_rel
from handedit.storage.store import jsonable, now_iso, read_array
from handedit.storage.summary import curated_clips

READS = ("ingest", "segment")  # clip units a pair reads; plus its embodiment's composite, harmonize, qc


class ReleaseConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    sources: list[str] = Field(description="curated runs (folders or URLs) whose kept pairs the release holds")
    out: str = Field(description="the releases folder or URL (versions v0001, v0002, ... and shards/)")
    embodiments: list[str] = Field(default_factory=list, description="only these (default: every curated one)")
    target_shard_bytes: int = Field(TARGET_SHARD_BYTES, gt=0, description="~size of one WebDataset shard")
    cluster: ClusterConfig = ClusterConfig()
    videos: bool = Field(False, description="also frame-aligned MP4s (source, pseudo-GT, robot mask) per clip x "
                         "embodiment, beside the shards (storage.releases: videos/)")
    publish_unchanged: bool = Field(True, description="publish a new version even when its pairs and shards are the "
                                    "parent's (the scheduled release sets False: nothing changed, nothing published)")


def _digests(records: dict, chunk: int) -> list[str]:
    rec = records.get(chunk)
    return sorted(rec.outputs.values()) if rec is not None else []


def _stage_versions(root, clip: str, emb: str) -> dict:
    """Version and parameters of the stages a pair reads, as the curate run stored them."""
    out = {}
    for stage in ("ingest", "segment", "retarget", "render", "composite", "harmonize", "qc"):
        u = Unit(stage, clip) if stage in READS else Unit(stage, clip, embodiment=emb)
        attrs = root[u.path].attrs if u.path in root else {}
        out[stage] = {"version": attrs.get("version"), "params": attrs.get("params")}
    return out


def by_part(pairs: list[Pair]) -> dict[str, list[Pair]]:
    """Pairs grouped by their ``part``, in first-seen order (one pass)."""
    groups: dict[str, list[Pair]] = {}
    for p in pairs:
        groups.setdefault(p.part, []).append(p)
    return groups


def plan_pairs(loc: Location, root, clips: list[str], embodiments: list[str], target_bytes: int) -> tuple[list[Pair], dict]:
    """Every kept pair of one curated run's ``clips``, each with its shard part (see module doc)."""
    from handedit.benchmark.testset import instruction
    from handedit.storage.audit import release_view
    from handedit.storage.shards import read_manifest, shard_ids

    clips = set(clips)
    f = int(root.attrs["frames_per_chunk"])
    manifests = {s: read_manifest(loc, s) or {} for s in shard_ids(loc)}
    group_of = {c: s for s, m in manifests.items() for c in m.get("clips", [])}
    order = [c for m in manifests.values() for c in m.get("clips", []) if c in clips]
    order += sorted(clips - set(order))
    pairs: list[Pair] = []
    fingerprints, stages, n_frames, hw = {}, {}, {}, None
    held_back = 0
    rejected_by_audit, audits = release_view(loc)  # pairs reviewers rejected stay out of every release
    left_out = []
    for clip in order:
        info = dict(root[Unit("ingest", clip).path].attrs.get("info") or {})
        meta = info.get("meta") or {}
        fingerprints[clip], n_frames[clip] = info.get("fingerprint", ""), int(info["n_frames"])
        hw = hw or (int(info["height"]), int(info["width"]))
        clip_records = {u: read_records(root, Unit(u, clip)) for u in READS}
        embs = root[f"clips/{clip}/embodiments"].group_keys() if f"clips/{clip}/embodiments" in root else []
        for emb in sorted(e for e in embs if not embodiments or e in embodiments):
            qc_unit = Unit("qc", clip, embodiment=emb)
            if qc_unit.path not in root:
                continue
            stages = stages or _stage_versions(root, clip, emb)
            e = get_embodiment(emb)
            text = instruction(e.track, e.name, e.description)
            reference = f"{emb}:bank-view-0"
            status = read_array(root[qc_unit.path]["status"])
            hs = read_array(root[qc_unit.path]["hand_status"]) if "hand_status" in root[qc_unit.path] else None
            sides = unit_sides(root, qc_unit)
            emb_records = {s: read_records(root, Unit(s, clip, embodiment=emb)) for s in ("composite", "harmonize", "qc")}
            part = f"{group_of.get(clip, 'clips')}/{emb}"
            unreviewed = pending_review(read_records(root, Unit("retarget", clip, embodiment=emb))) if e.track == "hand_arm" else set()
            for t in map(int, (status == Reason.OK).nonzero()[0]):
                replaced = tuple(s for k, s in enumerate(sides) if hs is None or hs[t, k] == Reason.OK)
                if unreviewed & set(replaced):
                    held_back += 1
                    continue
                why = rejected_by_audit.get(f"{clip}/{emb}/{t}")
                if why:
                    left_out.append({"id": f"{clip}/{emb}/{t}", **why})
                    continue
                digests = [d for recs in (*clip_records.values(), *emb_records.values()) for d in _digests(recs, t // f)]
                pairs.append(Pair(clip, emb, t, replaced, e.track, str(meta.get("dataset", "")),
                                  str(meta.get("task") or meta.get("task_folder") or ""), text, reference,
                                  content_key(t, replaced, digests, text, reference), part))
    # cut each (curate shard, embodiment) group into parts of whole clips, by frame count
    per_part = pairs_per_shard(*(hw or (1, 1)), target_bytes)
    out = []
    for group, members in by_part(pairs).items():
        cut = cut_parts([(c, n_frames[c]) for c in dict.fromkeys(p.clip for p in members)], per_part)
        out += [replace(p, part=f"{group}/{cut[p.clip]:04d}") for p in members]
    source = {"store": loc.store_url, "clips": len(order), "stages": stages,
              "fingerprint": hashlib.sha256(json.dumps(fingerprints, sort_keys=True).encode()).hexdigest(),
              "frames_per_chunk": f, "pairs_per_shard": per_part, "held_back_unreviewed": held_back,
              "left_out_by_audit": left_out, "audits": audits}
    return out, source


@flow(name="release")
def release(cfg: ReleaseConfig) -> dict:
    from handedit.flows.curate import code_version
    from handedit.flows.runner import task_runner
    from handedit.tasks.release import ShardJob

    logger = get_run_logger()
    t0 = time.time()
    loc = Location(cfg.out)
    parent = latest(loc)
    parent_manifest = read_release(loc, parent) if parent else None
    parent_pairs = read_pairs(loc, parent) if parent else None
    # a parent's shard is reused only if its bytes were checked against the records when it was written
    reusable = {s["key"]: s for s in (parent_manifest or {}).get("shards", []) if s.get("verified")}
    pairs, sources, jobs, curated, left_out, audits = [], [], [], [], [], {}
    video_jobs, videos = [], {}
    for store in cfg.sources:
        src = Location(store)
        root = open_store(src)
        clips = curated_clips(root)
        require_complete(src, clips, "release")
        curated.append((root, clips))
        got, source = plan_pairs(src, root, clips, cfg.embodiments, cfg.target_shard_bytes)
        left_out += source["left_out_by_audit"]
        source["left_out_by_audit"] = len(source["left_out_by_audit"])  # the ids and why: changelog.json
        audits.update({f"{src.url}#{name}": a for name, a in source["audits"].items()})
        sources.append(source)
        if cfg.videos:
            for job in plan_videos(cfg.out, src, root, got):
                done = loc.read_json(video_info_rel(job.key))
                if done and done.get("verified"):
                    videos[job.key] = {**_video_entry(done), "reused": True}
                else:
                    video_jobs.append(job)
        for members in by_part(got).values():
            key = shard_key(members)
            pairs += [(p, key) for p in members]
            if key not in reusable:
                jobs.append(ShardJob(cfg.out, src.store_url, key, tuple(p.meta() for p in members)))
    shards = {k: {**_shard_entry(s), "reused": True} for k, s in reusable.items()}
    from handedit.flows.api import api_is_temporary

    # a release is permanent: it keeps only links that outlive this command
    links = {"Prefect run": None if api_is_temporary() else run_url(), "Dask dashboard": None}
    if jobs or video_jobs:
        with cfg.cluster.connect() as address:
            links["Dask dashboard"] = dashboard_link(address) if cfg.cluster.address else None
            shard_res, video_res = write_shards.with_options(task_runner=task_runner(address))(jobs, video_jobs)
            for res in shard_res:
                shards[res["key"]] = {**_shard_entry(res), "reused": False}
            for res in video_res:
                videos[res["key"]] = {**_video_entry(res), "reused": False}
    used = list(dict.fromkeys(k for _, k in pairs))
    table = pd.DataFrame([{**p.meta(), "id": p.id, "sides": ",".join(p.sides), "shard": k} for p, k in pairs],
                         columns=["id", "clip", "embodiment", "frame", "sides", "track", "dataset", "task", "instruction",
                                  "reference", "content", "shard"])
    changes = changelog(parent_pairs, table)
    if parent and not cfg.publish_unchanged and not jobs and not video_jobs and not any(changes[k] for k in ("added", "removed", "changed")) \
            and set(used) == set(reusable):
        note = f"nothing changed since {parent} (the same {len(table)} pairs in the same {len(used)} shards): no version published"
        logger.info(note)
        return {**parent_manifest, "published": False, "note": note}
    version = next_version(loc)
    sheet = datasheet.build(table, _status(curated), _ledger(curated),
                            sorted(set(table["embodiment"])) if len(table) else [])
    sheet["audits"] = audits
    loc.write_table(f"{version}/pairs.parquet", table)
    changes["left_out_by_audit"] = sorted(left_out, key=lambda r: r["id"])
    loc.write_json(f"{version}/changelog.json", {"parent": parent, **changes})
    loc.write_bytes(f"{version}/changelog.md", _changelog_md(version, parent, changes).encode())
    loc.write_json(f"{version}/datasheet.json", sheet)
    loc.write_bytes(f"{version}/datasheet.md", datasheet.markdown(sheet, f"handedit release {version}").encode())
    manifest = jsonable({
        "schema": RELEASE_SCHEMA, "version": version, "parent": parent, "created": now_iso(), "code_version": code_version(),
        "links": links, "sources": sources, "counts": {"pairs": len(table), "shards": len(used), "shards_reused": sum(
            1 for k in used if shards[k]["reused"]), "added": len(changes["added"]), "removed": len(changes["removed"]),
            "changed": len(changes["changed"]), "left_out_by_audit": len(left_out),
            **({"videos": len(videos), "videos_reused": sum(1 for v in videos.values() if v["reused"])} if cfg.videos else {})},
        "shards": [shards[key] for key in used],
        **({"videos": sorted(videos.values(), key=lambda v: (v["clip"], v["embodiment"]))} if cfg.videos else {}),
    })
    if not publish(loc, version, manifest):
        raise StoreError(f"another release published {version} of {cfg.out} while this one ran; run `handedit release` "
                         f"again to publish the next version")
    logger.info("published %s: %d pairs in %d shards (%d reused) in %.0f s", version, len(table), len(used),
                manifest["counts"]["shards_reused"], time.time() - t0)
    _publish_artifact(loc, manifest, changes)
    return manifest


def _publish_artifact(loc: Location, manifest: dict, changes: dict) -> None:
    """The release in Prefect's UI (the run's Artifacts tab): version, counts, changes and where
    its manifest, datasheet and changelog are."""
    from prefect.artifacts import create_markdown_artifact

    from handedit.markdown import md

    v, c = manifest["version"], manifest["counts"]
    lines = [f"# release {md(v)} (parent {md(manifest['parent'] or '-')})", "",
             f"- pairs: {c['pairs']} in {c['shards']} shard(s), {c['shards_reused']} reused from the parent",
             f"- changes: {c['added']} added, {c['removed']} removed, {c['changed']} changed"
             + (f" (first added: {md(', '.join(changes['added'][:5]))})" if changes["added"] else ""),
             f"- manifest: `{loc.path(v, 'manifest.json')}`",
             f"- datasheet: `{loc.path(v, 'datasheet.md')}`",
             f"- changelog: `{loc.path(v, 'changelog.md')}`"]
    create_markdown_artifact("\n".join(lines), key="release", description=f"handedit release {v}")


@flow(name="release-shards")
def write_shards(jobs: list, video_jobs: list = ()) -> tuple[list[dict], list[dict]]:
    """One task per new shard (and per new clip x embodiment's videos) on the run's Dask
    cluster; one that fails after its retries fails the release (nothing is published)."""
    from handedit.tasks.release import write_release_shard, write_release_videos

    shards = [write_release_shard.submit(j) for j in jobs]
    videos = [write_release_videos.submit(j) for j in video_jobs]
    return [f.result() for f in shards], [f.result() for f in videos]


VIDEO_SCHEMA = 1


def plan_videos(out: str, src: Location, root, pairs: list[Pair]) -> list:
    """One ``VideoJob`` per clip x embodiment with pairs, keyed by the content of every frame
    its videos show (the chunk records' digests) and the frames it keeps."""
    from handedit.export.video import PAIR_SPECS
    from handedit.storage.episodes import content_key as episode_key
    from handedit.tasks.release import VideoJob

    kept: dict[tuple[str, str], list[int]] = {}
    for p in pairs:
        kept.setdefault((p.clip, p.embodiment), []).append(p.frame)
    jobs = []
    options = {"schema": VIDEO_SCHEMA, "specs": {k: vars(v) for k, v in PAIR_SPECS.items()}}
    for (clip, emb), frames in kept.items():
        info = dict(root[Unit("ingest", clip).path].attrs.get("info") or {})
        frames = sorted(frames)
        key = hashlib.sha256(f"{episode_key(root, clip, emb, options, [])}:{frames}".encode()).hexdigest()[:32]
        jobs.append(VideoJob(out, src.store_url, key, clip, emb, int(info["n_frames"]), float(info.get("fps") or 30.0),
                             tuple(frames)))
    return jobs


def _video_entry(info: dict) -> dict:
    return {**{k: info[k] for k in ("key", "clip", "embodiment", "frames", "fps", "files")},
            "kept_frames": len(info["kept"]), "index": video_info_rel(info["key"]), "verified": bool(info.get("verified"))}


SHARD_FIELDS = ("key", "path", "sha256", "bytes", "pairs")


def _shard_entry(info: dict) -> dict:
    return {**{k: info[k] for k in SHARD_FIELDS}, "verified": bool(info.get("verified"))}


def _status(curated: list) -> pd.DataFrame:
    """Frames per (stage, status) over every source's released clips."""
    df = pd.concat([status_counts(root, clips=clips) for root, clips in curated], ignore_index=True)
    return df.groupby(["stage", "status"], sort=False, as_index=False)["frames"].sum()


def _ledger(curated: list) -> pd.DataFrame:
    return pd.concat([read_ledger(root, clips=clips) for root, clips in curated], ignore_index=True)


def _changelog_md(version: str, parent: str | None, changes: dict) -> str:
    from handedit.markdown import md

    out = [f"# {md(version)} against {md(parent or '(no parent: first release)')}", ""]
    for kind in ("added", "removed", "changed"):
        ids = changes[kind]
        out += [f"## {kind}: {len(ids)}", ""] + [f"- {md(i)}" for i in ids[:1000]]
        if len(ids) > 1000:
            out.append(f"- ... {len(ids) - 1000} more (changelog.json)")
        out.append("")
    left = changes.get("left_out_by_audit") or []
    out += [f"## left out: rejected by a reviewer in an audit: {len(left)}", ""]
    out += [f"- {md(r['id'])}: audit {md(r['audit'])}, cause {md(r['cause'] or 'not given')}, "
            f"{r['reviewers']} reviewer(s)" for r in left[:1000]]
    if len(left) > 1000:
        out.append(f"- ... {len(left) - 1000} more (changelog.json)")
    return "\n".join(out) + "\n"


@flow(name="release-from-config", log_prints=True)
def release_from_config(sources: list[str], out: str, cluster_path: str | None = None, shard_mb: float = 1024.0) -> dict:
    """Deployment entry point: publish the next release of curated runs ``sources``."""
    return release(ReleaseConfig(sources=sources, out=out, target_shard_bytes=int(shard_mb * (1 << 20)),
                                 cluster=_cluster(cluster_path)))


@flow(name="curate-and-release", log_prints=True)
def curate_and_release(config_path: str, releases: str, cluster_path: str | None = None, out: str | None = None,
                       shard_mb: float = 1024.0) -> dict:
    """The scheduled incremental release: curate the config's sources (only new or changed
    chunks cost compute), then publish the next version (only changed shards are written)."""
    from handedit.flows.curate import curate, load_config

    config = load_config(config_path, cluster_path, out)
    summary = curate(config)
    manifest = release(ReleaseConfig(sources=[config.out], out=releases, target_shard_bytes=int(shard_mb * (1 << 20)),
                                     cluster=config.cluster, publish_unchanged=False))
    if manifest.get("published", True):
        print(f"curated: {summary['shards']}; published {manifest['version']}: {manifest['counts']}")
    else:
        print(f"curated: {summary['shards']}; nothing changed since {manifest['version']}: no version published")
    return {"curate": {k: summary[k] for k in ("shards", "stages", "errors")}, "release": manifest}


def _cluster(path: str | None) -> ClusterConfig:
    if not path:
        return ClusterConfig()
    import yaml

    spec = yaml.safe_load(Path(path).read_text()) or {}
    return ClusterConfig.model_validate(spec.get("cluster", spec))


def run_release(cfg: ReleaseConfig) -> dict:
    from handedit.flows.api import run_api

    with run_api():
        return release(cfg)


__all__ = ["ReleaseConfig", "release", "run_release", "plan_pairs", "release_from_config", "curate_and_release"]
