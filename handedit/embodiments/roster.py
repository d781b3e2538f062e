"""The embodiment roster: which robot, where its URDF lives, how MANO maps onto it.

One frozen ``Embodiment`` per target robot. Everything embodiment-specific that later
stages need is here and nowhere else: URDF asset candidates (resolved at run time, never
downloaded), MANO keypoint correspondences for retargeting, the fixed SE(3) from the
MANO wrist frame to the robot root link, the frozen text description from the paper's
Embodiment Reference Bank, and render-time material colours consistent with it.

Asset resolution order (first hit wins):
  1. user asset dirs in dex-urdf layout (``hands/``, ``arms/``, ``assembly/``), listed in
     the env var ``HANDEDIT_ASSET_DIRS`` (os.pathsep-separated);
  2. PyPI packages that ship real URDFs (``example-robot-data``: Allegro right hand).

Wrist frame convention (``handedit.retarget.palm``): origin at the wrist keypoint, z from
the wrist towards the middle MCP, y across the palm towards the index side (orthogonal
to z), x = y x z (the palm normal, pointing out of the palm for a right hand).
"""

from __future__ import annotations

import importlib.metadata
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from handedit.embodiments.errors import AssetsMissing, EmbodimentError

ASSET_DIRS_ENV = "HANDEDIT_ASSET_DIRS"
RGBA = tuple[float, float, float, float]
Kind = Literal["wrist", "cmc", "mcp", "pip", "dip", "tip"]


@dataclass(frozen=True)
class KeypointLink:
    """MANO keypoint ``mano`` (index into handedit.keypoints.MANO_JOINTS) sits at
    ``offset`` (metres, link frame) on robot link ``link``. ``kind`` selects its weight."""

    mano: int
    link: str
    kind: Kind
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class UrdfAsset:
    """One candidate URDF for an embodiment plus the data that depends on that file.

    source="asset_dir": ``path`` is relative to a dex-urdf root in HANDEDIT_ASSET_DIRS.
    source="package": ``path`` is a file of the installed distribution ``package``.
    ``wrist_from_root`` (4x4, row-major tuple) places the URDF root link in the MANO wrist
    frame; ``locked_joints`` are held fixed while retargeting (e.g. Shadow's wrist joints,
    redundant with the free 6-DoF root pose).
    """

    source: Literal["asset_dir", "package"]
    path: str
    keypoints: tuple[KeypointLink, ...]
    wrist_from_root: tuple[tuple[float, ...], ...]
    package: str = ""
    locked_joints: tuple[tuple[str, float], ...] = ()

    @property
    def wrist_from_root_matrix(self) -> np.ndarray:
        """The 4x4 transform with its rotation re-orthonormalised (the table is rounded)."""
        T = np.asarray(self.wrist_from_root, dtype=float).reshape(4, 4).copy()
        u, _, vt = np.linalg.svd(T[:3, :3])
        T[:3, :3] = u @ vt
        return T


@dataclass(frozen=True)
class HandSpec:
    assets: tuple[UrdfAsset, ...]  # candidates; resolution order is by source (see module doc)
    side: Literal["right", "left"] = "right"


@dataclass(frozen=True)
class ArmSpec:
    """The arm of a hand-arm embodiment (filled in by the hand-arm issue)."""

    assets: tuple[UrdfAsset, ...]
    ee_link: str
    ee_from_hand_root: tuple[tuple[float, ...], ...]  # 4x4 mount transform, row-major
    nominal_reach_m: float


@dataclass(frozen=True)
class Embodiment:
    id: str
    name: str
    track: Literal["hand", "hand_arm"]
    description: str  # frozen, verbatim from the paper's Embodiment Reference Bank
    hand: HandSpec
    arm: ArmSpec | None = None
    # link-name regex (re.fullmatch, first match wins) -> RGBA in [0,1]
    materials: dict[str, RGBA] = field(default_factory=dict, hash=False)

    def link_color(self, link_name: str) -> RGBA | None:
        """Render colour of a link from ``materials`` (None: keep the URDF's own)."""
        for pattern, rgba in self.materials.items():
            if re.fullmatch(pattern, link_name):
                return rgba
        return None


@dataclass(frozen=True)
class ResolvedAsset:
    path: Path
    asset: UrdfAsset


# ----------------------------------------------------------------------------------------
# helpers to write the table compactly

