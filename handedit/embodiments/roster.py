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
from handedit.embodiments.linkage import Linkage, Loop
from handedit.keypoints import FINGERS

ASSET_DIRS_ENV = "HANDEDIT_ASSET_DIRS"
RGBA = tuple[float, float, float, float]
CAPS = "@caps"  # a materials key LINK_REGEX@caps colours those links' joint caps (handedit.render.model)
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
    mount_at_root: bool = False  # the URDF includes its own wrist module: mount its root on a flange
    # what the URDF does not encode (handedit.embodiments.derive): (joint, source, multiplier,
    # offset) couplings written as <mimic>, and a link regex whose visuals are not the robot's
    couplings: tuple[tuple[str, str, float, float], ...] = ()
    hidden_visuals: str = ""
    linkages: tuple[Linkage, ...] = ()  # closed loops solved into polynomial mimics

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
class ArmAsset:
    """One candidate URDF of an arm (same ``source``/``path``/``package`` rules as UrdfAsset).

    ``ee_link`` carries the hand; ``ee_from_tool`` (4x4) places the tool frame (z out of the
    flange) in it; ``drop_links`` are subtrees removed before mounting (a stock gripper);
    ``mounts`` are exact ee_from_hand_root overrides keyed by the hand asset's ``path``
    (the dex-urdf ``assembly/`` values). See handedit.embodiments.compose.
    """

    source: Literal["asset_dir", "package"]
    path: str
    ee_link: str
    package: str = ""
    ee_from_tool: tuple[tuple[float, ...], ...] = ((1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1))
    drop_links: tuple[str, ...] = ()
    mounts: tuple[tuple[str, tuple[tuple[float, ...], ...]], ...] = ()

    @property
    def ee_from_tool_matrix(self) -> np.ndarray:
        return np.asarray(self.ee_from_tool, dtype=float).reshape(4, 4)


@dataclass(frozen=True)
class ArmSpec:
    """The arm of a hand-arm embodiment: URDF candidates, how the hand's wrist sits on the
    tool frame, render colours of arm links (empty: keep the URDF's own) and, optionally, a
    fixed nominal reach (None: computed from the chain by compose.nominal_reach)."""

    name: str
    assets: tuple[ArmAsset, ...]
    tool_from_wrist: tuple[tuple[float, ...], ...] = ((1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0.02), (0, 0, 0, 1))
    materials: dict[str, RGBA] = field(default_factory=dict, hash=False)
    nominal_reach_m: float | None = None

    @property
    def tool_from_wrist_matrix(self) -> np.ndarray:
        return np.asarray(self.tool_from_wrist, dtype=float).reshape(4, 4)

    def link_color(self, link_name: str) -> RGBA | None:
        for pattern, rgba in self.materials.items():
            if re.fullmatch(pattern, link_name):
                return rgba
        return None


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
    path: Path  # the URDF to load (a derived file when the asset has couplings or hidden visuals)
    asset: UrdfAsset
    source: Path | None = None  # the asset's own file (None: ``path`` is it)

    @property
    def origin(self) -> Path:
        return self.source or self.path


# ----------------------------------------------------------------------------------------
# helpers to write the table compactly

def _fingers(spec: dict[str, tuple[str | None, ...]], offsets: dict[str, tuple[float, float, float]] | None = None):
    """Correspondences from {finger: (mcp|cmc, pip|mcp, dip|ip, tip)} link names (None: absent)."""
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
MATTE_GRAY: RGBA = (0.50, 0.51, 0.52, 1.0)
GREEN: RGBA = (0.20, 0.85, 0.25, 1.0)

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

# Hands with no public URDF reachable here (no dex-urdf folder, no PyPI package we depend on):
# the expected dex-urdf-layout path is what a user provides under $HANDEDIT_ASSET_DIRS.
# Their MANO correspondences and wrist calibration are added with the asset (``keypoints=()``
# marks an embodiment whose URDF may be found but is not yet supported).
_IDENTITY = _T(np.eye(4))


def _expected_hand(folder: str, file: str) -> UrdfAsset:
    return UrdfAsset(source="asset_dir", path=f"hands/{folder}/{file}", keypoints=(), wrist_from_root=_IDENTITY)


