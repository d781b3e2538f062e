"""Clip sources: the synthetic oracle, generic video files, and (later) dataset adapters."""

from __future__ import annotations

import json
from functools import lru_cache
from typing import Annotated, Union

from pydantic import Field, TypeAdapter

from handedit.sources.base import ClipChunk, ClipInfo, Source, SourceError, frame_status
from handedit.sources.synthetic import SyntheticSpec
from handedit.sources.video import VideoSpec

SourceSpec = Annotated[Union[SyntheticSpec, VideoSpec], Field(discriminator="kind")]
_SPEC = TypeAdapter(SourceSpec)


def parse_spec(data: dict) -> SyntheticSpec | VideoSpec:
    return _SPEC.validate_python(data)


def open_source(spec: SyntheticSpec | VideoSpec) -> Source:
    """Instantiate the source a spec describes (cheap; heavy work happens in ``read``)."""
    return spec.open()


@lru_cache(maxsize=16)
def open_source_json(spec_json: str) -> Source:
    """Per-process cache: a worker opens each clip's source once, whatever chunk it reads."""
    return open_source(parse_spec(json.loads(spec_json)))


__all__ = [
    "ClipChunk", "ClipInfo", "Source", "SourceError", "SourceSpec",
    "SyntheticSpec", "VideoSpec", "frame_status", "open_source", "open_source_json", "parse_spec",
]
