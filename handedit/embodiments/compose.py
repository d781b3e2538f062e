"""Hand-arm composition: an arm URDF + a hand URDF + a mount transform -> one robot.

Public API (used by retargeting's virtual-base search, rendering and the reference bank)::

    from handedit.embodiments.compose import compose_embodiment, nominal_reach, compose_urdf

    c = compose_embodiment("ur5_shadow")        # ComposedEmbodiment (cached per process)
    c.urdf_path                                 # composed URDF file (a cache file; assets untouched)
    kin = c.kinematics()                        # casadi Kinematics of the whole arm+hand tree
    kin.joint_names == [*c.arm_joint_names, *c.hand_joint_names]   # qpos order: arm first
    c.base_link, c.ee_link, c.hand_root         # arm root, arm flange link, hand URDF root (composed names)
    c.ee_from_hand_root                         # (4,4) the mount transform
    c.keypoints                                 # hand KeypointLinks renamed to composed link names
    c.wrist_from_root                           # (4,4) MANO wrist frame <- hand root (as for the hand alone)
    c.nominal_reach_m                           # L_r of the arm (virtual-base grid scales by it)
    c.arm_slice, c.hand_slice                   # column slices of qpos
    kin.fk_expr(link) / kin.jacobian_function(link)   # symbolic FK/Jacobian, base frame = c.base_link

``resolve_urdf(emb)`` of a hand-arm embodiment returns ``compose_embodiment(emb.id).urdf_path``,
so everything that takes a URDF path (Kinematics, RobotRenderer, describe_embodiment) works on
hand-arm embodiments unchanged.

Why a composed file: yourdfpy, the renderer and casadi FK all consume one URDF tree, and asset
files must never be edited. The composed URDF copies both trees into one XML document with
mesh filenames made absolute, hand names that clash with arm names prefixed ``hand_``
(``link_map`` records it), optional arm subtrees pruned (e.g. Panda's stock gripper), and one
fixed joint ``handedit_mount`` from the arm's ``ee_link`` to the hand's root link. It is
written atomically to ``$HANDEDIT_CACHE_DIR/composed`` (default ``~/.cache/handedit``), named
by a digest of its inputs, so concurrent workers agree on it.

Mount transform: ``ee_from_hand_root`` = an exact override for an (arm asset, hand asset) pair
(the dex-urdf ``assembly/`` values) or else ``ee_from_tool @ tool_from_wrist @ wrist_from_root``:
the arm asset's tool frame (z out of the flange), the MANO wrist frame placed a fixed adapter
length along it, and the hand's own wrist calibration. So every hand meets every arm the same way.
A hand whose URDF carries its own wrist module below the palm (``UrdfAsset.mount_at_root``, e.g.
ORCA's tower) is placed with the same orientation but its root, not its wrist, at that point:
otherwise the module would sit inside the arm's last link.

Nominal reach L_r (``nominal_reach``): the largest distance from the first actuated joint's
axis origin (the shoulder) to the ee link over in-limit joint samples (fixed seed): the
arm's reach from its URDF kinematic chain, honouring joint limits.
"""

from __future__ import annotations

import functools
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from lxml import etree

from handedit.embodiments.errors import BrokenUrdf, EmbodimentError
from handedit.cache import cache_root
from handedit.embodiments.urdf import absolutize_meshes, matrix_to_xyz_rpy, parse_urdf_xml
from handedit.files import atomic_write
from handedit.setup_meter import metered

MOUNT_JOINT = "handedit_mount"
CLASH_PREFIX = "hand_"


def _cache_dir() -> Path:
    d = cache_root() / "composed"
    d.mkdir(parents=True, exist_ok=True)
    return d


def _prune(root: etree._Element, drop_links: tuple[str, ...], path: Path) -> None:
    """Remove the subtrees rooted at ``drop_links`` (links and the joints into/inside them)."""
    if not drop_links:
        return
    children: dict[str, list[str]] = {}
    for j in root.findall("joint"):
        children.setdefault(j.find("parent").get("link"), []).append(j.find("child").get("link"))
    names = {l.get("name") for l in root.findall("link")}
    doomed: set[str] = set()
    stack = list(drop_links)
    while stack:
        n = stack.pop()
        if n not in names:
            raise EmbodimentError(f"URDF {path}: link '{n}' to prune does not exist; links: {sorted(names)}")
        doomed.add(n)
        stack += children.get(n, [])
    for el in list(root):
        if el.tag == "link" and el.get("name") in doomed:
            root.remove(el)
        elif el.tag == "joint" and el.find("child").get("link") in doomed:
            root.remove(el)
        elif el.tag in ("transmission", "gazebo"):
            root.remove(el)


