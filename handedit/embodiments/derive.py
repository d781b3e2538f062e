"""Derived URDFs: what a vendor's URDF does not encode, added without editing the asset.

Some hands are modelled more loosely than the real product: DexHand021's distal joints
are mechanically coupled to the proximal ones but independent in its URDF, and the file
carries debug visuals (tip spheres, pad boxes). A ``UrdfAsset`` states the fixes as data
(``couplings``: (joint, source joint, multiplier, offset), written as URDF ``<mimic>``
tags, which yourdfpy, the renderer and the casadi kinematics all honour; ``hidden_visuals``:
a link-name regex whose ``<visual>`` elements are dropped; ``linkages``: closed loops the
tree leaves open, solved into polynomial mimics by ``handedit.embodiments.linkage``). The
derived file lives in
``$HANDEDIT_CACHE_DIR/derived`` (mesh paths made absolute), named by a digest of its
inputs, written atomically, so concurrent workers agree on it.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

from lxml import etree

from handedit.embodiments import linkage
from handedit.embodiments.errors import EmbodimentError
from handedit.files import atomic_write


def needs_derivation(asset) -> bool:
    return bool(getattr(asset, "couplings", ()) or getattr(asset, "hidden_visuals", "") or getattr(asset, "linkages", ()))


def derived_urdf(path: Path, asset) -> Path:
    """The asset's URDF with its couplings and hidden visuals applied (``path`` if none)."""
    if not needs_derivation(asset):
        return path
    from handedit.cache import cache_root
    from handedit.embodiments.urdf import absolutize_meshes, parse_urdf_xml

    st = path.stat()
    key = hashlib.blake2b(repr((str(path), st.st_size, st.st_mtime_ns, asset.couplings, asset.hidden_visuals,
                              asset.linkages, linkage.POLY_DEGREE)).encode(),
                          digest_size=8).hexdigest()
    out = cache_root() / "derived" / f"{path.stem}-{key}.urdf"
    if out.is_file():
        return out
    tree = parse_urdf_xml(path)
    root = tree.getroot()
    absolutize_meshes(root, path)
    joints = {j.get("name"): j for j in root.findall("joint")}
    for name, source, multiplier, offset in asset.couplings:
        if name not in joints or source not in joints:
            raise EmbodimentError(f"URDF {path}: coupling {name} <- {source}: no such joint; joints: {sorted(joints)}")
        j = joints[name]
        for old in j.findall("mimic"):
            j.remove(old)
        etree.SubElement(j, "mimic", joint=source, multiplier=repr(float(multiplier)), offset=repr(float(offset)))
    if asset.linkages:
        from handedit.embodiments.kinematics import Kinematics

        open_tree = Kinematics(path)  # every joint a column: the loops are solved on it
        for lk in asset.linkages:
            missing = [n for n in (lk.actuator, *lk.passive) if n not in joints]
            if missing:
                raise EmbodimentError(f"URDF {path}: linkage of {lk.actuator}: no joint(s) {missing}; joints: {sorted(joints)}")
            for name, (poly, multiplier, offset) in linkage.fit(open_tree, lk).items():
                j = joints[name]
                for old in j.findall("mimic"):
                    j.remove(old)
                etree.SubElement(j, "mimic", joint=lk.actuator, multiplier=repr(multiplier), offset=repr(offset),
                                 **{linkage.POLY_ATTR: poly.attr()})
    if asset.hidden_visuals:
        pattern = re.compile(asset.hidden_visuals)
        for link in root.findall("link"):
            if pattern.fullmatch(link.get("name", "")):
                for v in link.findall("visual"):
                    link.remove(v)
    return atomic_write(out, etree.tostring(tree, pretty_print=True, xml_declaration=True, encoding="utf-8"))
