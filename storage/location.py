"""Where a run lives: a local folder or an object store prefix, behind one small interface.

``--out`` is a run folder (``runs/demo``) or an fsspec URL (``s3://bucket/prefix``); the
Zarr store is ``<out>/handedit.zarr`` (an ``--out`` ending in ``.zarr`` names the store
itself, its parent is the run folder) and the bookkeeping files (shard manifests, claims,
run logs, the index and ledger partitions) lie beside it. Everything else in the project
reads and writes through a ``Location``, so the same code runs on a laptop disk and on S3.

Object-store credentials and endpoints come from the environment the way the provider's
SDK reads them (``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``AWS_ENDPOINT_URL`` for
S3-compatible servers), or as JSON in ``HANDEDIT_STORAGE_OPTIONS``; they never travel in a
task's parameters (which Prefect records).

Writes of whole files are atomic: a local file is written to a temporary name and renamed,
an object-store PUT is atomic by itself. ``create`` is create-if-absent (``O_EXCL`` on a
file system, a conditional PUT with ``If-None-Match: *`` on S3), the primitive that shard
claims are built on.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import tempfile
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import Any

from handedit.files import atomic_write  # noqa: F401  (re-exported: storage's callers use it from here)

import fsspec

STORE_NAME = "handedit.zarr"
OPTIONS_ENV = "HANDEDIT_STORAGE_OPTIONS"


def _storage_options(protocol: str) -> dict:
    raw = os.environ.get(OPTIONS_ENV)
    opts = json.loads(raw) if raw else {}
    endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
    if protocol in ("s3", "s3a") and endpoint and "endpoint_url" not in opts.get("client_kwargs", {}):
        opts.setdefault("client_kwargs", {})["endpoint_url"] = endpoint
    return opts


class Location:
    """A run folder (see module doc). Cheap to build; picklable (the filesystem is rebuilt)."""

    def __init__(self, out: str | os.PathLike):
        text = str(out)
        if text.endswith(".zarr") or text.endswith(".zarr/"):
            text = text.rstrip("/")[: -len(".zarr")]
            text, _, store = text.rpartition("/")
            self.store_name = f"{store}.zarr"
            text = text or "."
        else:
            self.store_name = STORE_NAME
        self.protocol = text.split("://", 1)[0] if "://" in text else "file"
        if self.protocol == "file":
            text = str(Path(text.removeprefix("file://")).expanduser().absolute())
        self.url = text.rstrip("/")

    def __repr__(self) -> str:
        return f"Location({self.url!r})"

    def __reduce__(self):
        return (Location, (self.store_url,))

    def __eq__(self, other) -> bool:
        return isinstance(other, Location) and other.store_url == self.store_url

    def __hash__(self) -> int:
        return hash(self.store_url)

    @property
    def is_local(self) -> bool:
        return self.protocol == "file"

    @property
    def fs(self) -> fsspec.AbstractFileSystem:
        return _filesystem(self.protocol)

    @property
    def root(self) -> str:
        """The run folder's path inside ``fs``."""
        return self.url.split("://", 1)[1] if "://" in self.url else self.url

    @property
    def store_url(self) -> str:
        return f"{self.url}/{self.store_name}"

    def path(self, *parts: str) -> str:
        return "/".join([self.root, *parts])

    # -- the Zarr store -----------------------------------------------------------
    def zarr_store(self, read_only: bool = False):
        import zarr

        if self.is_local:
            return zarr.storage.LocalStore(self.path(self.store_name), read_only=read_only)
        return zarr.storage.FsspecStore.from_url(self.store_url, storage_options=_storage_options(self.protocol),
                                                 read_only=read_only)

    def store_exists(self) -> bool:
        return self.exists(f"{self.store_name}/zarr.json")

    # -- files --------------------------------------------------------------------
    def exists(self, rel: str) -> bool:
        return self.fs.exists(self.path(rel))

    def read_bytes(self, rel: str) -> bytes | None:
        try:
            return self.fs.cat_file(self.path(rel))
        except FileNotFoundError:
            return None

    def write_bytes(self, rel: str, data: bytes) -> None:
        """Atomic whole-file write (see module doc)."""
        p = self.path(rel)
        if self.is_local:
            atomic_write(p, data)
        else:
            self.fs.pipe_file(p, data)

    def put_file(self, local: str | os.PathLike, rel: str) -> None:
        """Move (local) or upload (object storage) a finished local file to ``rel``, whole."""
        p = self.path(rel)
        if self.is_local:
            Path(p).parent.mkdir(parents=True, exist_ok=True)
            os.chmod(local, 0o644)
            shutil.move(str(local), p)
        else:
            self.fs.put_file(str(local), p)
            os.unlink(local)

    def create(self, rel: str, data: bytes) -> bool:
        """Create-if-absent; False when the file already exists (someone else made it)."""
        p = self.path(rel)
        if self.is_local:
            Path(p).parent.mkdir(parents=True, exist_ok=True)
            try:
                fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                return False
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            return True
        try:
            self.fs.pipe_file(p, data, mode="create")
        except FileExistsError:
            return False
        return True

    def remove(self, rel: str) -> None:
        try:
            self.fs.rm_file(self.path(rel))
        except FileNotFoundError:
            pass

    def listdir(self, rel: str) -> list[str]:
        """Names directly under ``rel`` (empty when it does not exist)."""
        try:
            entries = self.fs.ls(self.path(rel), detail=False, refresh=True)
        except (FileNotFoundError, NotADirectoryError):
            return []
        return sorted(e.rstrip("/").rsplit("/", 1)[-1] for e in entries)

    def find(self, rel: str) -> set[str]:
        """Every file under ``rel``, recursively, as paths relative to ``rel`` (one listing:
        a directory walk locally, paged LIST calls on object storage)."""
        base = self.path(rel).rstrip("/")
        if self.is_local:
            out = set()
            for dirpath, _, files in os.walk(base):
                prefix = os.path.relpath(dirpath, base)
                out.update(f if prefix == "." else f"{prefix}/{f}" for f in files)
            return out
        self.fs.invalidate_cache(base)
        try:
            found = self.fs.find(base)
        except FileNotFoundError:
            return set()
        return {p[len(base) + 1:] for p in found if p.startswith(base + "/")}

    def read_json(self, rel: str) -> Any:
        data = self.read_bytes(rel)
        return None if data is None else json.loads(data)

    def write_json(self, rel: str, obj: Any) -> None:
        self.write_bytes(rel, json.dumps(obj, sort_keys=True, indent=1, default=str).encode())

    def create_json(self, rel: str, obj: Any) -> bool:
        return self.create(rel, json.dumps(obj, sort_keys=True, indent=1, default=str).encode())

    # -- entry folders: one create-once JSON file per entry, read in the order given ----
    def add_entry(self, rel_dir: str, obj: dict) -> dict:
        """Add ``obj``, stamped with the time, as its own file under ``rel_dir`` (named by time
        then a random suffix): written once, never rewritten, so a crash loses nothing already
        added and several writers never share a file. Returns the stamped entry."""
        import uuid
        from datetime import datetime, timezone

        now = datetime.now(timezone.utc)
        stamped = {**obj, "time": now.isoformat()}
        while not self.create_json(f"{rel_dir}/{now.strftime('%Y%m%dT%H%M%S.%f')}-{uuid.uuid4().hex[:12]}.json", stamped):
            pass  # a 48-bit collision within the same microsecond: another suffix
        return stamped

    def entries(self, rel_dir: str) -> list[dict]:
        """Every entry of ``rel_dir`` in the order added (file names sort by time)."""
        out = []
        for name in sorted(self.find(rel_dir)):
            data = self.read_json(f"{rel_dir}/{name}")
            if data is not None:
                out.append(data)
        return out

    # -- tables -------------------------------------------------------------------
    def write_table(self, rel: str, frame) -> None:
        buf = io.BytesIO()
        frame.to_parquet(buf, index=False)
        self.write_bytes(rel, buf.getvalue())

    def read_tables(self, rel_dir: str):
        """Every Parquet file under ``rel_dir``, concatenated, with a ``partition`` column."""
        import pandas as pd

        frames = []
        for name in self.listdir(rel_dir):
            if name.endswith(".parquet"):
                data = self.read_bytes(f"{rel_dir}/{name}")
                if data is not None:
                    f = pd.read_parquet(io.BytesIO(data))
                    f["partition"] = name[: -len(".parquet")]
                    frames.append(f)
        return pd.concat(frames, ignore_index=True) if frames else None


@lru_cache(maxsize=8)
def _filesystem(protocol: str) -> fsspec.AbstractFileSystem:
    return fsspec.filesystem(protocol, **_storage_options(protocol))


def location_of(root) -> Location:
    """The run folder of an open Zarr group (local or fsspec store)."""
    store = root.store
    if hasattr(store, "fs") and hasattr(store, "path"):  # FsspecStore
        proto = store.fs.protocol[0] if isinstance(store.fs.protocol, (tuple, list)) else store.fs.protocol
        return Location(f"{proto}://{store.path.rstrip('/')}")
    return Location(str(store.root))


@contextmanager
def staged_dir(final: str | os.PathLike):
    """Build a folder beside its final place and move it there only once complete: an
    interrupted build leaves the previous folder (or none), never a half-written one.
    A rebuild replaces the previous folder as a whole."""
    final = Path(final).absolute()
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=final.parent, prefix=f".{final.name}.partial-"))
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = final.parent / f".{final.name}.old-{os.getpid()}"
    if final.exists():
        os.replace(final, old)
    os.replace(tmp, final)
    shutil.rmtree(old, ignore_errors=True)


