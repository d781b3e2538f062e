"""Editor adapters: one request = source image + reference render + instruction -> image.

- ``HttpImageEditor``: an OpenAI-compatible ``POST {base_url}/images/edits`` (multipart:
  ``model``, ``prompt``, ``image[]`` = source then reference render; answer
  ``data[0].b64_json`` or ``data[0].url``). Base URL, model and key come from
  settings or the environment (HANDEDIT_EDITOR_BASE_URL / _MODEL / _API_KEY, or
  OPENAI_API_KEY).
- ``CommandEditor``: a local model behind a command line. The template's placeholders
  ``{src} {ref} {prompt_file} {out} {id}`` (and ``{gt}``, for oracle baselines only) are
  substituted with shell-quoted paths; the command must write the image to ``{out}``.

Errors carry ``transient`` so the runner retries network hiccups and 429/5xx answers,
but not a 400 or a command that exits non-zero twice the same way.
"""

from __future__ import annotations

import base64
import json
import os
import shlex
import subprocess
import urllib.error
import urllib.request
import uuid
from dataclasses import dataclass
from pathlib import Path

from pydantic import BaseModel, Field, SecretStr

from handedit.http import Redirected, fetch_url, open_url
from handedit.secrets import redact, register


class EditorError(RuntimeError):
    def __init__(self, message: str, transient: bool = False):
        super().__init__(redact(message))  # an error body may echo the request's headers
        self.transient = transient


@dataclass
class EditRequest:
    item_id: str
    src_path: Path
    ref_path: Path | None
    instruction: str
    out_path: Path
    gt_path: Path | None = None


class HttpEditorConfig(BaseModel):
    base_url: str
    model: str
    api_key: SecretStr | None = None
    timeout_s: float = Field(300.0, gt=0, description="seconds per try (`bench run --timeout`)")
    size: str | None = Field(None, description="optional 'WxH' sent as size; default: the API's default")

    @classmethod
    def from_env(cls, **overrides) -> "HttpEditorConfig":
        base = overrides.pop("base_url", None) or os.environ.get("HANDEDIT_EDITOR_BASE_URL")
        model = overrides.pop("model", None) or os.environ.get("HANDEDIT_EDITOR_MODEL")
        if not base or not model:
            raise EditorError("the HTTP editor needs a base URL and a model: pass --base-url/--model or set "
                              "HANDEDIT_EDITOR_BASE_URL and HANDEDIT_EDITOR_MODEL")
        key = overrides.pop("api_key", None) or os.environ.get("HANDEDIT_EDITOR_API_KEY") or os.environ.get("OPENAI_API_KEY")
        return cls(base_url=base, model=model, api_key=key, **overrides)


