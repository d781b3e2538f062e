"""The one owner of the Zarr v3 layout: group paths, chunking, codecs, and the stages' schemas
(each stage declares the arrays it writes in its ``tasks/<stage>.py``; ``stage_layouts`` reads them).

Nothing else in the project builds a store path by hand. The tree is::

    <store>.zarr/                         attrs: schema, frames_per_chunk, created
      clips/<clip>/source/                ingest: frames, camera, keypoints (per hand), arm joints, object, gt_*
      clips/<clip>/estimate_hands/        keypoints estimated from the pixels (sources without any), raw + smoothed
      clips/<clip>/registration/        keypoints registered to the pixels, offset_px, scale
      clips/<clip>/segment/               hand_mask, handarm_mask (per hand), confidence
      clips/<clip>/restore_background/<scope>/   background (scope = hand | hand_arm)
      clips/<clip>/embodiments/<emb>/<stage>/    retarget, render, composite, harmonize, qc
    beside it: shards/, index/, ledger/   per-shard bookkeeping (handedit.storage.shards)

Every stage group ("unit") holds a ``status`` array (one int16 per frame, codes in
``handedit.reasons``) and, in its attributes, a provenance record per chunk.

Hands: per-hand arrays have a ``hand`` axis after ``frame`` (size S, in the order of the
source's ``hands`` attribute, e.g. left, right). Stages that work per hand (estimate_hands, registration,
segment, retarget, render, composite, qc) also write ``hand_status`` (frame, hand): OK,
ABSENT (not in view), UPSTREAM or the side's own rejection; their frame-level ``status``
is OK when at least one side is OK (see ``handedit.reasons.per_frame``). Why an axis and
not per-side groups: the sides of a frame are decided together (two hands in one GrabCut
so neither swallows the other, two robots in one depth test, one keep decision), so one
task and one writer own both.

Chunking enforces one writer per chunk: a task always covers whole chunks of
``frames_per_chunk`` (F) frames. Image arrays store one frame per inner chunk, F frames
per shard; small per-frame arrays store F frames per chunk. So two tasks never touch the
same file, and a unit's arrays and attributes are created and written by the one task that
owns it (a clip's task its clip units, an embodiment task its embodiment units).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

SCHEMA_VERSION = 2  # 2: hand axis, registration stage, shard bookkeeping beside the store
STORE_SUFFIX = ".zarr"
SCOPES = ("hand", "hand_arm")



@dataclass(frozen=True, order=True)
class Unit:
    """One stage applied to one clip (and scope or embodiment): one Zarr group."""

    stage: str
    clip: str
    scope: str | None = None
    embodiment: str | None = None

    def __post_init__(self) -> None:
        layout = stage_layouts().get(self.stage)
        if layout is None:
            raise ValueError(f"unknown stage {self.stage!r}; stages are {', '.join(stage_layouts())}")
        level = layout.level
        if (level == "scope") != (self.scope is not None) or (level == "embodiment") != (self.embodiment is not None):
            raise ValueError(f"stage {self.stage!r} is addressed per {level}: got {self}")
        if self.scope is not None and self.scope not in SCOPES:
            raise ValueError(f"unknown scope {self.scope!r}; scopes are {SCOPES}")

    @property
    def path(self) -> str:
        c = clip_path(self.clip)
        if self.stage == "ingest":
            return f"{c}/source"
        if self.scope is not None:
            return f"{c}/{self.stage}/{self.scope}"
        if self.embodiment is not None:
            return f"{c}/embodiments/{self.embodiment}/{self.stage}"
        return f"{c}/{self.stage}"

    @property
    def label(self) -> str:
        extra = self.scope or self.embodiment
        return f"{self.stage}[{self.clip}{'/' + extra if extra else ''}]"


_SAFE = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]*")


def safe_name(kind: str, name: str) -> str:
    """One path segment of the store or a benchmark folder: letters, digits, '-', '_', '.',
    never empty, not starting with '.' (what a URL, a shell and a tar member keep as is)."""
    if not isinstance(name, str) or not _SAFE.fullmatch(name):
        raise ValueError(f"invalid {kind} {name!r}: use letters, digits, '-', '_', '.' (no '/', not starting with '.')")
    return name


def clip_path(clip: str) -> str:
    return f"clips/{safe_name('clip id', clip)}"


# Review previews of a hand-arm sequence's top virtual-base candidates: a sequence-level
# group per hand inside its retarget unit (not per frame), written by the one retarget task.
#   <retarget unit>/previews/<side>/ego, third   (K, P, H, W, 4) uint8   K candidates x P frames
#   <retarget unit>/previews/<side>/candidates   (K,) int16 (-1: none)   frames (P,) int32 (-1: none)
# P: 3 stills, or the replay's frames under ``review: manual`` (VirtualBaseConfig.preview_frames)
PREVIEW_CANDIDATES = 3


def preview_path(unit: Unit, side: str) -> str:
    if unit.stage != "retarget" or unit.embodiment is None:
        raise ValueError(f"previews belong to a hand-arm retarget unit, not {unit.label}")
    return f"{unit.path}/previews/{safe_name('side', side)}"


@dataclass(frozen=True)
class ArraySpec:
    """Schema of one per-frame array; ``tail`` may name sizes ('H', 'W', 'dof')."""

    name: str
    tail: tuple[int | str, ...]
    dtype: str
    dims: tuple[str, ...]  # dimension names after 'frame' (xarray needs them)
    image: bool = False  # Blosc zstd (colour: level 1, masks/depth: bit-shuffled), 1 frame per inner chunk
    when: str | None = None  # only when the source has this: 'object', 'gt' or 'arm'
    fill: float | int | bool = 0

    def shape(self, n_frames: int, sizes: dict[str, int]) -> tuple[int, ...]:
        return (n_frames, *(sizes[d] if isinstance(d, str) else d for d in self.tail))


# Building blocks of the stages' output schemas (each ``tasks/<stage>.py`` declares its own).
STATUS = ArraySpec("status", (), "int16", ())
HAND_STATUS = ArraySpec("hand_status", ("S",), "int16", ("hand",))
MASK, MASK_DIMS = ("H", "W"), ("y", "x")
HAND_MASK, HAND_MASK_DIMS = ("S", "H", "W"), ("hand", "y", "x")
RGB, RGB_DIMS = ("H", "W", 3), ("y", "x", "rgb")
LEVELS = ("clip", "scope", "embodiment")  # which address fields identify one unit of a stage


@dataclass(frozen=True)
class StageLayout:
    """What the store needs of a stage: its level and the arrays it writes."""

    level: str
    arrays: tuple[ArraySpec, ...]

    @property
    def per_hand(self) -> bool:
        return HAND_STATUS in self.arrays


_LAYOUTS: dict[str, StageLayout] | None = None


def stage_layouts() -> dict[str, StageLayout]:
    """Every stage's layout in pipeline order. Each stage declares its level and output
    arrays once, in its ``tasks/<stage>.py`` (``Stage(..., writes=...)``); storage places
    them (paths, chunking, codecs) and checks them here."""
    global _LAYOUTS
    if _LAYOUTS is None:
        from handedit.tasks import STAGES  # the list of stage declarations; imported on first use

        layouts = {}
        for st in STAGES:
            names = [a.name for a in st.writes]
            if st.level not in LEVELS or "status" not in names or len(set(names)) != len(names):
                raise ValueError(f"stage {st.name!r} (tasks/{st.name}.py): level must be one of {LEVELS} and "
                                 f"writes= must name each array once, 'status' included; got {st.level!r}, {names}")
            layouts[st.name] = StageLayout(st.level, tuple(st.writes))
        _LAYOUTS = layouts
    return _LAYOUTS


def stage_names() -> tuple[str, ...]:
    return tuple(stage_layouts())


def stage_arrays(stage: str) -> tuple[ArraySpec, ...]:
    return stage_layouts()[stage].arrays


# Which mask of the segment stage a scope uses.
SCOPE_MASK = {"hand": "hand_mask", "hand_arm": "handarm_mask"}
REVIEWS_ATTR = "reviews"  # a hand-arm retarget unit's operator decisions (``handedit review``; an input of its key)

LEDGER_COLUMNS: tuple[tuple[str, str], ...] = (
    ("stage", "str"),
    ("clip", "str"),
    ("scope", "str"),
    ("embodiment", "str"),
    ("side", "str"),  # "" for a frame-level rejection
    ("frame", "int32"),
    ("reason", "int16"),
    ("reason_name", "str"),
    ("detail", "str"),
)


def arrays_for(stage: str, has_object: bool, has_gt: bool, has_arm: bool = False) -> tuple[ArraySpec, ...]:
    flags = {"object": has_object, "gt": has_gt, "arm": has_arm, None: True}
    return tuple(a for a in stage_arrays(stage) if flags[a.when])


def chunk_ranges(n_frames: int, frames_per_chunk: int) -> list[tuple[int, int]]:
    """Frame ranges of the chunks of a clip: the unit of one task and of one writer."""
    return [(s, min(s + frames_per_chunk, n_frames)) for s in range(0, n_frames, frames_per_chunk)]


# ----------------------------------------------------------------------------- benchmark
# A benchmark folder (test set, predictions, metric results, reports) is plain files,
# because the authors' evaluation toolkit reads PNG paths from a JSONL manifest::
#
#     <bench>/testset.json                          meta: tracks, items, source store, bank
#     <bench>/manifest.jsonl                        the toolkit manifest (pred_path empty)
#     <bench>/items/<item>/{src,gt}.png             source image, pseudo-GT
#     <bench>/items/<item>/{human,robot,test,object}_mask.png
#     <bench>/refs/<embodiment>/{view,mask}_<v>.png reference views + masks
#     <bench>/predictions/<editor>/<item>.png       an editor's outputs
#     <bench>/predictions/<editor>/records.jsonl    one record per attempt-finished item
#     <bench>/results/<editor>/items.csv            per-item metrics and errors
#     <bench>/results/<editor>/summary.json         per-track means, FID, skipped metrics
#     <bench>/vlm_cache/<sha256>.json               judge answers by content hash
#     <bench>/report/                               tables (md, tex, csv), radar PNGs

BENCH_META = "testset.json"
BENCH_MANIFEST = "manifest.jsonl"
BENCH_ITEM_FILES = {
    "src": "src.png", "gt": "gt.png", "human_mask": "human_mask.png", "robot_mask": "robot_mask.png",
    "test_mask": "test_mask.png", "object_mask": "object_mask.png",
}
TRACKS = {"hand": "hand-only", "hand_arm": "hand-arm"}  # scope -> track name


def bench_item_dir(item_id: str) -> str:
    return f"items/{safe_name('benchmark item id', item_id)}"


def bench_ref_paths(embodiment: str, view: int) -> tuple[str, str]:
    return f"refs/{embodiment}/view_{view:02d}.png", f"refs/{embodiment}/mask_{view:02d}.png"


def bench_prediction_dir(editor: str) -> str:
    return f"predictions/{safe_name('editor name', editor)}"


def bench_results_dir(editor: str) -> str:
    return f"results/{safe_name('editor name', editor)}"


BENCH_VLM_CACHE = "vlm_cache"
BENCH_REPORT = "report"


# ---- reference bank (handedit bank build; read by the benchmark) ----------------------------
# A separate store (not a curate store):
#     <bank>.zarr/                      attrs: bank_schema, views, width, height, seed, rig
#       embodiments/<emb>/              attrs: name, track, description (frozen, verbatim), urdf
#         rgb   (V,H,W,3) uint8         canonical views, black where the robot is not
#         mask  (V,H,W)   bool          robot silhouettes
#         camera_from_root (V,4,4) float64, qpos (V,dof) float32, K (3,3) float64
BANK_SCHEMA_VERSION = 1
BANK_GROUP = "embodiments"
BANK_ARRAYS: tuple[str, ...] = ("rgb", "mask", "camera_from_root", "qpos", "K")


def bank_embodiment_path(embodiment_id: str) -> str:
    return f"{BANK_GROUP}/{safe_name('embodiment id', embodiment_id)}"
