"""Clip sources: the synthetic oracle, generic video files, and dataset adapters.

Two kinds of spec: a *clip* spec (``SourceSpec``) describes one clip and is what a worker
opens; a *tree* spec (``TreeSpec``, e.g. a whole EgoDex tree) expands to clip specs in a
stable listing order, grouped (EgoDex: by task) so that shards can be cut lazily.
"""

from __future__ import annotations

import json
from functools import lru_cache
from typing import Annotated, Iterator, Union

from pydantic import Field, TypeAdapter

from handedit.sources.arctic import ArcticSpec, ArcticTree
from handedit.sources.hocap import HocapSpec, HocapTree
from handedit.sources.hoi4d import Hoi4dSpec, Hoi4dTree
from handedit.sources.oakink2 import Oakink2Spec, Oakink2Tree
from handedit.sources.base import ClipChunk, ClipInfo, Source, SourceError, frame_status
from handedit.sources.egodex import EgoDexSpec, EgoDexTree
from handedit.sources.synthetic import SyntheticSpec
from handedit.sources.video import VideoSpec

SourceSpec = Annotated[Union[SyntheticSpec, VideoSpec, EgoDexSpec, ArcticSpec, Oakink2Spec, Hoi4dSpec, HocapSpec],
                      Field(discriminator="kind")]
TreeSpec = Annotated[Union[EgoDexTree, ArcticTree, Oakink2Tree, Hoi4dTree, HocapTree], Field(discriminator="kind")]
_SPEC = TypeAdapter(SourceSpec)
# --source NAME -> its tree spec
TREES = {"egodex": EgoDexTree, "arctic": ArcticTree, "oakink2": Oakink2Tree, "hoi4d": Hoi4dTree, "hocap": HocapTree}
# what each source needs beyond its files, and what it provides (`handedit sources list`)
SOURCES: dict[str, dict[str, str]] = {
    "synthetic": {"needs": "nothing (generated)", "provides": "one right hand, exact keypoints, "
                  "object mesh + pose + mask, ground-truth masks and background"},
    "video": {"needs": "a video; optional keypoints file; else the hand models (`handedit models fetch`)",
              "provides": "frames; hands from the keypoints file or estimated (estimate_hands)"},
    "egodex": {"needs": "an EgoDex tree (<task>/<k>.hdf5 + .mp4)", "provides": "both hands, arms (elbow, shoulder), "
               "camera poses (ARKit world, Y up); no objects"},
    "arctic": {"needs": "an ARCTIC tree (raw_seqs/, meta/, images/) and your MANO model (--mano-dir)",
               "provides": "both hands (MANO), egocentric camera (undistorted), articulated object pose + mesh + mask"},
    "oakink2": {"needs": "an OakInk2 tree (anno_preview/, data/, object_raw/), your MANO model, torch (its pickles)",
                "provides": "both hands (MANO, quaternions), egocentric camera, object pose + mesh + mask"},
    "hoi4d": {"needs": "a HOI4D tree (frames decoded to align_rgb/), handpose/, camera_params/, CAD models, your MANO model",
              "provides": "hands annotated (mostly the right), object pose (category-level) + CAD mesh, shipped 2-D object masks"},
    "hocap": {"needs": "an HO-Cap data folder (calibration/, models/, subject_*/) and your MANO model",
              "provides": "the annotated hands (MANO, 45 PCA), HoloLens egocentric camera, object pose + mesh + mask"},
}


def parse_spec(data: dict):
    return _SPEC.validate_python(data)


def open_source(spec) -> Source:
    """Instantiate the source a spec describes (reads metadata; frames are read in ``read``)."""
    return spec.open()


@lru_cache(maxsize=16)
def open_source_json(spec_json: str) -> Source:
    """Per-process cache: a worker opens each clip's source once, whatever chunk it reads."""
    return open_source(parse_spec(json.loads(spec_json)))


def iter_groups(trees, clips=()) -> Iterator[tuple[str, list]]:
    """(group name, clip specs) of explicit clips (one group, "clips") then of each tree."""
    if clips:
        yield "clips", list(clips)
    for tree in trees:
        for name, specs in tree.groups():
            yield f"{tree.kind}-{name}", specs


__all__ = [
    "SOURCES", "TREES", "ArcticSpec", "ArcticTree", "ClipChunk", "ClipInfo", "EgoDexSpec", "EgoDexTree", "HocapSpec",
    "HocapTree", "Hoi4dSpec", "Hoi4dTree", "Oakink2Spec", "Oakink2Tree", "Source", "SourceError", "SourceSpec",
    "SyntheticSpec", "TreeSpec", "VideoSpec", "frame_status", "iter_groups", "open_source", "open_source_json", "parse_spec",
]