# BrainCo Revo2 (BrainCoTech/revo2_description_ros1): 6 actuated joints, the distal joints
# follow their proximal ones as URDF mimic joints (thumb 1.0, fingers 1.155).
_REVO2 = UrdfAsset(
    source="asset_dir",
    path="hands/revo2_hand/urdf/revo2_right_hand_rel.urdf",
    keypoints=(_wrist("right_base_link"),)
    + _fingers({
        "thumb": ("right_thumb_metacarpal_link", "right_thumb_proximal_link", "right_thumb_distal_link", "right_thumb_tip_link"),
        "index": ("right_index_proximal_link", "right_index_distal_link", None, "right_index_tip_link"),
        "middle": ("right_middle_proximal_link", "right_middle_distal_link", None, "right_middle_tip_link"),
        "ring": ("right_ring_proximal_link", "right_ring_distal_link", None, "right_ring_tip_link"),
        "pinky": ("right_pinky_proximal_link", "right_pinky_distal_link", None, "right_pinky_tip_link"),
    }),
    wrist_from_root=_T([[0.9985, -0.00606, 0.05448, 0.0], [0.0124, 0.99308, -0.11677, 0.0], [-0.0534, 0.11727, 0.99166, 0.0], [0, 0, 0, 1]]),
)
# DexHand021 (DexRobot/dexrobot_urdf, the vendor's simplified meshes). Its README: the
# proximal and distal joints (*_3, *_4) are mechanically coupled on the real hand but not in
# the URDF; it gives no ratio, and both joints span [0, 1.3], so the coupling is 1:1. The
# middle finger's spread (joint3_1, limits +-0.001) is locked at 0; the red tip spheres and
# green pad boxes are debug visuals. The base runs ~9 cm below the palm (a wrist module):
# the wrist keypoint sits 9.5 cm up it, and an arm mounts the base.
_DEXHAND021 = UrdfAsset(
    source="asset_dir",
    path="hands/dexhand021/urdf/dexhand021_right_simplified.urdf",
    keypoints=(_wrist("right_hand_base", (0.0, 0.0, 0.095)),)
    + _fingers({
        "thumb": ("r_f_link1_1", "r_f_link1_3", "r_f_link1_4", "r_f_link1_tip"),
        "index": ("r_f_link2_2", "r_f_link2_3", "r_f_link2_4", "r_f_link2_tip"),
        "middle": ("r_f_link3_2", "r_f_link3_3", "r_f_link3_4", "r_f_link3_tip"),
        "ring": ("r_f_link4_2", "r_f_link4_3", "r_f_link4_4", "r_f_link4_tip"),
        "pinky": ("r_f_link5_2", "r_f_link5_3", "r_f_link5_4", "r_f_link5_tip"),
    }),
    wrist_from_root=_T([[0.99713, 0.01429, -0.0744, 0.00707], [-0.02237, 0.9938, -0.10891, 0.01035], [0.07238, 0.11027, 0.99126, -0.09417], [0, 0, 0, 1]]),
    locked_joints=(("r_f_joint3_1", 0.0),),
    couplings=tuple((f"r_f_joint{k}_4", f"r_f_joint{k}_3", 1.0, 0.0) for k in range(1, 6)),
    hidden_visuals=r"r_f_link\d_(tip|pad)",
    mount_at_root=True,
)
# OrcaHand v2 ships inside the PyPI package ``orca-arm`` (bimanual OpenArm, no licence
# metadata, 137 MB installed): not a dependency; provide a stand-alone right-hand URDF instead.
# ORCA v1 (orcahand/orcahand_description): its own wrist joint is held at 0 (the free root
# pose or the arm does its job); MCP abduction and flexion share one point, fingers have no DIP.
_ORCA = UrdfAsset(
    source="asset_dir",
    path="hands/orca_hand/v1/models/urdf/orcahand_right_rel.urdf",
    keypoints=(_wrist("right_wrist_jointbody"),)
    + _fingers({
        "thumb": ("right_thumb_mcp_jointbody", "right_thumb_pip_jointbody", "right_thumb_dip_jointbody", "right_thumb_fingertip"),
        "index": ("right_index_mcp_jointbody", "right_index_pip_jointbody", None, "right_index_fingertip"),
        "middle": ("right_middle_mcp_jointbody", "right_middle_pip_jointbody", None, "right_middle_fingertip"),
        "ring": ("right_ring_mcp_jointbody", "right_ring_pip_jointbody", None, "right_ring_fingertip"),
        "pinky": ("right_pinky_mcp_jointbody", "right_pinky_pip_jointbody", None, "right_pinky_fingertip"),
    }),
    wrist_from_root=_T([[-0.07202, 0.99724, -0.01781, 0.00849], [-0.99715, -0.07239, -0.0213, 0.08361], [-0.02253, 0.01622, 0.99961, -0.14874], [0, 0, 0, 1]]),
    locked_joints=(("right_wrist", 0.0),),
    mount_at_root=True,  # its tower (the wrist module, 15 cm below the palm) is what meets an arm
)
_RH5DG2 = _expected_hand("inspire_rh5dg2", "rh5dg2_right.urdf")

