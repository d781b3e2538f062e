"""HOI4D (Liu et al., CVPR 2022): egocentric RGB-D of category-level hand-object interaction.

Layout (the release and HOI4D-Instructions' loaders):

* ``<root>/<ZY...>/<H>/<C>/<N>/<S>/<s>/<T>/align_rgb/%05d.jpg``: the frames, decoded from
  ``image.mp4`` at 15 fps by HOI4D's ``utils/decode.py`` (1920x1080); without them the
  adapter decodes ``image.mp4`` itself when it runs at 15 fps (else: run decode.py);
* ``.../2Dseg/mask/%05d.png``: 2-D masks, colour-coded with the VOC palette
  (``utils/color_map.py``); label 2 is the right hand, the left hand's label is its
  category's (``definitions/motion segmentation/label.csv``: "Left Hand"), every other
  non-zero label is the object;
* ``.../objpose/<k>.json``: the object's category-level pose in the camera frame (``center``
  metres, ``rotation`` Euler XYZ radians, ``dimensions``), ``dataList`` or ``objects``;
* ``<handpose_root>/refinehandpose_{right,left}/<sequence>/<k>.pickle``: MANO per frame in
  the **camera** frame: ``poseCoeff`` (3 global + 45 axis-angle), ``beta`` (10), ``trans``
  (metres); manopth's layer, ``flat_hand_mean=True``, no PCA: joints = MANO joints + trans;
  mostly the right hand only;
* ``<camera_root>/<ZY...>/intrin.npy``: the 3x3 intrinsics of that camera;
* ``<cad_root>/rigid/<Category>/<N>.obj``: the object's CAD model (metres).

Defaults for the three roots are siblings of ``root`` (``handpose``, ``camera_params``,
``HOI4D_CAD_Model_for_release``). A frame without a hand pickle has that side invalid.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from handedit.hands.mano import TIPS_MANOPTH, ManoConvention
from handedit.keypoints import SIDES
from handedit.sources.base import SourceError
from handedit.sources.mano_model import mano_digest, mano_model
from handedit.sources.sequence import ManoSpecBase, ManoTreeBase, Sequence, SequenceSource, load_mesh, load_pickle
from handedit.vision.object_depth import rasterize_depth

CONVENTION = ManoConvention(pca=False, flat_hand_mean=True, tips=TIPS_MANOPTH)  # manopth, camera frame
FPS = 15.0
RIGHT_HAND_LABEL = 2
CATEGORIES = ("", "ToyCar", "Mug", "Laptop", "StorageFurniture", "Bottle", "Safe", "Bowl", "Bucket", "Scissors", "",
              "Pliers", "Kettle", "Knife", "TrashCan", "", "", "Lamp", "Stapler", "", "Chair")
LEFT_HAND_LABEL = {"C8": 6}  # categories whose label table has a "Left Hand" (Bucket)


def voc_palette(n: int = 16) -> np.ndarray:
    """(n,3) RGB of label i in HOI4D's masks (the PASCAL VOC bit-interleaved palette)."""
    cmap = np.zeros((n, 3), np.uint8)
    for i in range(n):
        r = g = b = 0
        c = i
        for j in range(8):
            r |= ((c >> 0) & 1) << (7 - j)
            g |= ((c >> 1) & 1) << (7 - j)
            b |= ((c >> 2) & 1) << (7 - j)
            c >>= 3
        cmap[i] = (r, g, b)
    return cmap


def decode_mask(rgb: np.ndarray) -> np.ndarray:
    """(H,W) label per pixel of a palette-coded mask (0 where no palette colour matches)."""
    pal = voc_palette().astype(np.int32)
    code = (rgb[..., 0].astype(np.int32) << 16) | (rgb[..., 1].astype(np.int32) << 8) | rgb[..., 2]
    keys = (pal[:, 0] << 16) | (pal[:, 1] << 8) | pal[:, 2]
    labels = np.zeros(rgb.shape[:2], np.uint8)
    for i, k in enumerate(keys[1:], start=1):
        labels[code == k] = i
    return labels


