"""The VLM judge (paper appendix "VLM-Based Judgment Protocol").

Two calls per item to any OpenAI-compatible chat endpoint: Semantic Consistency (SC:
source, edited image, instruction, URDF reference render) and Perceptual Quality (PQ:
edited image only), with the paper's prompt templates verbatim. Sub-scores are 1-5;
each aspect keeps its minimum (conservative, as VIEScore), normalised (s-1)/4, and
S_vlm = sqrt(SC * PQ).

Answers are cached on disk by a content hash of (model, prompt, images), so a re-run
or a resumed run never pays twice. A malformed answer (no JSON, a missing field, a
score outside 1-5) is retried; after the last try it is recorded as a failure.
"""

from __future__ import annotations

import base64
import hashlib
import json
import math
import os
import re
import threading
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, Field, SecretStr

from handedit.http import open_url
from handedit.secrets import redact, register

SC_PROMPT = """You are evaluating an image editing result for a benchmark on egocentric hand-to-dexterous-robot image editing.

You are given:
(1) a source image showing a human hand or hand-arm interacting with an object;
(2) an edited image;
(3) a text instruction describing the target robot embodiment;
(4) a URDF reference render of the target robot embodiment.

Your task is to judge whether the edited image successfully transforms the human hand or hand-arm region into the requested dexterous robot embodiment while preserving the original object interaction and surrounding scene structure.

Please assign four 1--5 sub-scores:
Robotness: Whether the edited region is clearly robotic rather than human-like.
Target-embodiment match: Whether the robot matches the requested target embodiment, using the text instruction and URDF reference render as cues.
Interaction preservation: Whether the original object state, contact relationship, and hand-object interaction remain recognizable.
Scene preservation: Whether the surrounding scene structure is preserved without unnecessary global changes.

Use the following scale for each sub-score: 1 = failure, 2 = largely incorrect, 3 = partially correct, 4 = mostly correct, and 5 = clearly successful.

Output a concise rationale and the following numeric fields:
robotness: integer score from 1 to 5
target_embodiment_match: integer score from 1 to 5
interaction_preservation: integer score from 1 to 5
scene_preservation: integer score from 1 to 5
reasoning: brief explanation"""

PQ_PROMPT = """You are evaluating the perceptual quality of an edited image.

You are given:
(1) an edited image.

Judge only the visual quality of the edited image. Do not evaluate whether the requested robot embodiment is correct, and do not evaluate whether the editing instruction has been fully satisfied. Focus on whether the image is visually coherent as a single image.

Please assign three 1--5 sub-scores:
Naturalness: Whether the edited image looks visually plausible as a single image.
Artifact absence: Whether the image avoids visible artifacts such as duplicated fingers, broken geometry, halos, blur, or distorted robot parts.
Local coherence: Whether boundaries, texture, lighting, and occlusion near the edited region are consistent with the surrounding scene.

Use the following scale for each sub-score: 1 = very poor, 2 = poor, 3 = acceptable, 4 = good, and 5 = high perceptual quality.

Output a concise rationale and the following numeric fields:
naturalness: integer score from 1 to 5
artifact_absence: integer score from 1 to 5
local_coherence: integer score from 1 to 5
reasoning: brief explanation"""

# Appended to both prompts (not in the paper): machine-readable output.
JSON_SUFFIX = "\n\nRespond with a single JSON object containing exactly these fields."

SC_FIELDS = ("robotness", "target_embodiment_match", "interaction_preservation", "scene_preservation")
PQ_FIELDS = ("naturalness", "artifact_absence", "local_coherence")


class MalformedAnswer(ValueError):
    """The judge's reply has no parseable JSON with every sub-score in 1..5."""


def parse_answer(text: str, fields: tuple[str, ...]) -> dict:
    """Extract the JSON object of a reply (fenced or bare) and validate its sub-scores."""
    m = re.search(r"\{.*\}", text or "", flags=re.S)
    if not m:
        raise MalformedAnswer(f"no JSON object in the reply: {text[:120]!r}")
    try:
        obj = json.loads(m.group(0))
    except json.JSONDecodeError as exc:
        raise MalformedAnswer(f"invalid JSON in the reply ({exc}): {m.group(0)[:120]!r}") from None
    out = {}
    for f in fields:
        v = obj.get(f)
        if isinstance(v, str) and v.strip().isdigit():
            v = int(v.strip())
        if isinstance(v, float) and v.is_integer():
            v = int(v)
        if not isinstance(v, int) or isinstance(v, bool) or not 1 <= v <= 5:
            raise MalformedAnswer(f"field {f!r} must be an integer 1-5, got {v!r}")
        out[f] = v
    out["reasoning"] = str(obj.get("reasoning", ""))
    return out