# OYMotion RoHand (oymotion/rohand_urdf_ros2): the URDF is an open tree of 25 joints; the
# real hand has 6 (a linear actuator per digit, and the thumb's rotation). Each finger's slider
# drives a slider-crank (rod ``slider_abpart`` pinned to the proximal phalanx at pin C) and a
# four-bar (``connecting`` link pinned to the distal phalanx at pin E); the thumb's slider, in
# its proximal phalanx, turns it about the thumb root through a short rod the URDF does not
# model (A on the root, B on the slider) and drives the distal phalanx through the
# ``connecting`` link (pin D). Pivots are the URDF's joint origins; link lengths (mm) are the
# vendor's calibration table (FingerMathURDF.py: L_AC, L_OC, L_BE, L_DE per finger; L_OA,
# L_AB, L_BP0, L_OP, L_CD, L_ED for the thumb), which also fixes each circle intersection's
# branch (the assembled one: its closed-loop curves agree with the vendor's to <= 0.006 rad
# for the proximal and distal joints; the vendor's connecting-link angle differs by up to
# 0.12 rad, and the loop closes only with ours). B is L_BP0 along the slider and L_OP across
# from the proximal pivot, in the slider frame.
def _rohand_finger(f: str, l_ac: float, l_oc: float, l_be: float, l_de: float) -> Linkage:
    return Linkage(
        actuator=f"{f}_slider_link",
        passive=(f"{f}_slider_abpart_link", f"{f}_proximal_link", f"{f}_distal_link", f"{f}_connecting_link"),
        loops=(
            Loop(f"{f}_slider_abpart_link", f"{f}_slider_abpart_link", l_ac / 1e3, f"{f}_proximal_link", f"{f}_proximal_link", l_oc / 1e3),
            Loop(f"{f}_connecting_link", f"{f}_connecting_link", l_be / 1e3, f"{f}_distal_link", f"{f}_distal_link", l_de / 1e3),
        ),
    )


_ROHAND_LINKAGES = (
    _rohand_finger("if", 19.63, 14.25, 34.14, 7.69),
    _rohand_finger("mf", 19.63, 14.31, 39.48, 7.69),
    _rohand_finger("rf", 19.63, 14.25, 34.14, 7.69),
    _rohand_finger("lf", 19.63, 14.27, 30.85, 7.53),
    Linkage(
        actuator="th_slider_link",
        passive=("th_proximal_link", "th_connecting_link", "th_distal_link"),
        loops=(
            Loop("th_root_link", "th_proximal_link", 10.00e-3, "th_slider_link", "th_proximal_link", 0.0, branch=-1,
                 length=10.98e-3, b_point=(-1.598e-3, -1.529e-3, 0.018e-3)),
            Loop("th_connecting_link", "th_connecting_link", 9.90e-3, "th_distal_link", "th_distal_link", 11.30e-3, branch=-1),
        ),
    ),
)
_ROHAND_TIPS = {"if": (-0.0291, 0.0, -0.0410), "mf": (-0.0296, 0.0, -0.0406), "rf": (-0.0262, 0.0, -0.0429),
                "lf": (-0.0182, 0.0, -0.0306), "th": (0.0230, -0.0152, -0.0024)}  # the distal meshes' far ends
