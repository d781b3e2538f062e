"""A MANO-format model file whose hand is a hand: for adapter fixtures (not MANO's values).

MANO's licence forbids shipping the model, so the adapters' tests write their own file in
its format: 16 joints at a straight-fingered adult hand's positions (hand frame: fingers
+x, thumb +y for the right hand, palm facing -z), the joint regressor one-hot on vertices
placed at the joints, rigid skinning (every vertex follows one joint), no pose blend
shapes, and the fingertip vertices at the tips. Its forward kinematics is then a plain
kinematic chain, which the tests compute independently (``chain_fk``).
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from handedit.hands.mano import N_VERTS, TIPS_MANOPTH, TIPS_SMPLX

PARENTS = np.array([-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14])
# MANO-16 order: wrist, index 1-3, middle 1-3, pinky 1-3, ring 1-3, thumb 1-3; and the tips
_BASES = {"index": (0.090, 0.026), "middle": (0.092, 0.004), "ring": (0.086, -0.016), "pinky": (0.078, -0.034)}
_LENGTHS = {"index": (0.040, 0.024, 0.022), "middle": (0.045, 0.027, 0.023), "ring": (0.042, 0.026, 0.023),
            "pinky": (0.033, 0.019, 0.021)}
_ORDER = ("index", "middle", "pinky", "ring")  # MANO's finger order in joints 1..12
WRIST_OFFSET = np.array([0.012, -0.004, 0.003])
TIP_OF = {"thumb": 15, "index": 3, "middle": 6, "ring": 12, "pinky": 9}  # distal joint each tip rides on


def rest_joints(side: str = "right") -> tuple[np.ndarray, np.ndarray]:
    """(16,3) joints and (5,3) tips (thumb, index, middle, ring, pinky) at rest, hand frame."""
    J = np.zeros((16, 3))
    tips = {}
    for k, name in enumerate(_ORDER):
        x, y = _BASES[name]
        p = np.array([x, y, 0.0])
        for i, L in enumerate((0.0, *_LENGTHS[name][:2])):
            p = p + [L, 0, 0]
            J[1 + 3 * k + i] = p
        tips[name] = p + [_LENGTHS[name][2], 0, 0]
    thumb = [np.array([0.030, 0.030, -0.012]), np.array([0.052, 0.050, -0.012]), np.array([0.072, 0.064, -0.012])]
    J[13:16] = thumb
    tips["thumb"] = thumb[2] + [0.020, 0.012, 0.0]
    T = np.array([tips[n] for n in ("thumb", "index", "middle", "ring", "pinky")])
    J, T = J + WRIST_OFFSET, T + WRIST_OFFSET  # the wrist off the origin, as MANO's is: centring conventions show
    if side == "left":
        J, T = J * [1, -1, 1], T * [1, -1, 1]
    return J, T


def write_hand_model(path: Path, side: str, seed: int = 0, components: np.ndarray | None = None) -> Path:
    """The model file; ``components``: its PCA basis (45,45) (default the identity)."""
    rng = np.random.default_rng(seed)
    J, tips = rest_joints(side)
    v = np.zeros((N_VERTS, 3))
    owner = rng.integers(0, 16, N_VERTS)
    v[:] = J[owner] + rng.normal(0, 0.004, (N_VERTS, 3))
    v[:16], owner[:16] = J, np.arange(16)
    for tip_ids in (TIPS_SMPLX, TIPS_MANOPTH):
        for (name, _), vid, t in zip(TIP_OF.items(), tip_ids, tips):
            v[vid], owner[vid] = t, TIP_OF[name]
    w = np.zeros((N_VERTS, 16))
    w[np.arange(N_VERTS), owner] = 1.0
    Jr = np.zeros((16, N_VERTS))
    Jr[np.arange(16), np.arange(16)] = 1.0
    shapedirs = np.zeros((N_VERTS, 3, 10))
    shapedirs[:, :, 0] = v * 0.05  # beta 0 scales the hand by 5 % per unit
    d = {"v_template": v, "shapedirs": shapedirs, "posedirs": np.zeros((N_VERTS, 3, 135)), "J_regressor": Jr,
         "weights": w, "kintree_table": np.stack([np.where(PARENTS < 0, 4294967295, PARENTS), np.arange(16)]),
         "f": rng.integers(0, N_VERTS, (1538, 3)), "hands_components": np.eye(45) if components is None else components,
         "hands_mean": np.tile([0.0, 0.0, 0.15], 15)}  # a slight curl: flat_hand_mean=False shows
    with open(path, "wb") as f:
        pickle.dump(d, f, protocol=2)
    return path


def chain_fk(side: str, betas: np.ndarray, global_orient: np.ndarray, hand_pose: np.ndarray, transl: np.ndarray,
             add_mean: bool) -> np.ndarray:
    """(T,21,3) MANO-21 joints of the fixture model, by a plain kinematic chain (no LBS)."""
    from scipy.spatial.transform import Rotation

    J0, tips0 = rest_joints(side)
    out = []
    for b, go, hp, t in zip(betas, global_orient, hand_pose, transl):
        s = 1.0 + 0.05 * b[0]
        J, tips = J0 * s, tips0 * s
        pose = np.concatenate([go, hp + (np.tile([0.0, 0.0, 0.15], 15) if add_mean else 0.0)]).reshape(16, 3)
        R = Rotation.from_rotvec(pose).as_matrix()
        Rg, pos = [None] * 16, np.zeros((16, 3))
        for i in range(16):
            p = PARENTS[i]
            Rg[i] = R[i] if p < 0 else Rg[p] @ R[i]
            pos[i] = J[i] if p < 0 else pos[p] + Rg[p] @ (J[i] - J[p])
        tip = np.array([pos[j] + Rg[j] @ (tp - J[j]) for j, tp in zip(TIP_OF.values(), tips)])
        j21 = np.concatenate([pos, tip])[[0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7, 8, 9, 20]]
        out.append(j21 + t)
    return np.array(out)
