"""Robot files: one YAML file per hand, per arm and per hand-arm, validated by a typed schema.

The roster is these files: the built-in ones under ``handedit/embodiments/robots/`` (``hands/``,
``arms/``, ``hand_arms/``) and a user's, in the folders ``$HANDEDIT_ROBOT_DIRS`` lists
(os.pathsep-separated, searched recursively for ``*.yaml``). A file's stem is its key; a key
defined twice is an error naming both files (a user file never replaces a built-in silently).
A hand and a hand-arm are embodiments; an arm is what a hand-arm names.

    kind: hand                       # hands/<key>.yaml
    name: Allegro
    description: A compact black robotic hand ...   # the paper's frozen text
    materials: {'link_(3|7|11|15)\\.0_tip': [0.92, 0.92, 0.9, 1.0], '.*': [0.08, 0.08, 0.09, 1.0]}
    urdf:                            # candidates: asset dirs first, then installed packages
      - source: asset_dir            # or: package (with package: <PyPI distribution>)
        path: hands/allegro_hand/allegro_hand_right_glb.urdf
        wrist: {link: wrist}         # the link the human wrist sits on (offset: metres, link frame)
        fingers:                     # thumb: cmc, mcp, ip, tip; others: mcp, pip, dip, tip (null: none)
          thumb: [link_13.0, link_14.0, link_15.0, link_15.0_tip]
        wrist_from_root: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.095], [0, 0, 0, 1]]
    retarget_weights: {tip: 2.0}     # optional: this robot's multipliers on the run's keypoint weights

    kind: hand_arm                   # hand_arms/<key>.yaml: an arm and a hand, by key
    name: UR5 + Shadow Hand
    description: ...
    arm: ur5
    hand: shadow

Schema errors name the file, the field and what it takes (``RobotFileError``).
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
from pathlib import Path
from typing import Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from handedit.embodiments.errors import EmbodimentError

ROBOT_DIRS_ENV = "HANDEDIT_ROBOT_DIRS"
BUILTIN = Path(__file__).with_name("robots")
FINGER_NAMES = ("thumb", "index", "middle", "ring", "pinky")
IDENTITY = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


class RobotFileError(EmbodimentError):
    """A robot file that does not parse or validate, named down to the field."""


def _matrix(v):
    a = np.asarray(v, dtype=float)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)) or not np.allclose(a[3], [0, 0, 0, 1]):
        raise ValueError("a 4x4 homogeneous transform: 4 rows of 4 numbers, the last row [0, 0, 0, 1]")
    return tuple(tuple(float(x) for x in row) for row in v)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


Matrix = tuple[tuple[float, ...], ...]
RGBA = tuple[float, float, float, float]


class Point(_Strict):
    link: str
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


class ExtraKeypoint(_Strict):
    """A keypoint beyond ``fingers`` (e.g. a tip on a distal link, at an offset)."""

    joint: str = Field(description="MANO joint name, e.g. thumb_tip (handedit.keypoints.MANO_JOINTS)")
    link: str
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @field_validator("joint")
    @classmethod
    def _known(cls, v: str) -> str:
        from handedit.keypoints import MANO_JOINTS

        if v not in MANO_JOINTS or v == "wrist":
            raise ValueError(f"a MANO finger joint: one of {', '.join(MANO_JOINTS[1:])}")
        return v


class Coupling(_Strict):
    joint: str
    follows: str
    multiplier: float = 1.0
    offset: float = 0.0


class LoopFile(_Strict):
    a: str
    a_about: str
    ra: float
    b: str
    b_about: str
    rb: float
    branch: int = 1
    length: float = 0.0
    b_point: tuple[float, float, float] | None = None


class LinkageFile(_Strict):
    actuator: str
    passive: tuple[str, ...]
    loops: tuple[LoopFile, ...]


class HandUrdf(_Strict):
    source: Literal["asset_dir", "package"]
    path: str
    package: str = ""
    wrist: Point | None = Field(None, description="None (with no fingers): a URDF not supported yet")
    fingers: dict[str, tuple[Union[None, str, Point], ...]] = Field(default_factory=dict)
    extra_keypoints: tuple[ExtraKeypoint, ...] = ()
    wrist_from_root: Matrix = Field(IDENTITY, description="the URDF root in the MANO wrist frame (4x4)")
    locked_joints: dict[str, float] = Field(default_factory=dict)
    couplings: tuple[Coupling, ...] = ()
    hidden_visuals: str = ""
    linkages: tuple[LinkageFile, ...] = ()
    mount_at_root: bool = False

    @field_validator("wrist_from_root", mode="before")
    @classmethod
    def _wrist_from_root(cls, v):
        return _matrix(v)

    @field_validator("fingers")
    @classmethod
    def _fingers(cls, v: dict) -> dict:
        for finger, links in v.items():
            if finger not in FINGER_NAMES:
                raise ValueError(f"finger {finger!r}: the fingers are {', '.join(FINGER_NAMES)}")
            if len(links) != 4:
                raise ValueError(f"{finger}: 4 entries (thumb: cmc, mcp, ip, tip; others: mcp, pip, dip, tip; null: none)")
        return v


class ArmUrdf(_Strict):
    source: Literal["asset_dir", "package"]
    path: str
    package: str = ""
    ee_link: str = Field(description="the flange link that carries the hand")
    ee_from_tool: Matrix = IDENTITY
    drop_links: tuple[str, ...] = ()
    mounts: dict[str, Matrix] = Field(default_factory=dict, description="exact ee_from_hand_root by hand URDF path")

    @field_validator("ee_from_tool", mode="before")
    @classmethod
    def _ee_from_tool(cls, v):
        return _matrix(v)

    @field_validator("mounts", mode="before")
    @classmethod
    def _mounts(cls, v):
        return {k: _matrix(m) for k, m in (v or {}).items()}


class HandFile(_Strict):
    kind: Literal["hand"]
    name: str
    description: str
    materials: dict[str, RGBA] = Field(default_factory=dict, description="link regex (full match, first wins) -> RGBA")
    urdf: tuple[HandUrdf, ...] = Field(min_length=1)
    side: Literal["right", "left"] = "right"
    retarget_weights: dict[Literal["wrist", "cmc", "mcp", "pip", "dip", "tip"], float] = Field(
        default_factory=dict, description="this robot's multipliers on the run's keypoint weights (retarget.*_weight), "
        "by keypoint kind: tuned on real hands (bench/retarget.py --real)")

    @field_validator("retarget_weights")
    @classmethod
    def _weights(cls, v: dict) -> dict:
        bad = {k: w for k, w in v.items() if not (w >= 0 and np.isfinite(w))}
        if bad:
            raise ValueError(f"retarget_weights {bad}: multipliers are finite and >= 0")
        return v


class ArmFile(_Strict):
    kind: Literal["arm"]
    name: str
    urdf: tuple[ArmUrdf, ...] = Field(min_length=1)
    tool_from_wrist: Matrix = ((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.02), (0.0, 0.0, 0.0, 1.0))
    materials: dict[str, RGBA] = Field(default_factory=dict)
    nominal_reach_m: float | None = None

    @field_validator("tool_from_wrist", mode="before")
    @classmethod
    def _tool_from_wrist(cls, v):
        return _matrix(v)


class HandArmFile(_Strict):
    kind: Literal["hand_arm"]
    name: str
    description: str
    arm: str = Field(description="an arm file's key")
    hand: str = Field(description="a hand file's key")


KINDS = {"hand": HandFile, "arm": ArmFile, "hand_arm": HandArmFile}
RobotFile = Union[HandFile, ArmFile, HandArmFile]


def parse_file(path: Path) -> RobotFile:
    """One robot file, validated; ``RobotFileError`` names the file, the field and the fix."""
    import yaml

    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise RobotFileError(f"robot file {path}: cannot read it ({exc.strerror or exc})") from None
    except yaml.YAMLError as exc:
        raise RobotFileError(f"robot file {path}: not valid YAML ({exc})") from None
    if not isinstance(data, dict) or data.get("kind") not in KINDS:
        raise RobotFileError(f"robot file {path}: it must be a mapping with `kind: hand`, `kind: arm` or `kind: hand_arm` "
                             f"(start from a built-in one: `handedit embodiments show allegro --file`)")
    try:
        return KINDS[data["kind"]].model_validate(data)
    except ValidationError as exc:
        lines = []
        for err in exc.errors()[:5]:
            where = ".".join(str(p) for p in err["loc"]) or "(top level)"
            lines.append(f"field {where}: {err['msg']}")
        raise RobotFileError(f"robot file {path}: " + "; ".join(lines)) from None


def _folders(raw: str | None) -> list[str]:
    """The entries of a ``$HANDEDIT_ROBOT_DIRS`` value (blank ones dropped)."""
    return [d for d in (raw or "").split(os.pathsep) if d.strip()]


def user_dirs() -> list[Path]:
    return [Path(p).expanduser() for p in _folders(os.environ.get(ROBOT_DIRS_ENV))]


_scopes_lock = threading.Lock()
_scoped: dict[str, int] = {}  # folder -> how many open ``robot_dirs_added`` scopes named it
_outside: list[str | None] = [None]  # the variable's value when the first open scope began


@contextlib.contextmanager
def robot_dirs_added(dirs: list[str]):
    """The run's ``robots:`` folders in ``$HANDEDIT_ROBOT_DIRS`` while the block runs, and only then.

    Scoped, not joined for good: a driver or a Dask worker serves many runs, and a folder of an
    earlier run that was since deleted would fail every later one ("not a folder"). Scopes nest and
    overlap across a worker's threads (a count per folder, under a lock): the variable holds the
    folders any open scope names, after the ones it held outside every scope. A folder that is not
    one, or a key defined twice, fails on entry, naming the files."""
    dirs = [str(d) for d in dirs]
    if not dirs:
        yield
        return
    with _scopes_lock:
        if not _scoped:
            _outside[0] = os.environ.get(ROBOT_DIRS_ENV)
        for d in dirs:
            _scoped[d] = _scoped.get(d, 0) + 1
        _set_scoped()
    try:
        current_files()
        yield
    finally:
        with _scopes_lock:
            for d in dirs:
                _scoped[d] -= 1
                if not _scoped[d]:
                    del _scoped[d]
            _set_scoped()


def _set_scoped() -> None:
    """The variable from the value outside the scopes and the open scopes' folders (lock held)."""
    outside = _outside[0]
    if _scoped:
        have = _folders(outside)
        os.environ[ROBOT_DIRS_ENV] = os.pathsep.join([*have, *(d for d in _scoped if d not in have)])
    elif outside is None:
        os.environ.pop(ROBOT_DIRS_ENV, None)
    else:
        os.environ[ROBOT_DIRS_ENV] = outside  # as it was, to the character


