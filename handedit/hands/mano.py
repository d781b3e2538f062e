"""MANO in numpy: the hand model four of the source datasets store their hands in.

Forward kinematics by linear blend skinning, as in the MANO paper and its reference
layers (smplx's ``MANO``, manopth's ``ManoLayer``): shape blend shapes, the joint
regressor, pose blend shapes from the 15 finger joints' rotations, the kinematic tree,
skinning; then five fingertip vertices appended and the 21 joints put in
``handedit.keypoints`` order. No torch: an adapter turns a clip's parameters into
camera-frame keypoints on a worker with numpy alone.

The model file is the user's own (MANO's licence forbids redistribution): ``MANO_RIGHT.pkl``
/ ``MANO_LEFT.pkl`` from https://mano.is.tue.mpg.de (register, download "Models & Code"),
in the folder given by ``--mano-dir`` or ``$HANDEDIT_MANO_DIR``. Files pickled with chumpy
arrays (the official release) load without chumpy.

What differs between datasets is written once, next to each adapter, as a ``ManoConvention``:
axis-angle or PCA hand pose, ``flat_hand_mean``, which fingertip vertices, and whether the
output is re-centred on a joint before the translation is added (manopth's ``center_idx``).
"""

from __future__ import annotations

import os
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np

N_VERTS = 778
# fingertip vertices (thumb, index, middle, ring, pinky): smplx's VERTEX_IDS["mano"], and manopth's
TIPS_SMPLX = (744, 320, 443, 554, 671)
TIPS_MANOPTH = (745, 317, 444, 556, 673)
# MANO's 16 joints + the 5 tips (16..20: thumb, index, middle, ring, pinky) -> handedit.keypoints order
TO_MANO21 = (0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7, 8, 9, 20)
MANO_URL = "https://mano.is.tue.mpg.de"


class ManoError(ValueError):
    """The MANO model file is missing or not a MANO model; the message names the file and the fix."""


@dataclass(frozen=True)
class ManoConvention:
    """How a dataset's MANO parameters are meant (see the module doc)."""

    pca: bool = False  # hand_pose is PCA coefficients (first n components) instead of 45 axis-angle values
    flat_hand_mean: bool = True  # False: the model's mean hand pose is added to hand_pose
    tips: tuple[int, ...] = TIPS_SMPLX
    # MANO-21 joint moved to the origin before transl is added (manotorch's center_idx; manopth's
    # applies only when no translation is passed, so a translated manopth pose is never centred)
    center_joint: int | None = None


@dataclass
class ManoOutput:
    vertices: np.ndarray  # (T,778,3)
    joints: np.ndarray  # (T,21,3) handedit.keypoints order


class _Stub:
    """Stands in for a chumpy array (or any unknown class) while unpickling: keeps its state."""

    def __init__(self, *args, **kwargs):
        self.args = args

    def __setstate__(self, state):
        self.state = state


class _Unpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if module.startswith("chumpy"):
            return _Stub
        return super().find_class(module, name)


def _array(value, key: str, path: Path) -> np.ndarray:
    if isinstance(value, _Stub):
        state = getattr(value, "state", None)
        for cand in ((state or {}).get("x") if isinstance(state, dict) else None, *(value.args or ())):
            if cand is not None:
                return np.asarray(cand, np.float64)
        raise ManoError(f"{path}: '{key}' is a chumpy object whose values could not be read; convert the file "
                        f"to plain numpy arrays (e.g. load it with chumpy installed and pickle np.array(...) of each)")
    if hasattr(value, "toarray"):
        return np.asarray(value.toarray(), np.float64)
    return np.asarray(value)