def aspect_score(sub_scores: dict, fields: tuple[str, ...]) -> float:
    """min over the aspect's 1-5 sub-scores, normalised to [0,1] as (s - 1) / 4."""
    return (min(int(sub_scores[f]) for f in fields) - 1) / 4.0


def vlm_score(sc: float, pq: float) -> float:
    """S_vlm = sqrt(SC * PQ) of the normalised aspect scores."""
    if not (math.isfinite(sc) and math.isfinite(pq)):
        return float("nan")
    return math.sqrt(sc * pq)


def instruction_text(instruction: str) -> str:
    return f"\n\nText instruction: {instruction}"


def png_data_url(image: np.ndarray) -> str:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("cannot PNG-encode image")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode()


class JudgeConfig(BaseModel):
    """Where the judge lives; base URL, model and key default from the environment."""

    VERSION: int = 1
    base_url: str = Field(description="e.g. https://api.openai.com/v1 (env HANDEDIT_VLM_BASE_URL)")
    model: str = Field("gpt-4o", description="env HANDEDIT_VLM_MODEL")
    api_key: SecretStr | None = Field(None, description="env HANDEDIT_VLM_API_KEY or OPENAI_API_KEY (never logged)")
    cache_dir: Path | None = None
    max_tries: int = Field(3, ge=1, description="tries per call, malformed answers and HTTP errors alike")
    backoff_s: float = Field(1.0, ge=0)
    timeout_s: float = Field(120.0, gt=0)
    temperature: float = 0.0
    concurrency: int = Field(4, ge=1, description="judge calls in flight per evaluate task")
    protocol: Literal["paper", "toolkit"] = Field(
        "paper", description="paper: the paper's two prompts; toolkit: crops, labelled JPEGs, distractor references "
                             "and identity fields as the authors' toolkit judges (handedit.metrics.vlm_toolkit)")

    @classmethod
    def from_env(cls, **overrides) -> "JudgeConfig | None":
        import os

        base = overrides.pop("base_url", None) or os.environ.get("HANDEDIT_VLM_BASE_URL")
        if not base:
            return None
        return cls(base_url=base, model=overrides.pop("model", None) or os.environ.get("HANDEDIT_VLM_MODEL", "gpt-4o"),
                   api_key=overrides.pop("api_key", None) or os.environ.get("HANDEDIT_VLM_API_KEY") or os.environ.get("OPENAI_API_KEY"),
                   **overrides)


@dataclass
class Judgment:
    sc: float
    pq: float
    vlm: float
    sc_scores: dict | None
    pq_scores: dict | None
    errors: list[str]
    calls: int  # HTTP calls made (0 when both answers came from the cache)


