"""Pairs, samples and shards of a release.

A *pair* is one kept frame of one clip x embodiment: the source frame and its pseudo-GT
(every replaced hand at once; ``sides`` says which). A *sample* is what training code
loads for it from a WebDataset shard, under one key ``<clip>__<embodiment>__<frame>``:

    src.png  gt.png (harmonized)  composite.png (unharmonized)  human_mask.png
    robot_mask.png  object_mask.png (all zero when the source has no object mask)  json

``json`` holds the instruction (the paper's template), track, dataset, task, clip, frame,
sides, embodiment, the reference render id and the pair's content key. Every sample has
the same members, so Hugging Face ``datasets`` infers one schema.

Shard sizes: ~1 GB, the size WebDataset's authors recommend for streaming (large enough
for sequential reads at full bandwidth, small enough to shuffle and to retry one
download). A pair is three RGB PNGs and three masks; PNG keeps photographs at about half
their raw size, so a 960x540 pair is ~2.3 MB and a shard holds ~430 pairs
(``pairs_per_shard``). Shards are cut at clip boundaries inside one curate shard x
embodiment, by frame count (not kept count), so re-curating a clip or appending a clip to
a tree changes only the shard that holds it.

A shard's *key* hashes its pairs' content keys (which hash the digests of every stored
chunk a pair reads) and the sample format; two releases with the same key hold the same
bytes, so a release reuses its parent's shard without reading a pixel.
"""

from __future__ import annotations

import hashlib
import io
import json
import tarfile
from dataclasses import asdict, dataclass

import numpy as np

from handedit.images import encode_png

SAMPLE_FORMAT = 1
MEMBERS = ("src.png", "gt.png", "composite.png", "human_mask.png", "robot_mask.png", "object_mask.png", "json")
TARGET_SHARD_BYTES = 1 << 30
PNG_RATIO = 0.5  # PNG size / raw size for camera frames (masks compress to almost nothing)


def sample_key(clip: str, embodiment: str, frame: int) -> str:
    """A pair's WebDataset key, unique per pair. It holds no dot (WebDataset splits member
    names at the first): a name with dots has them replaced and a short hash of the name
    added, so ``take.1`` and ``take_1`` stay apart."""
    def part(name: str) -> str:
        if "." not in name:
            return name
        return name.replace(".", "_") + "-" + hashlib.blake2b(name.encode(), digest_size=4).hexdigest()

    return f"{part(clip)}__{part(embodiment)}__{int(frame):06d}"


@dataclass(frozen=True)
class Pair:
    clip: str
    embodiment: str
    frame: int
    sides: tuple[str, ...]
    track: str  # hand | hand_arm
    dataset: str
    task: str
    instruction: str
    reference: str  # the embodiment's reference render id (its bank entry)
    content: str  # content key: digests of the stored chunks this pair reads
    part: str = ""  # the release shard group it belongs to

    @property
    def id(self) -> str:
        return f"{self.clip}/{self.embodiment}/{self.frame}"

    @property
    def key(self) -> str:
        return sample_key(self.clip, self.embodiment, self.frame)

    def meta(self) -> dict:
        d = asdict(self)
        d["sides"] = list(self.sides)
        d.pop("part")
        return d


def pairs_per_shard(height: int, width: int, target_bytes: int = TARGET_SHARD_BYTES) -> int:
    """Pairs in a ~``target_bytes`` shard of frames this size (see module doc)."""
    pair = 3 * height * width * 3 * PNG_RATIO + 3 * height * width / 50
    return max(1, int(target_bytes // pair))


def content_key(frame: int, sides, chunk_digests: list[str], instruction: str, reference: str) -> str:
    payload = json.dumps([SAMPLE_FORMAT, frame, list(sides), sorted(chunk_digests), instruction, reference])
    return hashlib.blake2b(payload.encode(), digest_size=16).hexdigest()


def shard_key(pairs: list[Pair]) -> str:
    h = hashlib.blake2b(digest_size=16)
    h.update(f"format{SAMPLE_FORMAT}".encode())
    for p in sorted(pairs, key=lambda p: p.key):
        h.update(f"{p.key}:{p.content};".encode())
    return h.hexdigest()


def cut_parts(clips: list[tuple[str, int]], frames_per_part: int) -> dict[str, int]:
    """Clip -> part index: whole clips, in order, a new part once ``frames_per_part`` frames
    are reached (frame counts do not change when a clip is re-curated)."""
    out, part, filled = {}, 0, 0
    for clip, n in clips:
        if filled and filled + n > frames_per_part:
            part, filled = part + 1, 0
        out[clip] = part
        filled += n
    return out


def union_sides(masks: np.ndarray, sides_all: list[str], sides) -> np.ndarray:
    """(S,H,W) per-hand masks -> the union over the replaced ``sides`` (all when none match)."""
    idx = [sides_all.index(s) for s in sides if s in sides_all] or list(range(len(sides_all)))
    return np.asarray(masks)[idx].any(0)


def sample_files(pair: Pair, src, gt, composite, human_mask, robot_mask, object_mask) -> list[tuple[str, bytes]]:
    """The members of one sample (see module doc), in ``MEMBERS`` order."""
    obj = object_mask if object_mask is not None else np.zeros(np.asarray(human_mask).shape, bool)
    meta = {**pair.meta(), "has_object": object_mask is not None, "format": SAMPLE_FORMAT}
    images = (src, gt, composite, human_mask, robot_mask, obj)
    files = [(f"{pair.key}.{name}", encode_png(im)) for name, im in zip(MEMBERS[:-1], images)]
    return files + [(f"{pair.key}.json", json.dumps(meta, sort_keys=True).encode())]


class TarWriter:
    """A deterministic tar (fixed mtime, owner, mode; members in the order given): the same
    samples give the same bytes, hence the same content hash, in any process."""

    def __init__(self, fileobj):
        self.tar = tarfile.open(fileobj=fileobj, mode="w", format=tarfile.USTAR_FORMAT)

    def add(self, name: str, data: bytes) -> None:
        info = tarfile.TarInfo(name)
        info.size, info.mtime, info.mode, info.uid, info.gid = len(data), 0, 0o444, 0, 0
        info.uname = info.gname = ""
        self.tar.addfile(info, io.BytesIO(data))

    def close(self) -> None:
        self.tar.close()


def changelog(parent, current) -> dict:
    """Pairs added, removed and changed (same id, other content) against the parent."""
    old = dict(zip(parent["id"], parent["content"])) if parent is not None else {}
    new = dict(zip(current["id"], current["content"]))
    return {"added": sorted(set(new) - set(old)), "removed": sorted(set(old) - set(new)),
            "changed": sorted(k for k in set(new) & set(old) if new[k] != old[k])}