@dataclass(frozen=True)
class ManoModel:
    side: str
    v_template: np.ndarray  # (778,3)
    shapedirs: np.ndarray  # (778,3,B)
    posedirs: np.ndarray  # (778,3,135)
    J_regressor: np.ndarray  # (16,778)
    weights: np.ndarray  # (778,16)
    parents: np.ndarray  # (16,) -1 for the root
    faces: np.ndarray  # (1538,3)
    hands_components: np.ndarray  # (45,45) PCA basis, rows
    hands_mean: np.ndarray  # (45,)

    @classmethod
    def load(cls, path: str | os.PathLike, side: str | None = None) -> "ManoModel":
        p = Path(path).expanduser()
        if not p.is_file():
            raise ManoError(f"MANO model file {p} not found. MANO cannot be redistributed: register at {MANO_URL}, "
                            f"download 'Models & Code', and put MANO_RIGHT.pkl and MANO_LEFT.pkl in the folder given by "
                            f"--mano-dir or $HANDEDIT_MANO_DIR.")
        try:
            with open(p, "rb") as f:
                d = _Unpickler(f, encoding="latin1").load()
        except Exception as exc:  # noqa: BLE001 - any unpickling failure is the same fix
            raise ManoError(f"{p} is not a readable MANO pickle ({type(exc).__name__}: {exc}); use the official "
                            f"MANO_RIGHT.pkl / MANO_LEFT.pkl from {MANO_URL}") from None
        need = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f",
                "hands_components", "hands_mean")
        missing = [k for k in need if k not in d] if isinstance(d, dict) else list(need)
        if missing:
            raise ManoError(f"{p} lacks {missing}: not a MANO model file (expected the official MANO_*.pkl from {MANO_URL})")
        a = {k: _array(d[k], k, p) for k in need}
        side = side or ("left" if "LEFT" in p.name.upper() else "right")
        shapes = {"v_template": (N_VERTS, 3), "posedirs": (N_VERTS, 3, 135), "J_regressor": (16, N_VERTS),
                  "weights": (N_VERTS, 16), "hands_components": (45, 45), "hands_mean": (45,)}
        bad = [f"{k} {a[k].shape} (expected {s})" for k, s in shapes.items() if a[k].shape != s]
        if a["shapedirs"].ndim != 3 or a["shapedirs"].shape[:2] != (N_VERTS, 3):
            bad.append(f"shapedirs {a['shapedirs'].shape} (expected (778, 3, B))")
        if bad:
            raise ManoError(f"{p}: arrays of the wrong shape: {'; '.join(bad)}")
        parents = a["kintree_table"][0].astype(np.int64)
        parents[0] = -1
        return cls(side, a["v_template"].astype(np.float64), a["shapedirs"].astype(np.float64),
                   a["posedirs"].astype(np.float64), a["J_regressor"].astype(np.float64), a["weights"].astype(np.float64),
                   parents, a["f"].astype(np.int64), a["hands_components"].astype(np.float64),
                   a["hands_mean"].astype(np.float64))

    @classmethod
    def find(cls, mano_dir: str | os.PathLike | None, side: str) -> "ManoModel":
        """``MANO_RIGHT.pkl`` / ``MANO_LEFT.pkl`` in ``mano_dir`` (default ``$HANDEDIT_MANO_DIR``)."""
        d = mano_dir or os.environ.get("HANDEDIT_MANO_DIR")
        if not d:
            raise ManoError(f"this source stores hands as MANO parameters: pass --mano-dir DIR (or set HANDEDIT_MANO_DIR) "
                            f"to the folder holding MANO_RIGHT.pkl and MANO_LEFT.pkl (register at {MANO_URL})")
        return _load_cached(str(Path(d).expanduser() / f"MANO_{side.upper()}.pkl"), side)

    def full_pose(self, global_orient: np.ndarray, hand_pose: np.ndarray, conv: ManoConvention) -> np.ndarray:
        """(T,16,3) axis-angle of every joint from a dataset's parameters."""
        hp = np.asarray(hand_pose, np.float64)
        if conv.pca:
            hp = hp @ self.hands_components[: hp.shape[-1]]
        if not conv.flat_hand_mean:
            hp = hp + self.hands_mean
        return np.concatenate([np.asarray(global_orient, np.float64)[:, None], hp.reshape(-1, 15, 3)], axis=1)

    def forward(self, betas: np.ndarray, global_orient: np.ndarray, hand_pose: np.ndarray, transl: np.ndarray | None = None,
                conv: ManoConvention = ManoConvention()) -> ManoOutput:
        """Vertices and MANO-21 joints for T frames (betas (B,) or (T,B); global_orient (T,3)
        axis-angle; hand_pose (T,45) axis-angle or (T,n) PCA; transl (T,3) metres)."""
        pose = self.full_pose(global_orient, hand_pose, conv)
        T = pose.shape[0]
        betas = np.broadcast_to(np.asarray(betas, np.float64), (T, np.asarray(betas).shape[-1]))
        B = min(betas.shape[1], self.shapedirs.shape[2])
        v_shaped = self.v_template + np.einsum("vcb,tb->tvc", self.shapedirs[..., :B], betas[:, :B])
        J = np.einsum("jv,tvc->tjc", self.J_regressor, v_shaped)
        R = rodrigues(pose.reshape(-1, 3)).reshape(T, 16, 3, 3)
        feat = (R[:, 1:] - np.eye(3)).reshape(T, 135)
        v_posed = v_shaped + np.einsum("vcp,tp->tvc", self.posedirs, feat)
        G = np.zeros((T, 16, 4, 4))
        G[..., 3, 3] = 1.0
        for i in range(16):
            rel = J[:, i] - (J[:, self.parents[i]] if i else 0.0)
            local = np.zeros((T, 4, 4))
            local[:, :3, :3], local[:, :3, 3], local[:, 3, 3] = R[:, i], rel, 1.0
            G[:, i] = local if i == 0 else G[:, self.parents[i]] @ local
        joints16 = G[:, :, :3, 3].copy()
        A = G.copy()
        A[:, :, :3, 3] -= np.einsum("tjab,tjb->tja", G[:, :, :3, :3], J)
        Tv = np.einsum("vj,tjab->tvab", self.weights, A)
        verts = np.einsum("tvab,tvb->tva", Tv[:, :, :3, :3], v_posed) + Tv[:, :, :3, 3]
        joints = np.concatenate([joints16, verts[:, list(conv.tips)]], axis=1)[:, list(TO_MANO21)]
        if conv.center_joint is not None:
            c = joints[:, conv.center_joint : conv.center_joint + 1].copy()
            joints, verts = joints - c, verts - c
        if transl is not None:
            t = np.asarray(transl, np.float64)[:, None]
            joints, verts = joints + t, verts + t
        return ManoOutput(verts, joints)