_ROHAND = UrdfAsset(
    source="asset_dir",
    path="hands/rohand/urdf/rohand_right_rel.urdf",
    keypoints=(_wrist("base_link", (-0.02, 0.0, 0.0)),)
    + _fingers({
        "thumb": ("th_root_link", "th_proximal_link", "th_distal_link", None),
        "index": ("if_proximal_link", "if_distal_link", None, None),
        "middle": ("mf_proximal_link", "mf_distal_link", None, None),
        "ring": ("rf_proximal_link", "rf_distal_link", None, None),
        "pinky": ("lf_proximal_link", "lf_distal_link", None, None),
    })
    + tuple(KeypointLink(FINGERS[finger][-1], f"{f}_distal_link", "tip", _ROHAND_TIPS[f])
            for finger, f in (("thumb", "th"), ("index", "if"), ("middle", "mf"), ("ring", "rf"), ("pinky", "lf"))),
    wrist_from_root=_T([[-0.03447, 0.01836, -0.99924, -0.00069], [0.10771, -0.99394, -0.02198, 0.00215], [-0.99358, -0.10839, 0.03228, -0.01987], [0, 0, 0, 1]]),
    linkages=_ROHAND_LINKAGES,
)
# Sharpa Wave (sharpa-robotics/sharpa-urdf-usd-xml, wave_01): 22 joints; MCP flexion and
# abduction are two joints at one point (the *_MCP_VL link), the pinky adds a CMC.
_SHARPA = UrdfAsset(
    source="asset_dir",
    path="hands/sharpa_wave/wave_01/right_sharpa_wave/right_sharpa_wave_rel.urdf",
    keypoints=(_wrist("right_hand_C_MC"),)
    + _fingers({
        "thumb": ("right_thumb_CMC_VL", "right_thumb_MCP_VL", "right_thumb_DP", "right_thumb_fingertip"),
        "index": ("right_index_MCP_VL", "right_index_MP", "right_index_DP", "right_index_fingertip"),
        "middle": ("right_middle_MCP_VL", "right_middle_MP", "right_middle_DP", "right_middle_fingertip"),
        "ring": ("right_ring_MCP_VL", "right_ring_MP", "right_ring_DP", "right_ring_fingertip"),
        "pinky": ("right_pinky_MCP_VL", "right_pinky_MP", "right_pinky_DP", "right_pinky_fingertip"),
    }),
    wrist_from_root=_T([[0.99945, 0.03305, -0.00334, 0.0], [-0.03321, 0.99438, -0.10054, 0.0], [-0.0, 0.1006, 0.99493, 0.0], [0, 0, 0, 1]]),
)
# Wuji (wuji-technology/wuji-hand-description): finger1 is the thumb; each finger has MCP
# flexion + abduction (joint1, joint2), PIP (joint3), DIP (joint4). Its zero pose is below
# the thumb's joint1 limit: the rest pose is the zero pose clipped into the limits.
_WUJI = UrdfAsset(
    source="asset_dir",
    path="hands/wuji_hand/urdf/right.urdf",
    keypoints=(_wrist("right_palm_link"),)
    + _fingers({
        "thumb": ("right_finger1_link1", "right_finger1_link3", "right_finger1_link4", "right_finger1_tip_link"),
        "index": ("right_finger2_link1", "right_finger2_link3", "right_finger2_link4", "right_finger2_tip_link"),
        "middle": ("right_finger3_link1", "right_finger3_link3", "right_finger3_link4", "right_finger3_tip_link"),
        "ring": ("right_finger4_link1", "right_finger4_link3", "right_finger4_link4", "right_finger4_tip_link"),
        "pinky": ("right_finger5_link1", "right_finger5_link3", "right_finger5_link4", "right_finger5_tip_link"),
    }),
    wrist_from_root=_T([[0.99318, 0.0247, 0.11396, 0.0], [-0.01505, 0.99629, -0.08478, 0.0], [-0.11563, 0.08248, 0.98986, 0.0], [0, 0, 0, 1]]),
)

# ---- arms ------------------------------------------------------------------------------
_ERD = "cmeel.prefix/share/example-robot-data/robots/"
# Exact mounts of the dex-urdf assemblies (ee_from_hand_root; tests compare FK with assembly/*).
_MOUNT_UR5E_SHADOW = _T([[6.326794896668469e-06, 0.9999999999799859, 0.0, 0.0],
                         [-0.9999999999799858, 6.326794896668469e-06, 0.0, 0.0], [0, 0, 1, -0.01], [0, 0, 0, 1]])
_MOUNT_XARM7_ABILITY = _T([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.018], [0, 0, 0, 1]])
_MOUNT_RM75_INSPIRE = _IDENTITY

_UR5E_DEX = ArmAsset(source="asset_dir", path="arms/ur5e/ur5e_glb.urdf", ee_link="wrist_3_link",
                     mounts=((_SHADOW.path, _MOUNT_UR5E_SHADOW),))
_UR5_ERD = ArmAsset(source="package", package="example-robot-data", path=_ERD + "ur_description/urdf/ur5_robot.urdf",
                    ee_link="tool0")
_XARM7_DEX = ArmAsset(source="asset_dir", path="arms/xarm7/xarm7_glb.urdf", ee_link="link7",
                      mounts=((_ABILITY.path, _MOUNT_XARM7_ABILITY),))
_XARM7_ERD = ArmAsset(source="package", package="example-robot-data", path=_ERD + "xarm_description/urdf/xarm7.urdf",
                      ee_link="link7", mounts=((_ABILITY.path, _MOUNT_XARM7_ABILITY),))
_RM75_DEX = ArmAsset(source="asset_dir", path="arms/rm75/rm75_glb.urdf", ee_link="rm75_link_7",
                     mounts=((_INSPIRE.path, _MOUNT_RM75_INSPIRE),))
