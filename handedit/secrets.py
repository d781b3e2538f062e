"""Secrets stay secret: one redaction for every error text, log line and record.

An HTTP error body may echo the request headers, an exception may print a URL with a
token: any of it can end up in ``records.jsonl``, provenance, the ledger or a terminal.
``redact`` replaces every known secret value (the editor's and judge's configured keys,
registered with ``register``, and the values of ``*_API_KEY``, ``*_TOKEN``, ``*_SECRET*``
and ``*_PASSWORD`` environment variables) and any ``Authorization`` / ``Bearer`` value by
``[redacted]``. A secret is found in any letter case, JSON- or ``\\u``-escaped, and in
part: any run of 8 of its characters (for secrets of 12 characters or more), with the token
characters around it. ``install_log_filter`` applies it to every log record the process
creates.
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
from functools import lru_cache

MARK = "[redacted]"
_SECRET_ENV = re.compile(r"(API_KEY|TOKEN|SECRET|PASSWORD)", re.IGNORECASE)
_HEADER = re.compile(r"(?i)(authorization['\"]?\s*[:=]\s*['\"]?)(?:(bearer|basic|token)\s+)?[^\s'\",}]+")
_BEARER = re.compile(r"(?i)\b(bearer)\s+[A-Za-z0-9._~+/=-]{6,}")
_MIN_LEN = 6  # shorter values (e.g. "1", "true") would redact ordinary text
_PART = 8  # a run of this many of a secret's characters is redacted (secrets of 12 or more characters)

_registered: set[str] = set()
_lock = threading.Lock()


def register(*values) -> None:
    """Secrets known to this process besides the environment's (e.g. a configured key)."""
    with _lock:
        for v in values:
            text = v.get_secret_value() if hasattr(v, "get_secret_value") else v
            if text and len(str(text)) >= _MIN_LEN:
                _registered.add(str(text))


def known_secrets() -> list[str]:
    env = [v for k, v in os.environ.items() if _SECRET_ENV.search(k) and v and len(v) >= _MIN_LEN]
    with _lock:
        return sorted({*env, *_registered}, key=len, reverse=True)  # longest first: no partial leftovers


def redact(text, extra=()) -> str:
    """``text`` with every secret value and credential header replaced by ``[redacted]``."""
    if text is None:
        return text
    out = str(text)
    register(*extra)
    secrets = tuple(known_secrets())
    if secrets:
        out = _pattern(secrets).sub(MARK, out)
    out = _HEADER.sub(lambda m: m.group(1) + (m.group(2) + " " if m.group(2) else "") + MARK, out)
    return _BEARER.sub(lambda m: f"{m.group(1)} {MARK}", out)


def _forms(secret: str) -> list[str]:
    """How a secret can appear in text: as is, JSON-escaped, \\u-escaped (either case)."""
    escaped = "".join(f"\\u{ord(c):04x}" for c in secret)
    return [secret, json.dumps(secret)[1:-1], escaped, escaped.upper().replace("\\U", "\\u")]


@lru_cache(maxsize=16)
def _pattern(secrets: tuple[str, ...]) -> re.Pattern:
    """One case-insensitive pattern for every form of every secret, and for runs of ``_PART``
    of a long secret's characters with the token characters around them."""
    whole = sorted({re.escape(f) for s in secrets for f in _forms(s)}, key=len, reverse=True)
    parts = sorted({re.escape(s[i:i + _PART]) for s in secrets if len(s) >= 12 for i in range(len(s) - _PART + 1)})
    alts = whole + ([r"[\w.~+/=-]*(?:" + "|".join(parts) + r")[\w.~+/=-]*"] if parts else [])
    return re.compile("|".join(alts), re.IGNORECASE)


def redact_obj(obj):
    """A JSON-like value with every string redacted (records before they are written)."""
    if isinstance(obj, str):
        return redact(obj)
    if isinstance(obj, dict):
        return {k: redact_obj(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(redact_obj(v) for v in obj)
    return obj


def install_log_filter() -> None:
    """Redact every log record this process creates, whichever handler writes it, including
    handlers configured later (Prefect's): a log-record factory, installed once."""
    previous = logging.getLogRecordFactory()
    if getattr(previous, "redacts", False):
        return

    def factory(*args, **kwargs) -> logging.LogRecord:
        record = previous(*args, **kwargs)
        try:
            msg = record.getMessage()
        except Exception:  # noqa: BLE001 - a malformed record is reported when it is emitted
            return record
        clean = redact(msg)
        if clean != msg:
            record.msg, record.args = clean, None
        return record

    factory.redacts = True
    logging.setLogRecordFactory(factory)
