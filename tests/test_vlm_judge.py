"""The VLM judge: prompts, parsing, aggregation (hand-computed), cache and retries
against a fake OpenAI-compatible server on 127.0.0.1."""

from __future__ import annotations

import math

import numpy as np
import pytest

from _fake_openai import FakeOpenAI
from handedit.metrics.vlm import (PQ_FIELDS, SC_FIELDS, SC_PROMPT, PQ_PROMPT, JudgeConfig, MalformedAnswer, VlmJudge,
                                  aspect_score, parse_answer, vlm_score)


def test_aggregation_hand_computed():
    sc = aspect_score({"robotness": 5, "target_embodiment_match": 4, "interaction_preservation": 3,
                       "scene_preservation": 5}, SC_FIELDS)
    pq = aspect_score({"naturalness": 4, "artifact_absence": 4, "local_coherence": 5}, PQ_FIELDS)
    assert (sc, pq) == (0.5, 0.75)
    assert vlm_score(sc, pq) == pytest.approx(math.sqrt(0.375))
    assert vlm_score(0.0, 1.0) == 0.0 and math.isnan(vlm_score(float("nan"), 1.0))


def test_prompts_are_the_papers():
    for phrase in ("egocentric hand-to-dexterous-robot image editing", "URDF reference render of the target robot embodiment",
                   "1 = failure, 2 = largely incorrect, 3 = partially correct, 4 = mostly correct, and 5 = clearly successful",
                   "target_embodiment_match: integer score from 1 to 5"):
        assert phrase in SC_PROMPT
    for phrase in ("Judge only the visual quality of the edited image.", "duplicated fingers, broken geometry, halos, blur",
                   "5 = high perceptual quality", "local_coherence: integer score from 1 to 5"):
        assert phrase in PQ_PROMPT


def test_parse_answer():
    ok = parse_answer('Sure.\n```json\n{"naturalness": "4", "artifact_absence": 5, "local_coherence": 3.0}\n```', PQ_FIELDS)
    assert (ok["naturalness"], ok["artifact_absence"], ok["local_coherence"]) == (4, 5, 3)
    for bad in ("no json here", '{"naturalness": 6, "artifact_absence": 5, "local_coherence": 3}',
                '{"naturalness": 4, "artifact_absence": 5}', '{"naturalness": 4, "artifact_absence": true, "local_coherence": 3}',
                "{not json}"):
        with pytest.raises(MalformedAnswer):
            parse_answer(bad, PQ_FIELDS)


def test_judge_cache_retries_and_failures(tmp_path):
    src = np.zeros((16, 16, 3), np.uint8)
    pred = src.copy()
    pred[4:12, 4:12] = 200
    with FakeOpenAI() as server:
        cfg = JudgeConfig(base_url=server.base_url, model="gpt-4o", api_key="sk-test", cache_dir=tmp_path / "cache",
                          max_tries=3, backoff_s=0.0)
        judge = VlmJudge(cfg)
        server.malformed_next = 2  # SC: two malformed replies, then a valid one
        j = judge.judge(src, pred, src, "Replace the human hand region with ...")
        assert j.errors == [] and j.calls == 4  # 3 SC tries + 1 PQ
        assert j.sc == pytest.approx(0.75) and j.pq == pytest.approx(0.5) and j.vlm == pytest.approx(math.sqrt(0.375))
        sc_req = [r for r in server.requests if "Semantic" in r["text"] or "hand-to-dexterous" in r["text"]][0]
        assert sc_req["n_images"] == 3 and sc_req["auth"] == "Bearer sk-test"
        assert "Text instruction: Replace the human hand region" in sc_req["text"]
        # same content again: answered from the cache, no HTTP call
        n = len(server.requests)
        again = judge.judge(src, pred, src, "Replace the human hand region with ...")
        assert again.calls == 0 and len(server.requests) == n and again.vlm == j.vlm
        # unchanged image: SC collapses to 0 -> S_vlm 0
        assert judge.judge(src, src.copy(), src, "x").vlm == 0.0
        # always malformed: recorded as failures, NaN scores, no exception
        server.fail_always = True
        other = pred.copy()
        other[0, 0] = 1
        failed = VlmJudge(cfg.model_copy(update={"cache_dir": None})).judge(src, other, None, "y")
        assert math.isnan(failed.vlm) and len(failed.errors) == 2
        assert all("no valid answer after 3 tries" in e for e in failed.errors)
    assert "sk-test" not in repr(cfg) and "sk-test" not in cfg.model_dump_json()