_IIWA7_DEX = ArmAsset(source="asset_dir", path="arms/iiwa7/iiwa7_glb.urdf", ee_link="link_7",
                      ee_from_tool=_T([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.035], [0, 0, 0, 1]]))
# Panda without its stock Franka gripper (the hand replaces it); panda_link8 is the flange.
_PANDA_ERD = ArmAsset(source="package", package="example-robot-data", path=_ERD + "panda_description/urdf/panda.urdf",
                      ee_link="panda_link8", drop_links=("panda_hand",))
# JAKA Zu7 (JAKARobotics/jaka_ros2) and RealMan RM65-B (RealManRobot/rm_models): their last
# link's mesh ends at its origin plane (z <= 0), so the flange face is the link frame, z out.
_JAKA_ZU7 = ArmAsset(source="asset_dir", path="arms/jaka_zu7/src/jaka_description/urdf/jaka_zu7_rel.urdf", ee_link="Link_6")
_RM65 = ArmAsset(source="asset_dir", path="arms/rm65/RM65/urdf/RM65-B/urdf/RM65-B_rel.urdf", ee_link="link_6")

UR5 = ArmSpec(name="UR5", assets=(_UR5E_DEX, _UR5_ERD))
XARM = ArmSpec(name="xArm", assets=(_XARM7_DEX, _XARM7_ERD))
RM75 = ArmSpec(name="RM75", assets=(_RM75_DEX,))
KUKA = ArmSpec(name="KUKA", assets=(_IIWA7_DEX,))
PANDA = ArmSpec(name="Panda", assets=(_PANDA_ERD,))
# their STL meshes carry no colour: the frozen descriptions' (Jaka metallic grey with blue joint
# caps: the end faces of its joint housings, ``LINK@caps``; RM65 smooth white)
JAKA_BLUE: RGBA = (0.16, 0.36, 0.78, 1.0)
JAKA = ArmSpec(name="Jaka Zu7", assets=(_JAKA_ZU7,), materials={r"Link_[1-6]@caps": JAKA_BLUE, r".*": GRAY})
RM65 = ArmSpec(name="RM65", assets=(_RM65,), materials={r".*": WHITE})

