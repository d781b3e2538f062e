"""``handedit assets fetch``: the roster's public robots from their upstream repositories.

Each robot folder of the roster's asset layout (dex-urdf's ``hands/``, ``arms/``,
``assembly/``) comes from one repository at a pinned commit (``asset_table.FOLDERS``: which
files, their sha256, the licence). Downloads are the repositories' commit archives
(``{base_url}/{owner}/{repo}/tar.gz/{commit}``, GitHub's codeload layout: every path under
one ``{repo}-{commit}/`` folder), one per repository however many robots it holds.

- Resumable: an archive downloads into ``.downloads/*.part`` with HTTP ``Range``; a file that
  is already in place with the right digest is never fetched again; a robot whose files are
  all in place costs nothing.
- Verified: every file is checked against the table before it is moved into place
  (atomically), so a folder holds the upstream bytes or nothing.
- Per robot: a failure (unreachable server, missing archive, wrong digest) is reported for
  the robots it concerns, with the reason and the fix, and the others still land.
- ROS packages' ``package://`` mesh URIs are rewritten into ``*_rel.urdf`` copies beside the
  originals (the files the roster loads), as in the shared asset folder.

The default destination is the user cache (``$HANDEDIT_CACHE_DIR/assets`` or
``~/.cache/handedit/assets``), which the roster searches after ``$HANDEDIT_ASSET_DIRS``.
"""

from __future__ import annotations

import hashlib
import http.client
import os
import re
import shutil
import tarfile
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

from handedit.digests import file_sha256
from handedit.embodiments.asset_table import FOLDERS
from handedit.files import atomic_write

BASE_URL = "https://codeload.github.com"
CHUNK = 1 << 20


def default_dest() -> Path:
    from handedit.embodiments.compose import cache_root

    return cache_root() / "assets"


@dataclass
class FolderResult:
    folder: str
    robots: tuple[str, ...]
    license: str
    status: str  # "present" | "fetched" | "failed"
    detail: str = ""
    files: int = 0


@dataclass
class FetchReport:
    dest: Path
    results: list[FolderResult] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return all(r.status != "failed" for r in self.results)


def _missing(dest: Path, folder: str, spec: dict) -> dict[str, str]:
    """{path in folder: sha256} of the files not yet in place with the right digest."""
    out = {}
    for rel, digest in spec["files"].items():
        p = dest / folder / rel
        if not (p.is_file() and file_sha256(p) == digest):
            out[rel] = digest
    return out


def _download(url: str, part: Path, timeout: float) -> Path:
    """``url`` into ``part`` (resuming what is there), renamed without ``.part`` when complete."""
    done = part.with_suffix("")
    if done.is_file():
        return done
    part.parent.mkdir(parents=True, exist_ok=True)
    have = part.stat().st_size if part.is_file() else 0
    req = urllib.request.Request(url, headers={"Range": f"bytes={have}-"} if have else {})
    try:
        resp = urllib.request.urlopen(req, timeout=timeout)
    except urllib.error.HTTPError as e:
        if e.code == 416 and have:  # nothing left to send: the part is complete
            part.rename(done)
            return done
        raise
    with resp:
        resumed = have and resp.status == 206  # a server without ranges sends it all again
        length = resp.headers.get("Content-Length")
        expected = None if length is None else int(length) + (have if resumed else 0)
        with open(part, "ab" if resumed else "wb") as f:
            try:
                shutil.copyfileobj(resp, f, CHUNK)
            except http.client.HTTPException as e:
                raise OSError(f"connection broke off ({e!r})") from e
    got = part.stat().st_size
    if expected is not None and got < expected:
        raise OSError(f"connection broke off after {got} of {expected} bytes")
    part.rename(done)
    return done


def _rewrite_packages(dest: Path, folder: str, spec: dict) -> None:
    """``x.urdf`` -> ``x_rel.urdf`` with ``package://NAME/`` made relative to the URDF."""
    for urdf in spec.get("rel_urdfs", ()):
        src = dest / folder / urdf
        text = src.read_text(encoding="utf-8")
        for pkg, pkg_dir in spec["packages"].items():
            rel = os.path.relpath(dest / folder / pkg_dir, src.parent).replace(os.sep, "/")
            text = text.replace(f"package://{pkg}/", f"{rel}/")
        atomic_write(src.with_name(src.stem + "_rel.urdf"), text.encode("utf-8"))


def _extract(archive: Path, wanted: dict[str, tuple[str, str, str]], dest: Path) -> dict[str, str]:
    """Move the archive members in ``wanted`` ({member suffix: (folder, rel, sha256)}) into place;
    returns {folder: error} for folders with a missing or mismatching member."""
    errors: dict[str, str] = {}
    seen = set()
    try:
        with tarfile.open(archive, "r:*") as tar:
            for m in tar:
                key = m.name.partition("/")[2]  # drop the {repo}-{commit}/ folder
                if key not in wanted or not m.isfile():
                    continue
                folder, rel, digest = wanted[key]
                target = dest / folder / rel
                target.parent.mkdir(parents=True, exist_ok=True)
                tmp = target.with_name(f".{target.name}.tmp")
                h = hashlib.sha256()
                with tar.extractfile(m) as src, open(tmp, "wb") as f:
                    for block in iter(lambda: src.read(CHUNK), b""):
                        h.update(block)
                        f.write(block)
                if h.hexdigest() != digest:
                    tmp.unlink()
                    errors.setdefault(folder, f"{rel}: sha256 {h.hexdigest()[:12]}... is not the pinned {digest[:12]}...")
                    continue
                os.replace(tmp, target)
                seen.add(key)
    except (tarfile.TarError, EOFError, OSError) as e:
        archive.unlink(missing_ok=True)  # a damaged archive is fetched again next time
        for folder, _, _ in wanted.values():
            errors.setdefault(folder, f"archive {archive.name} is damaged ({e}); it was removed, run again")
        return errors
    for key, (folder, rel, _) in wanted.items():
        if key not in seen and folder not in errors:
            errors[folder] = f"{rel} is not in the archive"
    return errors