def compose_urdf(
    arm_urdf: str | os.PathLike,
    hand_urdf: str | os.PathLike,
    ee_link: str,
    ee_from_hand_root: np.ndarray,
    *,
    drop_links: tuple[str, ...] = (),
    name: str | None = None,
) -> tuple[Path, dict[str, str]]:
    """Write (or reuse) the composed URDF; returns (path, link_map hand name -> composed name).

    Joint names are renamed like links on a clash (``link_map`` holds both kinds of names).
    """
    arm_urdf, hand_urdf = Path(arm_urdf).resolve(), Path(hand_urdf).resolve()
    for p in (arm_urdf, hand_urdf):
        if not p.is_file():
            raise EmbodimentError(f"URDF file {p} does not exist; provide it or fix HANDEDIT_ASSET_DIRS.")
    T = np.asarray(ee_from_hand_root, float).reshape(4, 4)
    arm, hand = parse_urdf_xml(arm_urdf).getroot(), parse_urdf_xml(hand_urdf).getroot()
    _prune(arm, tuple(drop_links), arm_urdf)
    arm_links = {l.get("name") for l in arm.findall("link")}
    if ee_link not in arm_links:
        raise EmbodimentError(f"arm URDF {arm_urdf} has no link '{ee_link}' to mount the hand on; links: {sorted(arm_links)}")
    arm_joints = {j.get("name") for j in arm.findall("joint")}
    arm_mats = {m.get("name") for m in arm.findall("material")}
    hand_links = [l.get("name") for l in hand.findall("link")]
    child_links = {j.find("child").get("link") for j in hand.findall("joint")}
    roots = [l for l in hand_links if l not in child_links]
    if len(roots) != 1:
        raise BrokenUrdf(f"URDF {hand_urdf} must have exactly one root link, found {roots}.")
    link_map = {n: (CLASH_PREFIX + n if n in arm_links else n) for n in hand_links}
    joint_map = {j.get("name"): (CLASH_PREFIX + j.get("name") if j.get("name") in arm_joints | {MOUNT_JOINT} else j.get("name"))
                 for j in hand.findall("joint")}
    mat_map = {m.get("name"): (CLASH_PREFIX + m.get("name") if m.get("name") in arm_mats else m.get("name"))
               for m in hand.findall("material")}

    absolutize_meshes(arm, arm_urdf)
    absolutize_meshes(hand, hand_urdf)
    for l in hand.iter("link"):
        l.set("name", link_map[l.get("name")])
    for j in hand.findall("joint"):
        j.set("name", joint_map[j.get("name")])
        for tag in ("parent", "child"):
            e = j.find(tag)
            e.set("link", link_map[e.get("link")])
        m = j.find("mimic")
        if m is not None and m.get("joint") in joint_map:
            m.set("joint", joint_map[m.get("joint")])
    for m in hand.iter("material"):
        if m.get("name") in mat_map:
            m.set("name", mat_map[m.get("name")])

    xyz, rpy = matrix_to_xyz_rpy(T)
    mount = etree.SubElement(arm, "joint", name=MOUNT_JOINT, type="fixed")
    etree.SubElement(mount, "origin", xyz=" ".join(repr(float(v)) for v in xyz), rpy=" ".join(repr(float(v)) for v in rpy))
    etree.SubElement(mount, "parent", link=ee_link)
    etree.SubElement(mount, "child", link=link_map[roots[0]])
    for el in hand:
        if el.tag in ("link", "joint", "material"):
            arm.append(el)
    arm.set("name", name or f"{arm.get('name', 'arm')}__{hand.get('name', 'hand')}")

    text = etree.tostring(arm, pretty_print=True, xml_declaration=True, encoding="utf-8")
    key = hashlib.sha256(text).hexdigest()[:16]
    out = _cache_dir() / f"{arm.get('name')}-{key}.urdf"
    if not out.is_file():
        atomic_write(out, text)  # concurrent workers write identical bytes
    return out, {**link_map, **joint_map}


def nominal_reach(urdf_path: str | os.PathLike, ee_link: str, n: int = 2048, seed: int = 0) -> float:
    """L_r: max distance shoulder -> ``ee_link`` over ``n`` seeded in-limit samples (metres).

    The shoulder is the origin of the first actuated joint on the root->ee chain.
    """
    from handedit.embodiments.kinematics import get_kinematics

    kin = get_kinematics(Path(urdf_path).resolve())
    chain = kin.chain(ee_link)
    movable = [j for j in chain if j.q_index >= 0]
    if not movable:
        raise EmbodimentError(f"URDF {urdf_path}: no actuated joint between the root and '{ee_link}'")
    shoulder_link = movable[0].child
    f = kin.fk_function(ee_link).map(n)
    g = kin.fk_function(shoulder_link).map(n)
    Q = kin.random_q(np.random.default_rng(seed), n).T
    ee = np.asarray(f(Q))  # (4, 4n)
    sh = np.asarray(g(Q))
    pe = ee[:3, 3::4]
    ps = sh[:3, 3::4]
    return float(np.max(np.linalg.norm(pe - ps, axis=0)))