_HANDS: tuple[Embodiment, ...] = (
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
    Embodiment(
        id="dexhand021",
        name="DexHand021",
        track="hand",
        description=(
            "A metallic dexterous hand with dense exposed mechanisms, a ribbed silver palm surface, and "
            "articulated fingers composed of visible links and cable-like structures. Bright green fingertip "
            "markers make the hand visually distinctive and strongly mechanical."
        ),
        hand=HandSpec(assets=(_DEXHAND021,)),
        materials={r".*tip.*": GREEN, r".*": SILVER},
    ),
    Embodiment(
        id="orca",
        name="OrcaHand",
        track="hand",
        description=(
            "A dark robotic hand with a narrow palm and five slender fingers spread in a fan-like "
            "configuration. Alternating dark segments and bright fingertip caps create an open, lightweight, "
            "highly splayed silhouette."
        ),
        hand=HandSpec(assets=(_ORCA,)),
        materials={r".*(tip|Tip).*": WHITE, r".*": DARK},
    ),
    Embodiment(
        id="revo2",
        name="Revo2",
        track="hand",
        description=(
            "A smooth anthropomorphic robotic hand with a rounded human-like palm, slim fingers, and softly "
            "curved matte-gray surfaces. The design has limited exposed mechanics and a naturalistic silhouette."
        ),
        hand=HandSpec(assets=(_REVO2,)),
        materials={r".*": MATTE_GRAY},
    ),
    Embodiment(
        id="rh5dg2",
        name="RH5DG2",
        track="hand",
        description=(
            "A white-and-gray robotic hand with a rounded palm shell, dark cylindrical finger coverings, and "
            "a thick side thumb aligned close to the palm plane. It has an enclosed appearance with little "
            "exposed structure."
        ),
        hand=HandSpec(assets=(_RH5DG2,)),
        materials={r".*(base|palm).*": WHITE, r".*": DARK},
    ),
    Embodiment(
        id="rohand",
        name="RoHand",
        track="hand",
        description=(
            "A white robotic hand with a smooth enclosed palm shell, dark metallic finger segments, and a "
            "side-mounted thumb. Elongated anthropomorphic fingers and a compact rounded wrist base give it "
            "a polished integrated appearance."
        ),
        hand=HandSpec(assets=(_ROHAND,)),
        materials={r".*(base|palm).*": WHITE, r".*": DARK},
    ),
    Embodiment(
        id="sharpa",
        name="Sharpa",
        track="hand",
        description=(
            "A matte gray robotic hand with a clean anthropomorphic silhouette, smooth palm surfaces, and "
            "simple segmented fingers. The large articulated thumb contrasts with the otherwise minimal "
            "enclosed design."
        ),
        hand=HandSpec(assets=(_SHARPA,)),
        materials={r".*": MATTE_GRAY},
    ),
    Embodiment(
        id="wuji",
        name="Wuji",
        track="hand",
        description=(
            "A black-and-silver robotic hand with a glossy dark palm base, long light-gray articulated "
            "fingers made of segmented cylindrical links, and a widely extended side thumb."
        ),
        hand=HandSpec(assets=(_WUJI,)),
        materials={r".*(base|palm).*": BLACK, r".*": SILVER},
    ),
)
_HAND_COLOURS = {e.id: e.materials for e in _HANDS}
_ARMS: tuple[Embodiment, ...] = (
    Embodiment(
        id="jaka_zu7_dexhand021",
        name="Jaka Zu7 + DexHand021",
        track="hand_arm",
        description=(
            'A metallic-gray collaborative arm with blue circular joint caps, paired with a silver dexterous '
            'hand with dense exposed mechanisms, a ribbed palm surface, and slender articulated fingers. The '
            'transparent wrist housing and mechanical finger structure make it distinctive.'
        ),
        hand=HandSpec(assets=(_DEXHAND021,)),
        arm=JAKA,
        materials=_HAND_COLOURS["dexhand021"],
    ),
    Embodiment(
        id="kuka_sharpa",
        name="KUKA + Sharpa",
        track="hand_arm",
        description=(
            'A white KUKA-style arm with bright orange accent panels, paired with a smooth anthropomorphic '
            'hand. The clean enclosed hand silhouette contrasts with the strong white-orange arm styling.'
        ),
        hand=HandSpec(assets=(_SHARPA,)),
        arm=KUKA,
        materials=_HAND_COLOURS["sharpa"],
    ),
    Embodiment(
        id="panda_allegro",
        name="Panda + Allegro",
        track="hand_arm",
        description=(
            'A light Panda-style arm paired with a compact dark modular hand. The boxy palm, rectangular '
            'segmented fingers, and bright fingertip caps create a sharp contrast with the soft industrial '
            'arm.'
        ),
        hand=HandSpec(assets=(_ALLEGRO_DEX, _ALLEGRO_ERD)),
        arm=PANDA,
        materials=_HAND_COLOURS["allegro"],
    ),
    Embodiment(
        id="panda_orca",
        name="Panda + Orca",
        track="hand_arm",
        description=(
            'A light Panda-style arm attached to a dark hand with a narrow palm and strongly spread fingers. '
            'Long separated digits with bright caps create an open fan-like silhouette.'
        ),
        hand=HandSpec(assets=(_ORCA,)),
        arm=PANDA,
        materials=_HAND_COLOURS["orca"],
    ),
    Embodiment(
        id="rm65_brainco",
        name="RM65 + BrainCo",
        track="hand_arm",
        description=(
            'A smooth white arm paired with a compact anthropomorphic hand with a rounded palm shell, slim '
            'fingers, and a clean enclosed structure. The embodiment appears polished and tightly integrated.'
        ),
        hand=HandSpec(assets=(_REVO2,)),
        arm=RM65,
        materials=_HAND_COLOURS["revo2"],
    ),
    Embodiment(
        id="rm75_rohand",
        name="RM75 + RoHand",
        track="hand_arm",
        description=(
            'A smooth white RM75-style arm with curved segmented links and rounded joint housings, paired '
            'with a white enclosed RoHand with dark finger segments and a side-mounted thumb.'
        ),
        hand=HandSpec(assets=(_ROHAND,)),
        arm=RM75,
        materials=_HAND_COLOURS["rohand"],
    ),
    Embodiment(
        id="ur5_inspire",
        name="UR5 + RH56DFX",
        track="hand_arm",
        description=(
            'A metallic-gray industrial arm with rounded cylindrical links and blue joint caps, ending in a '
            'white-and-silver dexterous hand with a sculpted palm shell, dark finger pads, and a large side '
            'thumb.'
        ),
        hand=HandSpec(assets=(_INSPIRE,)),
        arm=UR5,
        materials=_HAND_COLOURS["inspire"],
    ),
    Embodiment(
        id="ur5_rh5dg2",
        name="UR5 + RH5DG2",
        track="hand_arm",
        description=(
            'A metallic-gray UR5-style arm with blue circular joint caps, attached to a white-and-gray hand '
            'with a rounded palm shell, dark cylindrical finger coverings, and a thick side thumb close to '
            'the palm plane.'
        ),
        hand=HandSpec(assets=(_RH5DG2,)),
        arm=UR5,
        materials=_HAND_COLOURS["rh5dg2"],
    ),
    Embodiment(
        id="ur5_schunk_svh",
        name="UR5 + Schunk Hand",
        track="hand_arm",
        description=(
            'A metallic-gray arm with blue round joint covers, paired with a robust white industrial hand. A '
            'broad palm, thick segmented fingers, gray fingertip pads, and heavy thumb create a sturdy '
            'precision-oriented look.'
        ),
        hand=HandSpec(assets=(_SCHUNK,)),
        arm=UR5,
        materials=_HAND_COLOURS["schunk_svh"],
    ),
    Embodiment(
        id="ur5_shadow",
        name="UR5 + Shadow Hand",
        track="hand_arm",
        description=(
            'A metallic-gray arm with blue circular joints, attached to a dark anthropomorphic hand with slim'
            ' multi-joint fingers and bright fingertip caps. The hand is lightweight and human-like relative '
            'to the heavier arm.'
        ),
        hand=HandSpec(assets=(_SHADOW,)),
        arm=UR5,
        materials=_HAND_COLOURS["shadow"],
    ),
    Embodiment(
        id="ur5_wuji",
        name="UR5 + Wuji",
        track="hand_arm",
        description=(
            'A metallic-gray arm with blue circular joint caps, ending in a slim dexterous hand with long '
            'narrow fingers and a thin side thumb. The hand appears lighter and more elongated than other '
            'UR5-based embodiments.'
        ),
        hand=HandSpec(assets=(_WUJI,)),
        arm=UR5,
        materials=_HAND_COLOURS["wuji"],
    ),
    Embodiment(
        id="xarm_ability",
        name="xArm + Ability",
        track="hand_arm",
        description=(
            'A white arm with smooth enclosed links, paired with a compact white hand with a rounded palm '
            'shell, dark finger coverings, and a thick side thumb. The embodiment is soft-contoured and '
            'highly enclosed.'
        ),
        hand=HandSpec(assets=(_ABILITY,)),
        arm=XARM,
        materials=_HAND_COLOURS["ability"],
    ),
    Embodiment(
        id="xarm_leap",
        name="xArm + Leap",
        track="hand_arm",
        description=(
            'A white arm with smooth rounded links, attached to a compact low-profile robotic hand with a '
            'blocky palm and modular fingers. Stacked box-like segments and bright caps give it a clean '
            'geometric appearance.'
        ),
        hand=HandSpec(assets=(_LEAP,)),
        arm=XARM,
        materials=_HAND_COLOURS["leap"],
    ),
)
_ROSTER: tuple[Embodiment, ...] = _HANDS + _ARMS
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
    """$HANDEDIT_ASSET_DIRS, then the folder ``handedit assets fetch`` fills by default."""
    from handedit.embodiments.fetch import default_dest

    raw = os.environ.get(ASSET_DIRS_ENV, "")
    dirs = [Path(p).expanduser() for p in raw.split(os.pathsep) if p.strip()]
    fetched = default_dest()
    return dirs + [fetched] if fetched.is_dir() and fetched not in dirs else dirs


