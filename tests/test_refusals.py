"""Clear refusals instead of silence or tracebacks, and secrets that stay secret."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from _fake_openai import FakeOpenAI
from handedit.benchmark.editors import CommandEditor, EditorError, EditRequest, HttpEditorConfig, HttpImageEditor
from handedit.flows.benchmark import build_testset, run_editor
from handedit.flows.cli import main
from handedit.flows.evaluate import summarise
from handedit.metrics.vlm import JudgeConfig, VlmJudge
from handedit.secrets import MARK, install_log_filter, redact, register
from handedit.storage import open_store, read_ledger
from handedit.storage.benchmark import iter_jsonl, BenchDir

KEY = "sk-live-0123456789abcdefXYZ"
JUDGE_KEY = "sk-judge-9876543210fedcbaQRS"


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    from test_benchmark import write_curated_store

    tmp = tmp_path_factory.mktemp("refusals")
    store, _ = write_curated_store(tmp / "handedit.zarr")
    build_testset(store, tmp / "bench", 3)
    return tmp / "bench"


def test_redaction_covers_configured_keys_env_keys_and_headers(monkeypatch):
    monkeypatch.setenv("SOME_SERVICE_API_KEY", "envsecret-123456")
    register("configured-secret-42")
    text = ("got envsecret-123456 and configured-secret-42; {'Authorization': 'Bearer abcdefghijk'} "
            "authorization: Basic dXNlcjpwYXNz and bearer zzzzzzzzzz")
    clean = redact(text)
    for s in ("envsecret-123456", "configured-secret-42", "abcdefghijk", "dXNlcjpwYXNz", "zzzzzzzzzz"):
        assert s not in clean
    assert clean.count(MARK) == 5 and redact("status 1, ok true") == "status 1, ok true"


def test_no_secret_on_disk_or_in_output_with_an_echoing_server(bench, monkeypatch, capsys, caplog):
    with FakeOpenAI() as server:
        server.echo_errors = True
        monkeypatch.setenv("HANDEDIT_EDITOR_API_KEY", KEY)
        monkeypatch.setenv("HANDEDIT_EDITOR_BASE_URL", server.base_url)
        code = main(["bench", "run", "--bench", str(bench), "--editor", "http", "--name", "leaky", "--model",
                     "gpt-image-1", "--tries", "1"])
        judge = VlmJudge(JudgeConfig(base_url=server.base_url, api_key=JUDGE_KEY, max_tries=1, backoff_s=0))
        img = np.zeros((16, 16, 3), np.uint8)
        verdict = judge.judge(img, img, None, "Replace the human hand with a robot hand")
    assert code == 1  # every item failed
    out = capsys.readouterr()
    assert "401" in out.out and KEY not in out.out + out.err
    records = [r for _, r, _ in iter_jsonl(BenchDir(bench).records("leaky"))]
    assert records and all(r["status"] == "failed" and "401" in r["error"] and MARK in r["error"] for r in records)
    for f in Path(bench).rglob("*"):
        if f.is_file():
            assert KEY.encode() not in f.read_bytes(), f
    assert verdict.errors and all("401" in e and JUDGE_KEY not in e for e in verdict.errors)
    install_log_filter()
    logging.getLogger("handedit.test").warning("request failed: Authorization: Bearer %s", KEY)
    assert KEY not in caplog.text and MARK in caplog.text


def test_http_editor_timeout_is_a_setting_and_says_so(tmp_path):
    src = tmp_path / "src.png"
    import cv2

    cv2.imwrite(str(src), np.zeros((8, 8, 3), np.uint8))
    with FakeOpenAI() as server:
        server.delay_s = 2.0
        editor = HttpImageEditor(HttpEditorConfig(base_url=server.base_url, model="m", timeout_s=0.5))
        with pytest.raises(EditorError, match=r"timed out after 0.5 s") as exc:
            editor.edit(EditRequest("i", src, None, "x", tmp_path / "out.png"))
    assert exc.value.transient and "cannot reach" not in str(exc.value)


def test_wrong_size_predictions_are_flagged(bench, capsys):
    import shlex
    import sys

    shrink = (f"{shlex.quote(sys.executable)} -c \"import cv2,sys; im=cv2.imread(sys.argv[1]); "
              f"cv2.imwrite(sys.argv[2], im[:20, :30])\" {{src}} {{out}}")
    summary = run_editor(bench, "shrinker", CommandEditor(shrink), backoff_s=0)
    assert summary.ok == summary.ran > 0 and len(summary.wrong_size) == summary.ok
    assert summary.wrong_size[0]["size"] == "30x20"
    recs = [r for _, r, _ in iter_jsonl(BenchDir(bench).records("shrinker"))]
    assert all(r["flags"] == ["wrong_size"] and (r["width"], r["height"]) == (30, 20) and r["src_width"] > 30 for r in recs)


def test_judge_failures_are_counted_not_blank():
    rows = [{"id": "a", "track": "hand", "error": "", "psnr_full": 20.0, "vlm_error": "SC: no valid answer"},
            {"id": "b", "track": "hand", "error": "", "psnr_full": 22.0, "vlm_error": ""}]
    s = summarise(rows, {}, "ed", [])
    assert s["tracks"]["hand"]["n_scored"] == 2 and s["tracks"]["hand"]["n_judge_failed"] == 1
    assert s["n_judge_failures"] == 1 and s["judge_failures"][0]["id"] == "a"


def _config(tmp_path: Path, **fields) -> Path:
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump({"out": str(tmp_path / "out"), "clips": [{"kind": "synthetic", "n_frames": 8}],
                                    **fields}))
    return path


def test_misspelled_keys_name_the_closest_valid_one(tmp_path, capsys):
    assert main(["curate", "--config", str(_config(tmp_path, frames_per_chunks=4))]) == 2
    assert "frames_per_chunks: unknown key; did you mean 'frames_per_chunk'?" in capsys.readouterr().err
    assert main(["curate", "--config", str(_config(tmp_path, cluster={"n_worker": 1}))]) == 2
    assert "cluster.n_worker: unknown key; did you mean 'n_workers'?" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_refusals_before_the_cluster_starts(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("")
    assert main(["curate", "--demo", "--out", str(afile)]) == 2
    assert "is a file; give a folder" in capsys.readouterr().err
    assert main(["curate", "--demo", "--out", str(tmp_path / "x"), "--address", "tcp://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert "cannot reach the Dask scheduler at tcp://127.0.0.1:9" in err and "Traceback" not in err
    bad_id = _config(tmp_path, clips=[{"kind": "synthetic", "clip_id": "a/b", "n_frames": 8}])
    assert main(["curate", "--config", str(bad_id)]) == 2
    assert "clips[0]: invalid clip id 'a/b'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists() and not (tmp_path / "x").exists()


def test_nothing_curated_exits_nonzero_and_counts_agree_with_the_ledger(tmp_path, capsys, prefect_api, dask_cluster):
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(os.urandom(4096))
    out = tmp_path / "run"
    assert main(["curate", "--video", str(bad), "--out", str(out), "--address", dask_cluster.scheduler_address,
                 "--no-progress"]) == 1
    printed = capsys.readouterr()
    ledger = read_ledger(open_store(out))
    assert len(ledger) == 1 and ledger["reason_name"][0] == "SOURCE_UNREADABLE"
    assert "rejections: 1" in printed.out and "nothing was curated" in printed.err


class _Scripted:
    """A server on 127.0.0.1 answering every POST with one scripted reply; records headers."""

    def __init__(self, status: int, headers: dict | None = None, body: bytes = b"{}"):
        import threading
        from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

        self.seen: list[dict] = []
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):
                pass

            def _answer(self):
                outer.seen.append(dict(self.headers))
                self.rfile.read(int(self.headers.get("Content-Length", 0) or 0))
                self.send_response(status)
                for k, v in (headers or {}).items():
                    self.send_header(k, v)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            do_POST = do_GET = _answer

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
        self.httpd.shutdown()


def _request(tmp_path) -> EditRequest:
    import cv2

    src = tmp_path / "src.png"
    cv2.imwrite(str(src), np.zeros((8, 8, 3), np.uint8))
    return EditRequest("i", src, None, "Replace the human hand with a robot hand", tmp_path / "out.png")


def test_a_redirect_never_carries_the_key_to_another_host(tmp_path):
    thief = _Scripted(200)
    hop = _Scripted(302, {"Location": thief.url + "/steal"})
    try:
        editor = HttpImageEditor(HttpEditorConfig(base_url=hop.url + "/v1", api_key=KEY, model="m"))
        with pytest.raises(EditorError, match="redirected to .*/steal"):
            editor.edit(_request(tmp_path))
        judge = VlmJudge(JudgeConfig(base_url=hop.url + "/v1", api_key=JUDGE_KEY, max_tries=2, backoff_s=0))
        img = np.zeros((16, 16, 3), np.uint8)
        judge.judge(img, img, None, "Replace the human hand with a robot hand")
    finally:
        thief.close()
        hop.close()
    assert hop.seen and thief.seen == []  # the key went to the configured host only


def test_an_image_url_must_be_http(tmp_path):
    import json

    server = _Scripted(200, {"Content-Type": "application/json"},
                       json.dumps({"data": [{"url": "file:///etc/hostname"}]}).encode())
    try:
        editor = HttpImageEditor(HttpEditorConfig(base_url=server.url + "/v1", api_key=KEY, model="m"))
        with pytest.raises(EditorError, match="refusing file URL") as err:
            editor.edit(_request(tmp_path))
    finally:
        server.close()
    assert not err.value.transient


def test_redaction_finds_a_key_in_any_case_escaped_or_in_part():
    register(KEY)
    escaped = "".join("\\u%04x" % ord(c) for c in KEY)
    for text in (KEY.lower(), KEY.upper(), f"key={KEY[:16]}...", escaped, '{"key": "' + KEY + '"}'):
        clean = redact(f"error: {text} was rejected")
        assert MARK in clean and KEY[3:11].lower() not in clean.lower() and "\\u0073\\u006b" not in clean, clean
    assert redact("the hand moved 0.12 m in frame 123") == "the hand moved 0.12 m in frame 123"
