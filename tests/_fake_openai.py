"""A fake OpenAI-compatible server on 127.0.0.1 (stdlib http.server in a thread).

- POST /v1/chat/completions: the judge. SC replies 1s when the edited image equals the
  source (nothing was edited), else 5/4/4/5 (and, asked for the toolkit protocol's identity
  fields, reference A, or B when unchanged or ``wrong_choice``); PQ replies 4/4/3. ``malformed_next``
  makes the next N replies unparseable; ``fail_always`` makes every reply malformed.
- POST /v1/images/edits: an editor that returns the first uploaded image (b64_json).
``echo_errors`` answers 401 with the request headers echoed; ``delay_s`` delays answers.
Every request is recorded in ``requests``.
"""

from __future__ import annotations

import base64
import json
import re
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np


def _decode_data_url(url: str) -> np.ndarray:
    data = base64.b64decode(url.split(",", 1)[1])
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)


class FakeOpenAI:
    def __init__(self):
        self.requests: list[dict] = []
        self.malformed_next = 0
        self.fail_always = False
        self.echo_errors = False  # answer 401 with the request's headers in the body (as some proxies do)
        self.delay_s = 0.0  # sleep before answering (timeouts)
        self.wrong_choice = False  # toolkit protocol: the judge picks distractor B
        self.lock = threading.Lock()
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):  # quiet
                pass

            def do_POST(self):
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                if outer.delay_s:
                    time.sleep(outer.delay_s)
                if outer.echo_errors:
                    data = json.dumps({"error": "unauthorized", "request_headers": dict(self.headers)}).encode()
                    self.send_response(401)
                    self.send_header("Content-Length", str(len(data)))
                    self.end_headers()
                    self.wfile.write(data)
                    return
                if self.path.endswith("/chat/completions"):
                    reply = outer.chat(json.loads(body), self.headers)
                elif self.path.endswith("/images/edits"):
                    reply = outer.edit(body, self.headers)
                else:
                    self.send_response(404)
                    self.end_headers()
                    return
                data = json.dumps(reply).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.server.server_address[1]}/v1"

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.server.shutdown()
        self.server.server_close()

    def chat(self, req: dict, headers) -> dict:
        content = req["messages"][0]["content"]
        text = content[0]["text"]
        images = [_decode_data_url(c["image_url"]["url"]) for c in content if c["type"] == "image_url"]
        labels = [c["text"] for c in content[1:] if c["type"] == "text"]
        with self.lock:
            self.requests.append({"kind": "chat", "text": text, "n_images": len(images), "labels": labels,
                                  "auth": headers.get("Authorization")})
            bad = self.fail_always or self.malformed_next > 0
            if self.malformed_next > 0:
                self.malformed_next -= 1
        if bad:
            answer = "I think the robot looks fine, maybe a 4 overall."
        elif "perceptual quality" in text:
            answer = json.dumps({"naturalness": 4, "artifact_absence": 4, "local_coherence": 3, "reasoning": "ok"})
        else:
            unchanged = images[0].shape == images[1].shape and np.array_equal(images[0], images[1])
            s = (1, 1, 1, 1) if unchanged else (5, 4, 4, 5)
            fields = dict(zip(("robotness", "target_embodiment_match", "interaction_preservation", "scene_preservation"), s))
            if "chosen_reference" in text:  # the toolkit protocol's identity fields (a distractor when unchanged)
                fields.update(chosen_reference="B" if unchanged else "A", target_choice_correct=not unchanged,
                              correct_ref_alignment=4.6, nearest_wrong_ref_alignment="2", identity_margin=9)
                if self.wrong_choice:
                    fields.update(chosen_reference="B", target_choice_correct="no")
            answer = "```json\n" + json.dumps(dict(fields, reasoning="fake")) + "\n```"
        return {"choices": [{"message": {"role": "assistant", "content": answer}}]}

    def edit(self, body: bytes, headers) -> dict:
        boundary = re.search(r"boundary=(\S+)", headers["Content-Type"]).group(1).encode()
        parts = [p for p in body.split(b"--" + boundary) if b"Content-Disposition" in p]
        fields, images = {}, []
        for p in parts:
            head, _, payload = p.partition(b"\r\n\r\n")
            payload = payload[:-2] if payload.endswith(b"\r\n") else payload
            name = re.search(rb'name="([^"]+)"', head).group(1).decode()
            if b"filename=" in head:
                images.append(payload)
            else:
                fields[name] = payload.decode()
        with self.lock:
            self.requests.append({"kind": "edit", "fields": fields, "n_images": len(images), "auth": headers.get("Authorization")})
        return {"data": [{"b64_json": base64.b64encode(images[0]).decode()}]}