def _package_file(dist_name: str, rel: str) -> Path | None:
    try:
        dist = importlib.metadata.distribution(dist_name)
    except importlib.metadata.PackageNotFoundError:
        return None
    p = Path(str(dist.locate_file(rel)))
    return p if p.is_file() else None


def _search(spec_assets, what: str, emb: Embodiment):
    """First existing candidate (asset dirs, then packages) or AssetsMissing naming what to provide."""
    dirs = asset_dirs()
    for a in spec_assets:
        if a.source == "asset_dir":
            for d in dirs:
                if (d / a.path).is_file():
                    return (d / a.path).resolve(), a
    for a in spec_assets:
        if a.source == "package":
            p = _package_file(a.package, a.path)
            if p is not None:
                return p.resolve(), a
    wanted = []
    for a in spec_assets:
        if a.source == "asset_dir":
            wanted.append(f"'{a.path}' (with its meshes) under a dex-urdf-layout directory listed in ${ASSET_DIRS_ENV}")
        else:
            wanted.append(f"the PyPI package '{a.package}' (pip install {a.package})")
    env = os.environ.get(ASSET_DIRS_ENV)
    raise AssetsMissing(
        f"no {what} URDF found for embodiment '{emb.id}' ({emb.name}). Provide "
        + " or ".join(wanted)
        + f". ${ASSET_DIRS_ENV} is currently {env!r} (searched: {[str(d) for d in dirs]}); "
        "run `handedit assets fetch` (downloads the public robots into the user cache, searched by "
        "default), or point it (os.pathsep-separated) at a folder in dex-urdf layout (hands/, arms/, "
        "assembly/), e.g. a checkout of https://github.com/dexsuite/dex-urdf."
    )