def _fingers(spec: dict[str, tuple[str | None, ...]], offsets: dict[str, tuple[float, float, float]] | None = None):
    """Correspondences from {finger: (mcp|cmc, pip|mcp, dip|ip, tip)} link names (None: absent)."""
    from handedit.keypoints import FINGERS

    offsets = offsets or {}
    out = []
    for finger, links in spec.items():
        kinds: tuple[Kind, ...] = ("cmc", "mcp", "pip", "tip") if finger == "thumb" else ("mcp", "pip", "dip", "tip")
        for mano, link, kind in zip(FINGERS[finger], links, kinds):
            if link is not None:
                out.append(KeypointLink(mano, link, kind, offsets.get(link, (0.0, 0.0, 0.0))))
    return tuple(out)


def _wrist(link: str, offset=(0.0, 0.0, 0.0)) -> KeypointLink:
    return KeypointLink(0, link, "wrist", offset)


def _T(rows) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(v) for v in r) for r in rows)


WHITE: RGBA = (0.92, 0.92, 0.90, 1.0)
BLACK: RGBA = (0.08, 0.08, 0.09, 1.0)
DARK: RGBA = (0.15, 0.15, 0.16, 1.0)
GRAY: RGBA = (0.55, 0.56, 0.58, 1.0)
SILVER: RGBA = (0.75, 0.76, 0.78, 1.0)

# wrist_from_root values are calibrated by handedit.retarget.palm.calibrate_wrist_from_root
# at the robot's neutral pose (tests/test_embodiments.py checks they stay consistent).

_ALLEGRO_DEX = UrdfAsset(
    source="asset_dir",
    path="hands/allegro_hand/allegro_hand_right_glb.urdf",
    keypoints=(_wrist("wrist"),)
    + _fingers({
        "thumb": ("link_13.0", "link_14.0", "link_15.0", "link_15.0_tip"),
        "index": ("link_1.0", "link_2.0", "link_3.0", "link_3.0_tip"),
        "middle": ("link_5.0", "link_6.0", "link_7.0", "link_7.0_tip"),
        "ring": ("link_9.0", "link_10.0", "link_11.0", "link_11.0_tip"),
    }),
    wrist_from_root=_T([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.095], [0, 0, 0, 1]]),
)
_ALLEGRO_ERD = UrdfAsset(
    source="package",
    package="example-robot-data",
    path="cmeel.prefix/share/example-robot-data/robots/allegro_hand_description/urdf/allegro_right_hand.urdf",
    keypoints=(_wrist("palm_link", (0.0, 0.0, -0.095)),)
    + _fingers(
        {
            "thumb": ("link_13.0", "link_14.0", "link_15.0", "link_15.0_tip"),
            "index": ("link_1.0", "link_2.0", "link_3.0", "link_3.0_tip"),
            "middle": ("link_5.0", "link_6.0", "link_7.0", "link_7.0_tip"),
            "ring": ("link_9.0", "link_10.0", "link_11.0", "link_11.0_tip"),
        },
        # the tip links sit at the centre of the 12 mm fingertip sphere; move to its end
        offsets={f"link_{i}.0_tip": (0.0, 0.0, 0.012) for i in (3, 7, 11, 15)},
    ),
    wrist_from_root=_T([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.095], [0, 0, 0, 1]]),
)

_SHADOW = UrdfAsset(
    source="asset_dir",
    path="hands/shadow_hand/shadow_hand_right_glb.urdf",
    keypoints=(_wrist("palm"),)
    + _fingers({
        "thumb": ("thbase", "thhub", "thdistal", "thtip"),
        "index": ("ffknuckle", "ffmiddle", "ffdistal", "fftip"),
        "middle": ("mfknuckle", "mfmiddle", "mfdistal", "mftip"),
        "ring": ("rfknuckle", "rfmiddle", "rfdistal", "rftip"),
        "pinky": ("lfknuckle", "lfmiddle", "lfdistal", "lftip"),
    }),
    wrist_from_root=_T([[1.0, -0.00001, 0.0, -0.01], [0.00001, 0.99388, -0.11043, 0.02728], [0.0, 0.11043, 0.99388, -0.2455], [0, 0, 0, 1]]),
    locked_joints=(("WRJ2", 0.0), ("WRJ1", 0.0)),
)

_LEAP = UrdfAsset(
    source="asset_dir",
    path="hands/leap_hand/leap_hand_right.urdf",
    keypoints=(_wrist("base", (0.015, 0.016, 0.0)),)
    + _fingers({
        "thumb": ("thumb_pip", "thumb_dip", "thumb_fingertip", "thumb_tip_head"),
        "index": ("mcp_joint", "dip", "fingertip", "index_tip_head"),
        "middle": ("mcp_joint_2", "dip_2", "fingertip_2", "middle_tip_head"),
        "ring": ("mcp_joint_3", "dip_3", "fingertip_3", "ring_tip_head"),
    }),
    wrist_from_root=_T([[0.99917, 0.00004, -0.04067, -0.01499], [0.00014, 0.99999, 0.00439, -0.016], [0.04067, -0.0044, 0.99916, -0.00054], [0, 0, 0, 1]]),
)