class HttpImageEditor:
    name_prefix = "http"

    def __init__(self, cfg: HttpEditorConfig):
        self.cfg = cfg
        self.model = cfg.model
        register(cfg.api_key)

    def edit(self, req: EditRequest) -> bytes:
        fields = [("model", self.cfg.model), ("prompt", req.instruction), ("n", "1")]
        if self.cfg.size:
            fields.append(("size", self.cfg.size))
        files = [("image[]", req.src_path)] + ([("image[]", req.ref_path)] if req.ref_path else [])
        body, ctype = _multipart(fields, files)
        headers = {"Content-Type": ctype}
        if self.cfg.api_key:
            headers["Authorization"] = f"Bearer {self.cfg.api_key.get_secret_value()}"
        url = self.cfg.base_url.rstrip("/") + "/images/edits"
        try:
            with open_url(urllib.request.Request(url, body, headers, method="POST"), timeout=self.cfg.timeout_s) as r:
                reply = json.loads(r.read())
        except Redirected as exc:
            raise EditorError(f"{url}: {exc.reason}") from None
        except urllib.error.HTTPError as exc:
            detail = exc.read()[:300].decode(errors="replace")
            raise EditorError(f"HTTP {exc.code} from {url}: {detail}", transient=exc.code == 429 or exc.code >= 500) from None
        except (urllib.error.URLError, TimeoutError, ConnectionError) as exc:
            if isinstance(exc, TimeoutError) or isinstance(getattr(exc, "reason", None), TimeoutError):
                raise EditorError(f"{url} timed out after {self.cfg.timeout_s:g} s (raise --timeout for slow models)",
                                  transient=True) from None
            raise EditorError(f"cannot reach {url}: {exc}", transient=True) from None
        except json.JSONDecodeError as exc:
            raise EditorError(f"{url} answered non-JSON ({exc})", transient=True) from None
        try:
            data = reply["data"][0]
        except (KeyError, IndexError, TypeError):
            raise EditorError(f"{url} answered without data[0]: {str(reply)[:200]}") from None
        if data.get("b64_json"):
            return base64.b64decode(data["b64_json"])
        if data.get("url"):
            try:
                return fetch_url(data["url"], timeout=self.cfg.timeout_s)
            except Redirected as exc:
                raise EditorError(f"the edited image {str(data['url'])[:80]}: {exc.reason}") from None
            except (urllib.error.URLError, TimeoutError, ValueError) as exc:
                refused = isinstance(exc, urllib.error.URLError) and str(exc.reason).startswith("refusing")
                raise EditorError(f"cannot download the edited image {str(data['url'])[:80]}: {exc}",
                                  transient=not refused) from None
        raise EditorError(f"{url} answered neither b64_json nor url")


def _multipart(fields: list[tuple[str, str]], files: list[tuple[str, Path]]) -> tuple[bytes, str]:
    boundary = uuid.uuid4().hex
    parts = []
    for k, v in fields:
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n{v}\r\n'.encode())
    for k, path in files:
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"; filename="{Path(path).name}"\r\n'
                     f"Content-Type: image/png\r\n\r\n".encode() + Path(path).read_bytes() + b"\r\n")
    parts.append(f"--{boundary}--\r\n".encode())
    return b"".join(parts), f"multipart/form-data; boundary={boundary}"


class CommandEditor:
    """A local model as a command template, e.g. ``python run_qwen.py --in {src} --ref {ref} --prompt-file {prompt_file} --out {out}``."""

    def __init__(self, template: str, model: str = "local", timeout_s: float = 1800.0):
        self.template = template
        self.model = model
        self.timeout_s = timeout_s
        if "{out}" not in template:
            raise EditorError("the command template must contain {out} (where the edited image is written)")

    def edit(self, req: EditRequest) -> bytes:
        prompt_file = req.out_path.with_suffix(".prompt.txt")
        req.out_path.parent.mkdir(parents=True, exist_ok=True)
        prompt_file.write_text(req.instruction)
        tmp_out = req.out_path.with_suffix(".tmp.png")
        q = lambda p: shlex.quote(str(p)) if p else "''"  # noqa: E731
        cmd = self.template.format(src=q(req.src_path), ref=q(req.ref_path), prompt_file=q(prompt_file),
                                   out=q(tmp_out), id=shlex.quote(req.item_id), gt=q(req.gt_path))
        try:
            proc = subprocess.run(cmd, shell=True, capture_output=True, text=True, timeout=self.timeout_s)
        except subprocess.TimeoutExpired:
            raise EditorError(f"command timed out after {self.timeout_s:.0f}s: {cmd}", transient=True) from None
        finally:
            prompt_file.unlink(missing_ok=True)
        if proc.returncode != 0:
            tmp_out.unlink(missing_ok=True)
            raise EditorError(f"command exited {proc.returncode}: {cmd}\n{proc.stderr.strip()[-500:]}")
        if not tmp_out.is_file():
            raise EditorError(f"command succeeded but wrote no image at {tmp_out}: {cmd}")
        data = tmp_out.read_bytes()
        tmp_out.unlink(missing_ok=True)
        return data