def fetch(dest: Path | None = None, robots: list[str] | None = None, base_url: str = BASE_URL,
          timeout: float = 60.0, log=print) -> FetchReport:
    """Fetch the folders holding ``robots`` (manifest keys; default all) into ``dest``."""
    dest = Path(dest or default_dest()).expanduser()
    unknown = sorted(set(robots or ()) - {k for s in FOLDERS.values() for k in s["robots"]})
    if unknown:
        known = sorted(k for s in FOLDERS.values() for k in s["robots"])
        raise ValueError(f"unknown robot(s) {unknown}; known: {known}")
    chosen = {f: s for f, s in FOLDERS.items() if not robots or set(s["robots"]) & set(robots)}
    report = FetchReport(dest)
    by_archive: dict[tuple[str, str], list[str]] = {}
    pending: dict[str, dict[str, str]] = {}
    for folder, spec in chosen.items():
        missing = _missing(dest, folder, spec)
        if missing:
            pending[folder] = missing
            by_archive.setdefault((spec["repo"], spec["commit"]), []).append(folder)
        else:
            _rewrite_packages(dest, folder, spec)
            report.results.append(FolderResult(folder, tuple(spec["robots"]), spec["license"], "present",
                                               files=len(spec["files"])))
    for (repo, commit), folders in by_archive.items():
        url = f"{base_url.rstrip('/')}/{repo}/tar.gz/{commit}"
        log(f"fetching {repo}@{commit[:10]} for {', '.join(folders)} ...")
        errors: dict[str, str]
        try:
            archive = _download(url, dest / ".downloads" / f"{repo.replace('/', '+')}-{commit}.tar.gz.part", timeout)
        except (urllib.error.URLError, OSError, TimeoutError) as e:
            why = f"HTTP {e.code}" if isinstance(e, urllib.error.HTTPError) else str(getattr(e, "reason", e))
            errors = {f: f"download of {url} failed ({why}); check the network (or --base-url) and run again: "
                         f"what was downloaded is kept and resumed" for f in folders}
        else:
            wanted = {}
            for f in folders:
                prefix = FOLDERS[f]["repo_path"]
                for rel, digest in pending[f].items():
                    wanted[f"{prefix}/{rel}" if prefix else rel] = (f, rel, digest)
            errors = _extract(archive, wanted, dest)
            if not errors:
                archive.unlink(missing_ok=True)
        for f in folders:
            spec = FOLDERS[f]
            if f in errors:
                report.results.append(FolderResult(f, tuple(spec["robots"]), spec["license"], "failed", errors[f]))
                continue
            _rewrite_packages(dest, f, spec)
            report.results.append(FolderResult(f, tuple(spec["robots"]), spec["license"], "fetched",
                                               files=len(spec["files"])))
    report.results.sort(key=lambda r: r.folder)
    return report


# ---------------------------------------------------------------------------------------
# the table itself is generated from a verified copy (the shared asset folder)

def build_table(robots_dir: Path, sources: dict[str, tuple[str, str, str]]) -> dict[str, dict]:
    """FOLDERS from a verified local copy: ``sources`` maps a folder to (repo, commit, path of
    the folder inside the repository); every file but the ``*_rel.urdf`` rewrites is pinned."""
    import json

    manifest = json.loads((robots_dir / "manifest.json").read_text())
    out = {}
    for folder, (repo, commit, repo_path) in sorted(sources.items()):
        root = robots_dir / folder
        files = {p.relative_to(root).as_posix(): file_sha256(p) for p in sorted(root.rglob("*"))
                 if p.is_file() and not p.name.endswith("_rel.urdf")}
        keys = sorted(k for k, v in manifest.items() if v["urdf"].startswith(folder + "/"))
        rel = sorted(p.relative_to(root).as_posix().replace("_rel.urdf", ".urdf") for p in root.rglob("*_rel.urdf"))
        packages = {}
        for r in rel:
            for pkg in re.findall(r"package://([^/]+)/", (root / r).read_text(encoding="utf-8")):
                packages[pkg] = _package_dir(root, pkg, files)
        out[folder] = {"repo": repo, "commit": commit, "repo_path": repo_path, "robots": keys,
                       "license": "; ".join(manifest[k]["license"] for k in keys) if keys else "",
                       "files": files, "rel_urdfs": rel, "packages": packages}
    return out


def _package_dir(root: Path, pkg: str, files: dict[str, str]) -> str:
    """Where ROS package ``pkg`` lives in the folder: the directory named like it (or the folder
    itself, when the repository is the package)."""
    dirs = {str(Path(f).parent) for f in files}
    named = sorted({d[: d.index(pkg) + len(pkg)] for d in dirs if f"/{pkg}/" in f"/{d}/"}, key=len)
    return named[0] if named else ""
