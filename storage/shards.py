"""Shard bookkeeping beside the store: manifests, claims, run logs, index and ledger partitions.

A run over a source tree is cut into shards of clips (``handedit.flows.plan``). Every file
here is per shard, so nothing grows with the total number of clips or runs::

    <run>/shards/<shard>/manifest.json        clips, plan digest, complete?, the last run's summary
    <run>/shards/<shard>/claims/<gen>.json    driver claims (create-if-absent, one per generation)
    <run>/shards/<shard>/runs/<run-id>.json   one log per run that worked on the shard
    <run>/index/<shard>.parquet               one row per clip x embodiment x hand (frames, kept)
                                              and one per unreadable clip (its error)
    <run>/ledger/<shard>.parquet              the shard's rejections (stage, clip, ..., detail)

**Claims.** A driver takes a shard by creating ``claims/<g+1>.json``, where g is the newest
generation there, create-if-absent: of two drivers racing for the same generation exactly
one wins. A claim holds its holder (host, pid, run id) and a lease (``expires``), renewed
while the shard is worked on; the newest generation is the holder. A claim is *stale*
when its lease expired, or when its holder ran on this host and that process is gone (a
SIGKILLed driver); a stale claim is taken over by claiming the next generation. A finished
shard releases its claim (``released: true``). A driver that finds a live claim of someone
else skips the shard and says who holds it and how to take over.

**Partitions.** The shard flow rewrites its index and ledger partitions at the end of each
run (from the store, so they always agree with it); readers concatenate all partitions and,
when a clip appears in several (its shard boundaries moved), keep the newest.
"""

from __future__ import annotations

import os
import socket
import time
import uuid
from dataclasses import asdict, dataclass

from handedit.storage.layout import safe_name
from handedit.storage.location import Location

SHARDS = "shards"
INDEX = "index"
LEDGER = "ledger"
DEFAULT_LEASE_S = 600.0


def shard_dir(shard: str) -> str:
    return f"{SHARDS}/{safe_name('shard id', shard)}"


def read_manifest(loc: Location, shard: str) -> dict | None:
    return loc.read_json(f"{shard_dir(shard)}/manifest.json")


def write_manifest(loc: Location, shard: str, manifest: dict) -> None:
    loc.write_json(f"{shard_dir(shard)}/manifest.json", manifest)


def is_complete(manifest: dict | None, digest: str) -> bool:
    """A shard whose last run covered exactly this plan and left every chunk current."""
    return bool(manifest) and manifest.get("digest") == digest and manifest.get("complete") is True


def invalidate(loc: Location, clips) -> list[str]:
    """Mark the shards holding ``clips`` incomplete, so the next run re-plans them (after an
    operator changed something a shard digest cannot see: a review, a repair)."""
    clips = set(clips)
    index = read_partitions(loc, INDEX)
    shards = sorted(set(index.loc[index["clip"].isin(clips), "shard"])) if index is not None and "shard" in index else []
    for shard in shards:
        manifest = read_manifest(loc, shard)
        if manifest:
            write_manifest(loc, shard, {**manifest, "complete": False})
    return shards


def shard_ids(loc: Location) -> list[str]:
    return loc.listdir(SHARDS)


def write_run_log(loc: Location, shard: str, run_id: str, log: dict) -> None:
    loc.write_json(f"{shard_dir(shard)}/runs/{safe_name('run id', run_id)}.json", log)


def run_logs(loc: Location, shard: str) -> list[dict]:
    d = f"{shard_dir(shard)}/runs"
    return [x for name in loc.listdir(d) if (x := loc.read_json(f"{d}/{name}")) is not None]


# ----------------------------------------------------------------------------- claims


@dataclass
class Claim:
    shard: str
    generation: int
    holder: str  # run id of the driver
    host: str
    pid: int
    since: float
    expires: float
    released: bool = False

    def describe(self) -> str:
        return (f"run {self.holder} (host {self.host}, pid {self.pid}), lease until "
                f"{time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(self.expires))}")


def new_holder() -> str:
    return f"{time.strftime('%Y%m%dT%H%M%S')}-{uuid.uuid4().hex[:8]}"


def _claims(loc: Location, shard: str) -> list[Claim]:
    d = f"{shard_dir(shard)}/claims"
    out = []
    for name in loc.listdir(d):
        if name.endswith(".json") and name[:-5].isdigit():
            data = loc.read_json(f"{d}/{name}")
            if data:
                out.append(Claim(**{k: v for k, v in data.items() if k in Claim.__dataclass_fields__}))
    return sorted(out, key=lambda c: c.generation)


def current_claim(loc: Location, shard: str) -> Claim | None:
    claims = _claims(loc, shard)
    return claims[-1] if claims else None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def is_stale(claim: Claim, now: float | None = None) -> bool:
    now = time.time() if now is None else now
    if claim.released or claim.expires < now:
        return True
    return claim.host == socket.gethostname() and not _pid_alive(claim.pid)


def try_claim(loc: Location, shard: str, holder: str, lease_s: float = DEFAULT_LEASE_S,
              take_over: bool = False) -> tuple[Claim | None, Claim | None]:
    """(my claim, None) when taken; (None, the live holder's claim) when someone else holds it.

    ``take_over``: claim even over a live claim (an operator who knows its holder is gone).
    """
    cur = current_claim(loc, shard)
    if cur is not None and cur.holder == holder and not cur.released:
        return cur, None
    if cur is not None and not is_stale(cur) and not take_over:
        return None, cur
    gen = (cur.generation + 1) if cur else 1
    now = time.time()
    mine = Claim(shard, gen, holder, socket.gethostname(), os.getpid(), now, now + lease_s)
    if loc.create_json(f"{shard_dir(shard)}/claims/{gen:08d}.json", asdict(mine)):
        return mine, None
    return None, current_claim(loc, shard)  # another driver won this generation


def renew(loc: Location, claim: Claim, lease_s: float = DEFAULT_LEASE_S) -> bool:
    """Extend my lease; False when a newer generation took the shard over."""
    cur = current_claim(loc, claim.shard)
    if cur is None or cur.generation != claim.generation:
        return False
    claim.expires = time.time() + lease_s
    loc.write_json(f"{shard_dir(claim.shard)}/claims/{claim.generation:08d}.json", asdict(claim))
    return True


def release(loc: Location, claim: Claim) -> None:
    cur = current_claim(loc, claim.shard)
    if cur is not None and cur.generation == claim.generation:
        claim.released = True
        loc.write_json(f"{shard_dir(claim.shard)}/claims/{claim.generation:08d}.json", asdict(claim))


# ----------------------------------------------------------------------------- partitions


def partition_rel(kind: str, shard: str) -> str:
    return f"{kind}/{safe_name('shard id', shard)}.parquet"


def write_partition(loc: Location, kind: str, shard: str, frame) -> None:
    loc.write_table(partition_rel(kind, shard), frame)


def has_partitions(loc: Location, shard: str) -> bool:
    """Whether a shard's index and ledger partitions are there (a complete shard without
    them runs again: every chunk is skipped, and both are written anew)."""
    return all(loc.exists(partition_rel(kind, shard)) for kind in (INDEX, LEDGER))


def read_partitions(loc: Location, kind: str, key: str = "clip"):
    """All partitions of ``kind`` (index | ledger); a clip found in several keeps the newest."""
    frame = loc.read_tables(kind)
    if frame is None or not len(frame):
        return frame
    if "written" in frame.columns and key in frame.columns:
        newest = frame.groupby(key)["written"].transform("max")
        frame = frame[frame["written"] == newest]
    return frame.reset_index(drop=True)