class VlmJudge:
    """OpenAI-compatible chat client with a content-hash cache and malformed-answer retries."""

    def __init__(self, cfg: JudgeConfig):
        self.cfg = cfg
        register(cfg.api_key)
        if cfg.cache_dir:
            Path(cfg.cache_dir).mkdir(parents=True, exist_ok=True)

    def judge(self, src: np.ndarray, pred: np.ndarray, ref: np.ndarray | None, instruction: str) -> Judgment:
        errors: list[str] = []
        calls = 0
        images_sc = [src, pred] + ([ref] if ref is not None else [])
        sc_scores = pq_scores = None
        try:
            sc_scores, n = self.ask(SC_PROMPT + instruction_text(instruction) + JSON_SUFFIX, images_sc, SC_FIELDS)
            calls += n
        except Exception as exc:  # recorded per item, never fatal for the run
            errors.append(f"SC: {exc}")
        try:
            pq_scores, n = self.ask(PQ_PROMPT + JSON_SUFFIX, [pred], PQ_FIELDS)
            calls += n
        except Exception as exc:
            errors.append(f"PQ: {exc}")
        sc = aspect_score(sc_scores, SC_FIELDS) if sc_scores else float("nan")
        pq = aspect_score(pq_scores, PQ_FIELDS) if pq_scores else float("nan")
        return Judgment(sc, pq, vlm_score(sc, pq), sc_scores, pq_scores, [redact(e) for e in errors], calls)

    def judge_toolkit(self, x) -> tuple[dict, list[str], int]:
        """The toolkit protocol's two calls (``handedit.metrics.vlm_toolkit``): (its row, errors, calls)."""
        from handedit.metrics import vlm_toolkit as vt

        sc_parts, pq_parts, flags = vt.requests(x)
        answers, errors, calls = {}, [], 0
        for name, parts in (("SC", sc_parts), ("PQ", pq_parts)):
            try:
                answers[name], n = self.ask_parts(parts, vt.lenient_json)
                calls += n
            except Exception as exc:  # recorded per item, never fatal for the run
                errors.append(f"{name}: {exc}")
        return vt.combine(answers.get("SC", {}), answers.get("PQ", {}), flags), [redact(e) for e in errors], calls

    def ask(self, prompt: str, images: list[np.ndarray], fields: tuple[str, ...]) -> tuple[dict, int]:
        """One validated answer (from the cache, or up to ``max_tries`` calls)."""
        urls = [png_data_url(im) for im in images]
        key = hashlib.sha256(json.dumps([self.cfg.model, prompt, [hashlib.sha256(u.encode()).hexdigest() for u in urls]]).encode()).hexdigest()
        content = [{"type": "text", "text": prompt}] + [{"type": "image_url", "image_url": {"url": u}} for u in urls]
        return self._ask(key, content, lambda text: parse_answer(text, fields))

    def ask_parts(self, parts: list[tuple[str, str | None]], parse) -> tuple[dict, int]:
        """Labelled images (text, then its image when given) as one message; the cache key
        carries the protocol so that the two protocols never share an answer."""
        content, digest = [], ["toolkit", self.cfg.model]
        for text, url in parts:
            content.append({"type": "text", "text": text})
            digest.append(text)
            if url:
                content.append({"type": "image_url", "image_url": {"url": url}})
                digest.append(hashlib.sha256(url.encode()).hexdigest())
        return self._ask(hashlib.sha256(json.dumps(digest).encode()).hexdigest(), content, parse)

    def _ask(self, key: str, content: list[dict], parse) -> tuple[dict, int]:
        cached = self._cache_path(key)
        if cached and cached.exists():
            try:
                return parse(json.loads(cached.read_text())["content"]), 0
            except (MalformedAnswer, ValueError, KeyError):
                cached.unlink(missing_ok=True)
        body = {"model": self.cfg.model, "temperature": self.cfg.temperature,
                "messages": [{"role": "user", "content": content}]}
        last = ""
        for attempt in range(self.cfg.max_tries):
            if attempt:
                time.sleep(self.cfg.backoff_s * 2 ** (attempt - 1))
            try:
                text = self._post(body)
                answer = parse(text)
            except (MalformedAnswer, urllib.error.URLError, TimeoutError, OSError, KeyError, ValueError) as exc:
                last = f"{type(exc).__name__}: {exc}"
                continue
            if cached:  # temp + rename: concurrent judges never read a half-written answer
                tmp = cached.with_suffix(f".{threading.get_ident()}.tmp")
                tmp.write_text(json.dumps({"content": text, "model": self.cfg.model}))
                os.replace(tmp, cached)
            return answer, attempt + 1
        raise RuntimeError(redact(f"no valid answer after {self.cfg.max_tries} tries; last: {last}"))

    def _cache_path(self, key: str) -> Path | None:
        return Path(self.cfg.cache_dir) / f"{key}.json" if self.cfg.cache_dir else None

    def _post(self, body: dict) -> str:
        url = self.cfg.base_url.rstrip("/") + "/chat/completions"
        headers = {"Content-Type": "application/json"}
        if self.cfg.api_key:
            headers["Authorization"] = f"Bearer {self.cfg.api_key.get_secret_value()}"
        req = urllib.request.Request(url, data=json.dumps(body).encode(), headers=headers, method="POST")
        with open_url(req, timeout=self.cfg.timeout_s) as resp:
            reply = json.loads(resp.read())
        return reply["choices"][0]["message"]["content"]