_CACHE: dict[str, ManoModel] = {}


def _load_cached(path: str, side: str) -> ManoModel:
    """One model per file and process (a worker opens each side once)."""
    if path not in _CACHE:
        _CACHE[path] = ManoModel.load(path, side)
    return _CACHE[path]


def rodrigues(aa: np.ndarray) -> np.ndarray:
    """(N,3) axis-angle -> (N,3,3) rotation matrices."""
    aa = np.asarray(aa, np.float64)
    theta = np.linalg.norm(aa, axis=1, keepdims=True)
    k = aa / np.maximum(theta, 1e-12)
    K = np.zeros((len(aa), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(theta)[:, :, None], np.cos(theta)[:, :, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def quat_wxyz_to_axis_angle(q: np.ndarray) -> np.ndarray:
    """(...,4) unit quaternions, scalar first (w, x, y, z) -> (...,3) axis-angle."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0, -q, q)  # the same rotation, angle in [0, pi]
    w, v = q[..., :1], q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2 * np.arctan2(s, w)
    return np.where(s > 1e-12, v / np.maximum(s, 1e-12) * angle, 2 * v)


def write_model_file(path: str | os.PathLike, rng: np.random.Generator, n_betas: int = 10) -> Path:
    """A file in MANO's format with made-up values (tests, and smoke runs without the real model):
    the official keys, shapes and a valid tree, J_regressor rows and skinning weights that sum to 1."""
    import scipy.sparse

    v = rng.normal(0, 0.04, (N_VERTS, 3))
    parents = np.array([-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14])
    Jr = rng.uniform(0, 1, (16, N_VERTS)) * (rng.uniform(0, 1, (16, N_VERTS)) > 0.97)
    Jr /= Jr.sum(1, keepdims=True)
    w = rng.uniform(0, 1, (N_VERTS, 16)) ** 4
    w /= w.sum(1, keepdims=True)
    comps = np.linalg.qr(rng.normal(size=(45, 45)))[0].T
    d = {"v_template": v, "shapedirs": rng.normal(0, 0.003, (N_VERTS, 3, n_betas)),
         "posedirs": rng.normal(0, 0.002, (N_VERTS, 3, 135)), "J_regressor": scipy.sparse.csc_matrix(Jr),
         "weights": w, "kintree_table": np.stack([np.where(parents < 0, 4294967295, parents), np.arange(16)]).astype(np.int64),
         "f": rng.integers(0, N_VERTS, (1538, 3)).astype(np.uint32), "hands_components": comps,
         "hands_mean": rng.normal(0, 0.2, 45), "hands_coeffs": rng.normal(size=(10, 45)), "bs_style": "lbs", "bs_type": "lrotmin"}
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with open(p, "wb") as f:
        pickle.dump(d, f, protocol=2)
    return p