_INSPIRE = UrdfAsset(
    source="asset_dir",
    path="hands/inspire_hand/inspire_hand_right.urdf",
    keypoints=(_wrist("hand_base_link"),)
    + _fingers({
        "thumb": ("thumb_proximal_base", "thumb_proximal", "thumb_intermediate", "thumb_tip"),
        "index": ("index_proximal", "index_intermediate", None, "index_tip"),
        "middle": ("middle_proximal", "middle_intermediate", None, "middle_tip"),
        "ring": ("ring_proximal", "ring_intermediate", None, "ring_tip"),
        "pinky": ("pinky_proximal", "pinky_intermediate", None, "pinky_tip"),
    }),
    wrist_from_root=_T([[1.0, -0.00003, 0.00208, 0.0], [0.00023, 0.99557, -0.09404, 0.0], [-0.00207, 0.09404, 0.99557, 0.0], [0, 0, 0, 1]]),
)

_ABILITY = UrdfAsset(
    source="asset_dir",
    path="hands/ability_hand/ability_hand_right_glb.urdf",
    keypoints=(_wrist("base"),)
    + _fingers({
        "thumb": ("thumb_L1", "thumb_L2", None, "thumb_tip"),
        "index": ("index_L1", "index_L2", None, "index_tip"),
        "middle": ("middle_L1", "middle_L2", None, "middle_tip"),
        "ring": ("ring_L1", "ring_L2", None, "ring_tip"),
        "pinky": ("pinky_L1", "pinky_L2", None, "pinky_tip"),
    }),
    wrist_from_root=_T([[0.99323, 0.02572, 0.11329, 0.0], [-0.01593, 0.99613, -0.08649, 0.0], [-0.11507, 0.0841, 0.98979, 0.0], [0, 0, 0, 1]]),
)

_SCHUNK = UrdfAsset(
    source="asset_dir",
    path="hands/schunk_hand/schunk_svh_hand_right_glb.urdf",
    keypoints=(_wrist("right_hand_base_link"),)
    + _fingers({
        "thumb": ("right_hand_a", "right_hand_b", "right_hand_c", "thtip"),
        "index": ("right_hand_l", "right_hand_p", "right_hand_t", "fftip"),
        "middle": ("right_hand_k", "right_hand_o", "right_hand_s", "mftip"),
        "ring": ("right_hand_j", "right_hand_n", "right_hand_r", "rftip"),
        "pinky": ("right_hand_i", "right_hand_m", "right_hand_q", "lftip"),
    }),
    wrist_from_root=_T([[0.99255, -0.02843, 0.11847, 0.0], [0.02823, 0.9996, 0.00337, 0.0], [-0.11852, 0.0, 0.99295, 0.0], [0, 0, 0, 1]]),
)

