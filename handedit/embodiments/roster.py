"""The embodiment roster: which robot, where its URDF lives, how MANO maps onto it.

The robots are data: one YAML file per hand, per arm and per hand-arm
(``handedit/embodiments/robots/``, and a user's in ``$HANDEDIT_ROBOT_DIRS``; schema in
``handedit.embodiments.robot_files``). This module turns them into one frozen ``Embodiment``
per target robot (URDF asset candidates, resolved at run time and never downloaded; MANO
keypoint correspondences for retargeting; the fixed SE(3) from the MANO wrist frame to the
robot root link; the paper's frozen description; render colours) and resolves their assets.
It holds no robot.

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
    weight_scale: tuple[tuple[str, float], ...] = ()  # (kind, multiplier): the robot's own retargeting weights

    def weight(self, kind: str, base: float) -> float:
        """A keypoint kind's weight in the retargeting cost: the run's, times this robot's multiplier."""
        return base * dict(self.weight_scale).get(kind, 1.0)

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
    # the robot files it is made of (its own first; a hand-arm's arm and hand after it)
    files: tuple[str, ...] = field(default=(), compare=False, hash=False)

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
# the roster: robot files (handedit.embodiments.robot_files) -> the frozen specs above

_KINDS: dict[str, tuple[Kind, ...]] = {f: (("cmc", "mcp", "pip", "tip") if f == "thumb" else ("mcp", "pip", "dip", "tip"))
                                       for f in FINGERS}


def _floats(v) -> tuple[float, ...]:
    return tuple(float(x) for x in v)


def _keypoints(u) -> tuple[KeypointLink, ...]:
    """Wrist, then each finger's links in order, then the extra keypoints (the order the
    retargeting cost sums them in)."""
    from handedit.keypoints import JOINT_INDEX

    if u.wrist is None:
        return ()
    out = [KeypointLink(0, u.wrist.link, "wrist", _floats(u.wrist.offset))]
    for finger, links in u.fingers.items():
        for mano, entry, kind in zip(FINGERS[finger], links, _KINDS[finger]):
            if entry is not None:
                link, offset = (entry, (0.0, 0.0, 0.0)) if isinstance(entry, str) else (entry.link, entry.offset)
                out.append(KeypointLink(mano, link, kind, _floats(offset)))
    for x in u.extra_keypoints:
        finger = x.joint.split("_")[0]
        mano = JOINT_INDEX[x.joint]
        out.append(KeypointLink(mano, x.link, _KINDS[finger][FINGERS[finger].index(mano)], _floats(x.offset)))
    return tuple(out)


def _hand_asset(u, weights: dict | None = None) -> UrdfAsset:
    return UrdfAsset(
        weight_scale=tuple(sorted((k, float(w)) for k, w in (weights or {}).items())),
        source=u.source, path=u.path, package=u.package, keypoints=_keypoints(u), wrist_from_root=u.wrist_from_root,
        locked_joints=tuple((n, float(v)) for n, v in u.locked_joints.items()), mount_at_root=u.mount_at_root,
        couplings=tuple((c.joint, c.follows, float(c.multiplier), float(c.offset)) for c in u.couplings),
        hidden_visuals=u.hidden_visuals,
        linkages=tuple(Linkage(l.actuator, tuple(l.passive), tuple(Loop(**lp.model_dump()) for lp in l.loops))
                       for l in u.linkages))


def _arm_spec(f) -> ArmSpec:
    assets = tuple(ArmAsset(source=a.source, path=a.path, ee_link=a.ee_link, package=a.package, ee_from_tool=a.ee_from_tool,
                            drop_links=tuple(a.drop_links), mounts=tuple(a.mounts.items())) for a in f.urdf)
    return ArmSpec(name=f.name, assets=assets, tool_from_wrist=f.tool_from_wrist, materials=dict(f.materials),
                   nominal_reach_m=f.nominal_reach_m)