_ROOTS = ("handpose_root", "camera_root", "cad_root")


class Hoi4dSpec(ManoSpecBase):
    kind: Literal["hoi4d"] = "hoi4d"
    root: Path
    sequence: str  # e.g. ZY20210800004/H4/C8/N14/S71/s03/T2
    handpose_root: Path | None = None
    camera_root: Path | None = None
    cad_root: Path | None = None

    @property
    def id(self) -> str:
        return self.clip_id or "hoi4d-" + self.sequence.replace("/", "-")

    def roots(self) -> tuple[Path, Path, Path]:
        up = Path(self.root).parent
        return (Path(self.handpose_root or up / "handpose"), Path(self.camera_root or up / "camera_params"),
                Path(self.cad_root or up / "HOI4D_CAD_Model_for_release"))

    def open(self) -> SequenceSource:
        return SequenceSource(load_sequence(self), self.frames, self.resize, "HOI4D")


class Hoi4dTree(ManoTreeBase):
    """Every sequence under ``root`` (a folder with ``align_rgb/``), sorted; one group per camera
    (``tasks``: ZY... folders)."""

    kind: Literal["hoi4d"] = "hoi4d"
    handpose_root: Path | None = None
    camera_root: Path | None = None
    cad_root: Path | None = None

    def _spec(self, **kw) -> Hoi4dSpec:
        return Hoi4dSpec(root=self.root, **{k: getattr(self, k) for k in _ROOTS}, **kw)

    def _groups(self):
        root = Path(self.root)
        if not root.is_dir():
            raise SourceError(f"HOI4D root {root} is not a directory; pass --root the folder holding ZY2021080000*/.")
        for cam in self.tasks or sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("ZY")):
            seqs = sorted(str(p.parent.relative_to(root)) for p in (root / cam).glob("*/*/*/*/*/*/align_rgb"))
            yield cam, [{"sequence": s} for s in seqs]


def _pose(path: Path) -> np.ndarray:
    """camera_from_object from one objpose json (first object)."""
    from scipy.spatial.transform import Rotation

    try:
        d = json.loads(path.read_text())
        a = (d.get("dataList") or d.get("objects"))[0]
        c, r = a["center"], a["rotation"]
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("XYZ", [r["x"], r["y"], r["z"]]).as_matrix()
        T[:3, 3] = [c["x"], c["y"], c["z"]]
        return T
    except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
        raise SourceError(f"HOI4D object pose {path} could not be read ({type(exc).__name__}: {exc}); "
                          f"download objpose/ of the sequence.") from None