@dataclass(frozen=True)
class ComposedEmbodiment:
    """A hand-arm embodiment as one kinematic tree (see module doc)."""

    embodiment_id: str
    urdf_path: Path
    arm_urdf: Path
    hand_urdf: Path
    base_link: str
    ee_link: str
    hand_root: str
    ee_from_hand_root: np.ndarray
    arm_joint_names: tuple[str, ...]
    hand_joint_names: tuple[str, ...]
    link_map: dict[str, str]
    keypoints: tuple  # tuple[KeypointLink, ...] in composed link names
    wrist_from_root: np.ndarray
    locked_joints: tuple[tuple[str, float], ...]
    nominal_reach_m: float

    @property
    def arm_slice(self) -> slice:
        return slice(0, len(self.arm_joint_names))

    @property
    def hand_slice(self) -> slice:
        n = len(self.arm_joint_names)
        return slice(n, n + len(self.hand_joint_names))

    def kinematics(self):
        from handedit.embodiments.kinematics import get_kinematics

        return get_kinematics(self.urdf_path)


def mount_transform(arm_asset, hand_asset, tool_from_wrist: np.ndarray) -> np.ndarray:
    """ee_from_hand_root for one (arm asset, hand asset) pair (see module doc)."""
    for hand_path, T in arm_asset.mounts:
        if hand_path == hand_asset.path:
            return np.asarray(T, float).reshape(4, 4)
    ee_from_wrist = arm_asset.ee_from_tool_matrix @ np.asarray(tool_from_wrist, float)
    T = ee_from_wrist @ hand_asset.wrist_from_root_matrix
    if hand_asset.mount_at_root:  # the URDF carries its own wrist module: its root meets the flange
        T[:3, 3] = ee_from_wrist[:3, 3]
    return T


def compose_embodiment(embodiment_id: str) -> ComposedEmbodiment:
    """Resolve both components of a hand-arm embodiment and compose them (cached per process
    and asset state; raises ``AssetsMissing`` naming what to provide)."""
    from handedit.embodiments.roster import asset_dirs, get_embodiment, resolve_arm, resolve_asset

    emb = get_embodiment(embodiment_id)
    if emb.arm is None:
        raise EmbodimentError(f"embodiment '{embodiment_id}' is hand-only; nothing to compose")
    hand = resolve_asset(emb)
    arm = resolve_arm(emb)
    stamp = tuple((str(p), p.stat().st_mtime_ns) for p in (hand.path, arm.path))
    return _compose_cached(embodiment_id, stamp, tuple(str(d) for d in asset_dirs()))


@functools.lru_cache(maxsize=64)
@metered
def _compose_cached(embodiment_id: str, stamp: tuple, _dirs: tuple) -> ComposedEmbodiment:
    from handedit.embodiments.kinematics import get_kinematics
    from handedit.embodiments.roster import KeypointLink, get_embodiment, resolve_arm, resolve_asset
    from handedit.embodiments.urdf import load_urdf

    emb = get_embodiment(embodiment_id)
    hand, arm = resolve_asset(emb), resolve_arm(emb)
    T = mount_transform(arm.asset, hand.asset, emb.arm.tool_from_wrist_matrix)
    path, names = compose_urdf(arm.path, hand.path, arm.asset.ee_link, T, drop_links=arm.asset.drop_links,
                               name=f"handedit_{embodiment_id}")
    arm_u = load_urdf(arm.path, load_meshes=False)
    hand_u = load_urdf(hand.path, load_meshes=False)
    arm_joints = tuple(j for j in arm_u.actuated_joint_names if j in {x.get("name") for x in _joints_after_prune(arm)})
    kin = get_kinematics(path)
    hand_joints = tuple(names[j] for j in hand_u.actuated_joint_names)
    if list(kin.joint_names) != [*arm_joints, *hand_joints]:
        raise BrokenUrdf(f"composed URDF {path}: unexpected joint order {kin.joint_names}")
    kps = tuple(KeypointLink(k.mano, names[k.link], k.kind, k.offset) for k in hand.asset.keypoints)
    reach = emb.arm.nominal_reach_m or nominal_reach(arm_reach_urdf(arm), arm.asset.ee_link)
    return ComposedEmbodiment(
        embodiment_id=embodiment_id,
        urdf_path=path,
        arm_urdf=arm.path,
        hand_urdf=hand.path,
        base_link=kin.base_link,
        ee_link=arm.asset.ee_link,
        hand_root=names[hand_u.base_link],
        ee_from_hand_root=T,
        arm_joint_names=arm_joints,
        hand_joint_names=hand_joints,
        link_map=names,
        keypoints=kps,
        wrist_from_root=hand.asset.wrist_from_root_matrix,
        locked_joints=tuple((names[n], v) for n, v in hand.asset.locked_joints),
        nominal_reach_m=reach,
    )


def _joints_after_prune(arm) -> list:
    root = parse_urdf_xml(arm.path).getroot()
    _prune(root, arm.asset.drop_links, arm.path)
    return root.findall("joint")


def arm_reach_urdf(arm) -> Path:
    """The arm alone (pruned) as a URDF, for its reach: an unpruned gripper would add length."""
    if not arm.asset.drop_links:
        return arm.path
    root = parse_urdf_xml(arm.path).getroot()
    _prune(root, arm.asset.drop_links, arm.path)
    absolutize_meshes(root, arm.path)
    text = etree.tostring(root, xml_declaration=True, encoding="utf-8")
    out = _cache_dir() / f"arm-{hashlib.sha256(text).hexdigest()[:16]}.urdf"
    if not out.is_file():
        atomic_write(out, text)
    return out
