"""Markdown text from data: a value shown in a table cell or a list line stays text (names,
tasks and ids come from datasets and manifests, not from us)."""

from __future__ import annotations

import html


def md(value) -> str:
    """``value`` as inert Markdown: HTML escaped, ``|`` escaped (it would split a table row),
    line breaks folded into spaces."""
    return html.escape(str(value), quote=False).replace("|", "\\|").replace("\r", " ").replace("\n", " ")