@dataclass(frozen=True)
class Roster:
    embodiments: dict[str, Embodiment]
    hands: dict[str, HandSpec]
    arms: dict[str, ArmSpec]


def _build(files: tuple) -> Roster:
    """Hands (by key), then hand-arms (by key); a hand-arm names its arm and hand by key."""
    from handedit.embodiments.robot_files import RobotFileError

    by_kind: dict[str, dict] = {"hand": {}, "arm": {}, "hand_arm": {}}
    for key, path, f in files:
        by_kind[f.kind][key] = (path, f)
    hands = {k: HandSpec(assets=tuple(_hand_asset(u, f.retarget_weights) for u in f.urdf), side=f.side)
             for k, (_, f) in by_kind["hand"].items()}
    arms = {k: _arm_spec(f) for k, (_, f) in by_kind["arm"].items()}
    embs: dict[str, Embodiment] = {}
    for k, (path, f) in by_kind["hand"].items():
        embs[k] = Embodiment(id=k, name=f.name, track="hand", description=f.description, hand=hands[k],
                             materials=dict(f.materials), files=(str(path),))
    for k, (path, f) in by_kind["hand_arm"].items():
        for field_name, known in (("hand", hands), ("arm", arms)):
            if getattr(f, field_name) not in known:
                raise RobotFileError(f"robot file {path}: field {field_name}: no {field_name} file with key "
                                     f"{getattr(f, field_name)!r}; the {field_name}s are {', '.join(sorted(known))}")
        hand_path, hand_file = by_kind["hand"][f.hand]
        embs[k] = Embodiment(id=k, name=f.name, track="hand_arm", description=f.description, hand=hands[f.hand],
                             arm=arms[f.arm], materials=dict(hand_file.materials),
                             files=(str(path), str(by_kind["arm"][f.arm][0]), str(hand_path)))
    return Roster(embs, hands, arms)


_ROSTERS: dict[tuple, Roster] = {}


def roster() -> Roster:
    """The roster of the built-in robot files and ``$HANDEDIT_ROBOT_DIRS`` (rebuilt when a file
    is added, removed or changed)."""
    from handedit.embodiments.robot_files import current_files

    files = tuple((k, p, f) for k, (p, f) in current_files().items())
    key = tuple((k, str(p), id(f)) for k, p, f in files)
    if key not in _ROSTERS:
        _ROSTERS.clear()
        _ROSTERS[key] = _build(tuple(sorted(files, key=lambda x: (x[2].kind != "hand", x[0]))))
    return _ROSTERS[key]


def list_embodiments() -> list[Embodiment]:
    return list(roster().embodiments.values())


def get_embodiment(embodiment_id: str) -> Embodiment:
    embs = roster().embodiments
    try:
        return embs[embodiment_id]
    except KeyError:
        raise EmbodimentError(
            f"unknown embodiment id {embodiment_id!r}; known ids: {', '.join(sorted(embs))} (a new robot is one file: "
            f"see `handedit embodiments show allegro --file`)"
        ) from None


def hand_spec(key: str) -> HandSpec:
    """A hand file's URDF candidates (``robots/hands/<key>.yaml``)."""
    return roster().hands[key]


def arm_spec(key: str) -> ArmSpec:
    """An arm file's spec (``robots/arms/<key>.yaml``)."""
    return roster().arms[key]


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
            f"or wrist calibration for it yet; add `wrist:` and `fingers:` to its robot file {_hand_file(emb)}, then "
            f"`handedit embodiments check {_hand_file(emb)}` fits the wrist_from_root to paste in."
        )
    from handedit.embodiments.derive import derived_urdf

    derived = derived_urdf(path, asset)
    return ResolvedAsset(derived, asset, path if derived != path else None)


def _hand_file(emb: Embodiment) -> str:
    return emb.files[-1] if emb.files else "(its hand file)"


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
            f"defined yet; set `ee_link` (and `ee_from_tool`) in its arm file {emb.files[1] if len(emb.files) > 1 else ''}."
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