def load_sequence(spec: Hoi4dSpec) -> Sequence:
    seq = Path(spec.root) / spec.sequence
    handpose, cameras, cad = spec.roots()
    images = sorted((seq / "align_rgb").glob("*.jpg"))
    video = None
    if images:
        T = int(images[-1].stem) + 1
        images = [seq / "align_rgb" / f"{k:05d}.jpg" for k in range(T)]
    else:  # not decoded yet: the video itself, when it runs at the annotations' 15 fps
        video, images = seq / "align_rgb" / "image.mp4", []
        if not video.is_file():
            raise SourceError(f"HOI4D {seq}/align_rgb has neither frames nor image.mp4; download the sequence.")
        from handedit.sources.decode import VideoReader

        probe = VideoReader(video, what="HOI4D video").probe
        if abs(probe.fps - FPS) > 0.5:
            raise SourceError(f"HOI4D video {video} runs at {probe.fps:g} fps, its annotations at {FPS:g}: decode it with "
                              f"HOI4D's utils/decode.py (ffmpeg fps=15, align_rgb/%05d.jpg) first.")
        T = probe.n_frames
    cam_id = spec.sequence.split("/")[0]
    K_p = cameras / cam_id / "intrin.npy"
    K = np.asarray(load_pickle(K_p, "HOI4D intrinsics", "download camera_params/ of the release"), float)
    if K.shape != (3, 3):
        raise SourceError(f"HOI4D intrinsics {K_p} has shape {K.shape}, expected (3, 3).")
    kp = np.zeros((T, 2, 21, 3))
    valid = np.zeros((T, 2), bool)
    for s_i, side in enumerate(SIDES):
        folder = handpose / f"refinehandpose_{side}" / spec.sequence
        files = {int(p.stem): p for p in folder.glob("*.pickle")} if folder.is_dir() else {}
        if not files:
            continue
        model = mano_model(spec.mano_dir, side)
        ks = sorted(k for k in files if k < T)
        d = [load_pickle(files[k], "HOI4D hand pose", "re-download handpose/") for k in ks]
        try:
            pose = np.array([np.asarray(x["poseCoeff"], float).reshape(48) for x in d])
            beta = np.array([np.asarray(x["beta"], float).reshape(10) for x in d])
            trans = np.array([np.asarray(x["trans"], float).reshape(3) for x in d])
        except (KeyError, ValueError, TypeError) as exc:
            raise SourceError(f"HOI4D hand poses in {folder}: {type(exc).__name__} {exc}; expected poseCoeff (48), "
                              f"beta (10), trans (3) per pickle.") from None
        kp[ks, s_i] = model.forward(beta, pose[:, :3], pose[:, 3:], trans, CONVENTION).joints
        valid[ks, s_i] = True
    if not valid.any():
        raise SourceError(f"HOI4D {spec.sequence}: no hand pose found under {handpose}/refinehandpose_{{right,left}}/"
                          f"{spec.sequence}; download the hand poses (or pass handpose_root).")
    hands = tuple(s for i, s in enumerate(SIDES) if valid[:, i].any())
    keep = [SIDES.index(h) for h in hands]
    parts = spec.sequence.split("/")
    category, instance = parts[2], parts[3]
    poses = np.stack([_pose(seq / "objpose" / f"{k}.json") for k in range(T)])
    name = CATEGORIES[int(category[1:])] if category[1:].isdigit() and int(category[1:]) < len(CATEGORIES) else category
    cands = [cad / "rigid" / name / f"{instance[1:]}.obj", cad / "rigid" / name / f"{int(instance[1:]):03d}.obj"] \
        if instance[1:].isdigit() else []
    mesh_p = next((p for p in cands if p.is_file()), None)
    mesh = load_mesh(mesh_p, "HOI4D CAD model") if mesh_p else None
    hand_labels = {RIGHT_HAND_LABEL, LEFT_HAND_LABEL.get(category, -1)}

    def mask(k: int, intr, size) -> np.ndarray:
        m = cv2.imread(str(seq / "2Dseg" / "mask" / f"{k:05d}.png"), cv2.IMREAD_COLOR)
        if m is None:  # no shipped mask: the CAD model's silhouette, where there is one
            return rasterize_depth(*mesh, poses[k], intr) > 0 if mesh else np.zeros(size[::-1], bool)
        labels = decode_mask(cv2.cvtColor(m, cv2.COLOR_BGR2RGB))
        obj = (labels > 0) & ~np.isin(labels, list(hand_labels))
        return cv2.resize(obj.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)

    def depth(k: int, intr, size) -> np.ndarray:  # the CAD model's, for occlusion
        return rasterize_depth(*mesh, poses[k], intr)

    return Sequence(
        clip_id=spec.id, keypoints=kp[:, keep], valid=valid[:, keep], hands=hands, images=images, K=K, fps=FPS,
        object_pose=poses, object_mesh=mesh, object_mask=mask, object_depth=depth if mesh else None, files=[K_p, *([mesh_p] if mesh_p else []), *([video] if video else [])],
        video=video,
        meta={"dataset": "hoi4d", "sequence": spec.sequence, "category": name, "instance": instance,
              "mano": mano_digest(spec.mano_dir), "mano_convention": "manopth, axis-angle, flat_hand_mean=True, camera frame",
              "object_mask": "shipped 2Dseg masks (labels other than the hands)", "hands_annotated": list(hands)})
