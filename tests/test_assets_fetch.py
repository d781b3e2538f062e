"""``handedit assets fetch`` against a real HTTP server on 127.0.0.1 that serves commit archives
built from ../shared/assets/robots in the upstream repositories' layout (GitHub codeload:
``/{owner}/{repo}/tar.gz/{commit}``, every path under ``{repo}-{commit}/``), with HTTP ranges."""

from __future__ import annotations

import io
import tarfile
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from handedit.embodiments.fetch import FOLDERS
from handedit.embodiments.fetch import build_table, fetch


def _archives(robots_dir: Path, tamper: str | None = None) -> dict[str, bytes]:
    """{url path: tar.gz bytes}, one per repository@commit; ``tamper`` flips a byte of that folder's URDF."""
    members: dict[tuple[str, str], list[tuple[str, Path]]] = {}
    for folder, spec in FOLDERS.items():
        for rel in spec["files"]:
            arc = f"{spec['repo_path']}/{rel}" if spec["repo_path"] else rel
            members.setdefault((spec["repo"], spec["commit"]), []).append((arc, robots_dir / folder / rel, folder))
    out = {}
    for (repo, commit), files in members.items():
        buf = io.BytesIO()
        with tarfile.open(fileobj=buf, mode="w:gz", compresslevel=1) as tar:
            for arc, path, folder in files:
                data = path.read_bytes()
                if folder == tamper and path.suffix == ".urdf":
                    data = data.replace(b"<robot", b"<robot ", 1)
                info = tarfile.TarInfo(f"{repo.split('/')[1]}-{commit}/{arc}")
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
        out[f"/{repo}/tar.gz/{commit}"] = buf.getvalue()
    return out


class _Server:
    """Serves ``archives``; ``cut[path] = n`` ends the next response for ``path`` after n bytes."""

    def __init__(self, archives: dict[str, bytes]):
        self.archives, self.cut, self.log = archives, {}, []
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):
                pass

            def do_GET(self):
                body = server.archives.get(self.path)
                rng = self.headers.get("Range")
                server.log.append((self.path, rng))
                if body is None:
                    self.send_error(404)
                    return
                start = int(rng.split("=")[1].split("-")[0]) if rng else 0
                self.send_response(206 if rng else 200)
                self.send_header("Content-Length", str(len(body) - start))
                self.end_headers()
                n = server.cut.pop(self.path, None)
                self.wfile.write(body[start:] if n is None else body[start:start + n])
                if n is not None:
                    self.close_connection = True

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture(scope="module")
def archives(robots_dir) -> dict[str, bytes]:
    return _archives(robots_dir)


def test_table_pins_the_shared_copy(robots_dir):
    """The package's table is exactly what a verified copy gives (digests of every file)."""
    sources = {f: (s["repo"], s["commit"], s["repo_path"]) for f, s in FOLDERS.items()}
    assert build_table(robots_dir, sources) == FOLDERS
    keys = {k for s in FOLDERS.values() for k in s["robots"]}
    assert {"rohand", "revo2", "allegro", "ur5e", "jaka_zu7"} <= keys and len(FOLDERS) == 21


def test_fetch_everything_then_the_roster_finds_it_without_settings(archives, monkeypatch, tmp_path, capsys):
    from handedit.embodiments import asset_status, list_embodiments
    from handedit.flows.cli import main

    server = _Server(archives)
    try:
        monkeypatch.setenv("HANDEDIT_CACHE_DIR", str(tmp_path / "cache"))
        monkeypatch.delenv("HANDEDIT_ASSET_DIRS", raising=False)
        assert sum(asset_status(e)[0] for e in list_embodiments()) <= 2  # only what PyPI packages ship
        assert main(["assets", "fetch", "--base-url", server.url]) == 0
        out = capsys.readouterr().out
        assert "21/21 robot folders" in out and "licence: MIT" in out and "rohand" in out
        assert len(server.log) == len(archives)  # one archive per repository, dex-urdf's 13 folders in one
        available = [e.id for e in list_embodiments() if asset_status(e)[0]]
        assert len(available) == 24 and "rm75_rohand" in available and "rh5dg2" not in available
        rel = tmp_path / "cache/assets/hands/rohand/urdf/rohand_right_rel.urdf"
        assert "package://" not in rel.read_text() and 'filename="../meshes_r/base_link.STL"' in rel.read_text()
        server.log.clear()
        assert main(["assets", "fetch", "--base-url", server.url]) == 0  # all in place: nothing downloaded
        assert server.log == [] and capsys.readouterr().out.count("present") == 21
    finally:
        server.close()


def test_interrupted_download_resumes_with_a_range(archives, tmp_path):
    server = _Server(archives)
    try:
        path = next(p for p in archives if "rohand" in p)
        server.cut[path] = 4096
        first = fetch(tmp_path, ["rohand"], base_url=server.url)
        assert not first.ok
        part = next((tmp_path / ".downloads").glob("*.part"))
        assert part.stat().st_size == 4096
        second = fetch(tmp_path, ["rohand"], base_url=server.url)
        assert second.ok and [r.status for r in second.results] == ["fetched"]
        assert server.log[-1] == (path, "bytes=4096-")
        assert not list((tmp_path / ".downloads").iterdir())  # the verified archive is dropped
        assert (tmp_path / "hands/rohand/urdf/rohand_right_rel.urdf").is_file()
    finally:
        server.close()


def test_failures_are_per_robot_and_leave_no_bad_file(robots_dir, tmp_path, capsys):
    from handedit.flows.cli import main

    served = _archives(robots_dir, tamper="hands/wuji_hand")
    served.pop(next(p for p in served if "rohand" in p))  # this repository's archive is gone
    server = _Server(served)
    try:
        code = main(["assets", "fetch", "--dest", str(tmp_path), "--base-url", server.url,
                     "--robot", "wuji", "--robot", "rohand", "--robot", "revo2"])
        out = capsys.readouterr().out
        assert code == 1
        assert "fetched  hands/revo2_hand" in out
        assert "failed   hands/rohand" in out and "HTTP 404" in out
        assert "failed   hands/wuji_hand" in out and "sha256" in out and "right.urdf" in out
        assert not (tmp_path / "hands/wuji_hand/urdf/right.urdf").exists()  # mismatching bytes never land
        assert (tmp_path / "hands/wuji_hand/LICENSE").is_file()  # its verified files do
        assert "HANDEDIT_ASSET_DIRS" in out  # a non-default --dest says how to use it
        assert main(["assets", "fetch", "--dest", str(tmp_path), "--robot", "nope"]) == 2
        assert "unknown robot(s) ['nope']" in capsys.readouterr().out
    finally:
        server.close()