_ROSTER: tuple[Embodiment, ...] = (
    Embodiment(
        id="allegro",
        name="Allegro",
        track="hand",
        description=(
            "A compact black robotic hand with a boxy palm, three straight front fingers made of "
            "rectangular joint modules, and a side thumb built from similar segmented black links. "
            "White rounded fingertip caps give the hand a high-contrast black-and-white appearance."
        ),
        hand=HandSpec(assets=(_ALLEGRO_DEX, _ALLEGRO_ERD)),
        materials={r"link_(3|7|11|15)\.0_tip": WHITE, r".*": BLACK},
    ),
    Embodiment(
        id="shadow",
        name="Shadow Hand",
        track="hand",
        description=(
            "A black anthropomorphic robotic hand with slim multi-joint fingers, white joint markings, "
            "and a curved white support structure near the wrist. The long human-like proportions make "
            "it dexterous but lightweight."
        ),
        hand=HandSpec(assets=(_SHADOW,)),
        materials={r"forearm|wrist": WHITE, r".*(knuckle|hub|base)": WHITE, r".*": BLACK},
    ),
    Embodiment(
        id="leap",
        name="Leap",
        track="hand",
        description=(
            "A compact black robotic hand with a low-profile rectangular palm and fingers made of stacked "
            "box-like modules. The white fingertip caps and short angular side thumb give the hand a simple "
            "modular appearance."
        ),
        hand=HandSpec(assets=(_LEAP,)),
        materials={r"(thumb_)?fingertip(_\d)?|.*tip_head": WHITE, r".*": BLACK},
    ),
    Embodiment(
        id="inspire",
        name="RH56DFX",
        track="hand",
        description=(
            "A white-and-silver robotic hand with a sculpted palm shell, black finger pads, and a diagonal "
            "striped panel across the back of the palm. The large articulated side thumb and metallic "
            "details are visually distinctive."
        ),
        hand=HandSpec(assets=(_INSPIRE,)),
        materials={r"base|hand_base_link": WHITE, r".*_proximal(_base)?": SILVER, r".*": BLACK},
    ),
    Embodiment(
        id="ability",
        name="Ability",
        track="hand",
        description=(
            "A smooth white robotic hand with a rounded palm shell, dark rubber-like finger coverings, and "
            "a thick side-mounted thumb. The overall shape is compact and softly contoured, with minimal "
            "exposed mechanics and a clean cylindrical wrist base."
        ),
        hand=HandSpec(assets=(_ABILITY,)),
        materials={r"base(_link)?|thumb_base|thumb_L1": WHITE, r".*": DARK},
    ),
    Embodiment(
        id="schunk_svh",
        name="Schunk SVH",
        track="hand",
        description=(
            "A white dexterous hand with gray fingertip pads, robust finger links, and a dark central palm "
            "pad. The circular wrist base and thick articulated thumb give the hand a sturdy industrial "
            "appearance."
        ),
        hand=HandSpec(assets=(_SCHUNK,)),
        materials={r"right_hand_(c|t|s|r|q)|.*tip": GRAY, r"right_hand_e[12]": DARK, r".*": WHITE},
    ),
)
_BY_ID = {e.id: e for e in _ROSTER}


def list_embodiments() -> list[Embodiment]:
    return list(_ROSTER)


def get_embodiment(embodiment_id: str) -> Embodiment:
    try:
        return _BY_ID[embodiment_id]
    except KeyError:
        raise EmbodimentError(
            f"unknown embodiment id {embodiment_id!r}; known ids: {', '.join(sorted(_BY_ID))}"
        ) from None


def asset_dirs() -> list[Path]:
    raw = os.environ.get(ASSET_DIRS_ENV, "")
    return [Path(p).expanduser() for p in raw.split(os.pathsep) if p.strip()]


def _package_file(dist_name: str, rel: str) -> Path | None:
    try:
        dist = importlib.metadata.distribution(dist_name)
    except importlib.metadata.PackageNotFoundError:
        return None
    p = Path(str(dist.locate_file(rel)))
    return p if p.is_file() else None


def resolve_asset(emb: Embodiment, spec: HandSpec | ArmSpec | None = None) -> ResolvedAsset:
    """First existing URDF candidate of ``emb`` (its hand by default); see module doc for order."""
    spec = spec or emb.hand
    dirs = asset_dirs()
    for a in spec.assets:
        if a.source == "asset_dir":
            for d in dirs:
                if (d / a.path).is_file():
                    return ResolvedAsset((d / a.path).resolve(), a)
    for a in spec.assets:
        if a.source == "package":
            p = _package_file(a.package, a.path)
            if p is not None:
                return ResolvedAsset(p.resolve(), a)
    wanted = []
    for a in spec.assets:
        if a.source == "asset_dir":
            wanted.append(f"'{a.path}' under a dex-urdf directory listed in ${ASSET_DIRS_ENV}")
        else:
            wanted.append(f"the PyPI package '{a.package}' (pip install {a.package})")
    env = os.environ.get(ASSET_DIRS_ENV)
    raise AssetsMissing(
        f"no URDF found for embodiment '{emb.id}' ({emb.name}). Provide "
        + " or ".join(wanted)
        + f". ${ASSET_DIRS_ENV} is currently {env!r} (searched: {[str(d) for d in dirs]}); "
        "point it (os.pathsep-separated) at a checkout of https://github.com/dexsuite/dex-urdf "
        "(the folder that holds hands/, arms/, assembly/)."
    )


def resolve_urdf(emb: Embodiment) -> Path:
    """Path of the embodiment's URDF (raises ``AssetsMissing`` naming what to provide)."""
    return resolve_asset(emb).path


def describe_embodiment(embodiment_id: str) -> tuple[str, list[str]]:
    """(track, qpos column names) of an embodiment; resolves and loads its URDF, so it
    raises the same ``EmbodimentError``s a later stage would (unknown id, assets, URDF)."""
    from handedit.embodiments.kinematics import get_kinematics

    emb = get_embodiment(embodiment_id)
    return emb.track, list(get_kinematics(resolve_urdf(emb)).joint_names)