def _files_in(d: Path) -> list[Path]:
    return sorted([*d.rglob("*.yaml"), *d.rglob("*.yml")])


@functools.lru_cache(maxsize=1)
def _builtin_paths() -> tuple[Path, ...]:
    return tuple(_files_in(BUILTIN))


def robot_paths(dirs: list[Path]) -> dict[str, Path]:
    """key -> file of the built-in robots and of ``dirs``; a key twice is an error naming both."""
    out: dict[str, Path] = {}
    listed = [*_builtin_paths()]
    for d in dirs:
        if not d.is_dir():
            raise RobotFileError(f"${ROBOT_DIRS_ENV} lists {d}, which is not a folder; point it at folders of robot files")
        listed += _files_in(d)
    for p in listed:
        if p.stem in out:
            raise RobotFileError(f"robot key {p.stem!r} is defined twice: {out[p.stem]} and {p}; rename one file (its "
                                 f"stem is the key)")
        out[p.stem] = p
    return out


@functools.lru_cache(maxsize=256)
def _parsed(path: str, mtime_ns: int, size: int) -> RobotFile:
    return parse_file(Path(path))


def current_files() -> dict[str, tuple[Path, RobotFile]]:
    """Every robot file, parsed (cached per file and modification time)."""
    out = {}
    for key, p in robot_paths(user_dirs()).items():
        st = p.stat()
        out[key] = (p, _parsed(str(p), st.st_mtime_ns, st.st_size))
    return out