def resolve_asset(emb: Embodiment, spec: HandSpec | None = None) -> ResolvedAsset:
    """First existing hand URDF candidate of ``emb`` (hand-arm: its hand); see module doc for order."""
    path, asset = _search((spec or emb.hand).assets, "hand", emb)
    if not asset.keypoints:
        raise AssetsMissing(
            f"embodiment '{emb.id}' ({emb.name}): found {path}, but handedit has no MANO correspondences "
            f"or wrist calibration for it yet; add them to handedit/embodiments/roster.py (UrdfAsset.keypoints, "
            f"wrist_from_root via handedit.retarget.palm.calibrate_wrist_from_root)."
        )
    from handedit.embodiments.derive import derived_urdf

    derived = derived_urdf(path, asset)
    return ResolvedAsset(derived, asset, path if derived != path else None)


@dataclass(frozen=True)
class ResolvedArm:
    path: Path
    asset: ArmAsset


def resolve_arm(emb: Embodiment) -> ResolvedArm:
    """First existing arm URDF candidate of a hand-arm embodiment."""
    if emb.arm is None:
        raise EmbodimentError(f"embodiment '{emb.id}' is hand-only; it has no arm")
    path, asset = _search(emb.arm.assets, f"arm ({emb.arm.name})", emb)
    if not asset.ee_link:
        raise AssetsMissing(
            f"embodiment '{emb.id}': found arm URDF {path}, but its flange link and tool frame are not "
            f"defined yet; set ArmAsset.ee_link / ee_from_tool in handedit/embodiments/roster.py."
        )
    return ResolvedArm(path, asset)


def resolve_urdf(emb: Embodiment) -> Path:
    """Path of the embodiment's URDF: the hand's, or for hand-arm embodiments the composed
    arm+hand URDF (handedit.embodiments.compose). Raises ``AssetsMissing`` naming what to provide."""
    if emb.arm is None:
        return resolve_asset(emb).path
    from handedit.embodiments.compose import compose_embodiment

    return compose_embodiment(emb.id).urdf_path


def asset_status(emb: Embodiment) -> tuple[bool, str]:
    """(available, where from or what is missing) without loading meshes."""
    try:
        hand = resolve_asset(emb)
        src = hand.asset.package if hand.asset.source == "package" else str(hand.origin.parent)
        if emb.arm is not None:
            arm = resolve_arm(emb)
            src = (arm.asset.package if arm.asset.source == "package" else str(arm.path.parent)) + " + " + src
        return True, src
    except EmbodimentError as e:
        return False, str(e)


def render_materials(emb: Embodiment, link_names: list[str] | None = None) -> dict[str, RGBA]:
    """Render-time material overrides (link regex -> RGBA) for the URDF ``resolve_urdf`` returns.

    Hand-only: ``emb.materials``. Hand-arm: explicit per-link colours, the hand's from
    ``emb.materials`` on its original link names and the arm's from ``emb.arm.materials``
    (arm links without a match keep their URDF colours), so the hand's catch-all patterns
    never paint the arm.
    """
    if emb.arm is None:
        return dict(emb.materials)
    from handedit.embodiments.compose import compose_embodiment

    c = compose_embodiment(emb.id)
    hand_names = {v: k for k, v in c.link_map.items()}
    out: dict[str, RGBA] = {}
    for link in link_names if link_names is not None else c.kinematics().link_names:
        rgba = emb.link_color(hand_names[link]) if link in hand_names else emb.arm.link_color(link)
        if rgba is not None:
            out[re.escape(link)] = rgba
        if link not in hand_names:  # joint-cap colours of the arm's links
            for pattern, cap in emb.arm.materials.items():
                if pattern.endswith(CAPS) and re.fullmatch(pattern[: -len(CAPS)], link):
                    out[re.escape(link) + CAPS] = cap
                    break
    return out


def describe_embodiment(embodiment_id: str) -> tuple[str, list[str]]:
    """(track, qpos column names) of an embodiment; resolves and loads its URDF, so it
    raises the same ``EmbodimentError``s a later stage would (unknown id, assets, URDF).
    Hand-arm: arm joints first, then the hand's."""
    from handedit.embodiments.kinematics import get_kinematics

    emb = get_embodiment(embodiment_id)
    return emb.track, list(get_kinematics(resolve_urdf(emb)).joint_names)
