"""The one owner of the release layout: versions, content-keyed shards, publishing.

    <releases>/                              a local folder or an object-store prefix
      shards/<key>.tar                       WebDataset shards, named by the content key of the
                                             pairs they hold; shared by every release, never rewritten
      shards/<key>.json                      its sha256, size and pairs, written once the shard is whole
      videos/<key>/source.mp4, pseudo_gt.mp4, robot_mask.mp4
                                             ``--videos``: one clip x embodiment, every frame of the
                                             clip in order (frame-aligned), named by content key
      videos/<key>.json                      its files' sha256 and sizes, frames, the kept-frame
                                             index: written once the videos are whole
      v0001/pairs.parquet                    every pair of the release with its metadata and shard
      v0001/changelog.json, changelog.md     added / removed / changed pairs against the parent
      v0001/datasheet.json, datasheet.md     counts, kept rates, rejection breakdown
      v0001/manifest.json                    written last: its existence publishes v0001

Publishing is one create-if-absent write of ``manifest.json`` (``O_EXCL`` locally, a
conditional PUT on S3), so an interrupted release leaves no visible version, two
concurrent releases cannot both publish the same number, and a published manifest is
never overwritten. Files of an unpublished attempt are rewritten by the next attempt.
A release reuses a parent's shard by key: nothing is copied or rewritten.
"""

from __future__ import annotations

import re

from handedit.storage.location import Location

RELEASE_SCHEMA = 1
SHARDS_DIR = "shards"
VIDEOS_DIR = "videos"
_VERSION = re.compile(r"^v(\d{4,})$")


def split_release(release: str) -> tuple[Location, str]:
    """``<releases>/<version>`` (a path or URL) -> (the releases location, the version)."""
    base, _, version = str(release).rstrip("/").rpartition("/")
    return Location(base or "."), version


def version_name(n: int) -> str:
    return f"v{n:04d}"


def shard_rel(key: str) -> str:
    return f"{SHARDS_DIR}/{key}.tar"


def shard_info_rel(key: str) -> str:
    """The sidecar written after a shard is complete: its hash, size and pair count."""
    return f"{SHARDS_DIR}/{key}.json"


def video_rel(key: str, name: str) -> str:
    return f"{VIDEOS_DIR}/{key}/{name}.mp4"


def video_info_rel(key: str) -> str:
    return f"{VIDEOS_DIR}/{key}.json"


def versions(loc: Location) -> list[str]:
    """Published versions, oldest first (a folder without its manifest is not published)."""
    names = [n for n in loc.listdir("") if _VERSION.match(n)]
    return sorted((n for n in names if loc.exists(f"{n}/manifest.json")), key=lambda n: int(n[1:]))


def latest(loc: Location) -> str | None:
    v = versions(loc)
    return v[-1] if v else None


def next_version(loc: Location) -> str:
    last = latest(loc)
    return version_name(int(last[1:]) + 1 if last else 1)


def read_release(loc: Location, version: str) -> dict:
    manifest = loc.read_json(f"{version}/manifest.json")
    if manifest is None:
        raise FileNotFoundError(f"{loc.path(version)} is not a published release (no manifest.json); "
                                f"published: {', '.join(versions(loc)) or 'none'}")
    return manifest


def read_pairs(loc: Location, version: str):
    import io

    import pandas as pd

    data = loc.read_bytes(f"{version}/pairs.parquet")
    if data is None:
        raise FileNotFoundError(f"{loc.path(version, 'pairs.parquet')} is missing")
    return pd.read_parquet(io.BytesIO(data))


def publish(loc: Location, version: str, manifest: dict) -> bool:
    """Make ``version`` visible; False when another release published that number first."""
    return loc.create_json(f"{version}/manifest.json", manifest)


def shard_urls(loc: Location, version: str) -> list[str]:
    """The release's shard files as paths or URLs (what ``webdataset`` / ``datasets`` take)."""
    manifest = read_release(loc, version)
    return [loc.path(s["path"]) if loc.is_local else f"{loc.protocol}://{loc.path(s['path'])}"
            for s in manifest["shards"]]


class ShardReader:
    """Members of a release's samples, read from its shards (each shard fetched once)."""

    def __init__(self, loc: Location):
        self.loc = loc
        self._tars: dict = {}

    def member(self, shard: str, key: str, name: str) -> bytes:
        import io
        import tarfile

        if shard not in self._tars:
            data = self.loc.read_bytes(shard_rel(shard))
            if data is None:
                raise FileNotFoundError(f"{self.loc.path(shard_rel(shard))} is missing")
            self._tars[shard] = tarfile.open(fileobj=io.BytesIO(data))
        return self._tars[shard].extractfile(f"{key}.{name}").read()
