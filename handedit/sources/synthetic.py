"""Procedural egocentric clip: a right hand reaches, grasps and lifts an object on a table.

This is the demo default and the ground-truth oracle for every later stage, so the
geometry is metric (an ~18.5 cm MANO-like hand, a 40-60 cm head camera), and every
ground-truth array comes from the same camera and scene as the pixels: masks from a
segmentation render with depth testing, the clean background from the same scene with
the hand and forearm hidden (no cast shadows, so it is exact outside the hand).

Everything about a clip is a pure function of the spec (``make_plan``) and every frame a
pure function of (plan, t) (``frame_state``): any frame range rendered on any worker is
identical to the same frames of a full-clip render, which chunk-parallel ingest relies on.
"""

from __future__ import annotations

import hashlib
import os
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import cv2
import numpy as np
import pydantic
import trimesh
from scipy.spatial.transform import Rotation, Slerp

from handedit.camera import CV_TO_GL, Intrinsics, look_at
from handedit.lru import Lru
from handedit.sources import _hand_model as hm
from handedit.sources.base import ClipChunk, ClipInfo, SourceError
from handedit.vision.object_depth import object_depth

if TYPE_CHECKING:
    import pyrender

GENERATOR_VERSION = "synthetic-v1"
# cloth colours a sleeve is drawn from (sRGB): dark, bright, and two close to skin
SLEEVE_COLOURS = ((0.12, 0.13, 0.16), (0.22, 0.42, 0.25), (0.85, 0.45, 0.15), (0.30, 0.36, 0.55),
                  (0.80, 0.66, 0.52), (0.70, 0.52, 0.42))
GROUND_TRUTH: tuple[str, ...] = ("hand_mask", "handarm_mask", "background")

# Motion script, as fractions of the clip (u = t / (n_frames - 1)).
APPROACH_END = 0.40  # open hand reaches the pre-grasp pose
CONTACT_END = 0.48  # palm arrives on the object
CLOSE_START, CLOSE_END = 0.42, 0.60  # fingers close
LIFT_START = 0.60  # hand and object lift together until the end
STILL_AT = 0.55  # a still clip's moment of the script: the hand on the object, fingers closing

_SEG_HAND, _SEG_ARM, _SEG_OBJ = (255, 0, 0), (0, 255, 0), (0, 0, 255)


class SyntheticSpec(pydantic.BaseModel):
    """A synthetic clip; every pixel is a function of these fields (picklable, cheap)."""

    model_config = pydantic.ConfigDict(extra="forbid")

    kind: Literal["synthetic"] = "synthetic"
    clip_id: str = "synthetic-0000"
    seed: int = 0
    width: int = pydantic.Field(640, ge=16, strict=True)
    height: int = pydantic.Field(480, ge=16, strict=True)
    n_frames: int = pydantic.Field(48, ge=1, strict=True)
    fps: float = 30.0
    still: bool = pydantic.Field(False, description="the hand holds its grasp (the script's moment STILL_AT) for the whole "
                                 "clip while the head camera keeps swaying: restoration never sees behind it")
    sleeve: bool = pydantic.Field(False, description="a cloth sleeve over the forearm from a few cm past the wrist (colours "
                                  "in SLEEVE_COLOURS, some close to skin, with a woven texture), and the elbow tracked in 3-D as "
                                  "EgoDex tracks it: the hand-arm ground truth is the arm with its sleeve")

    @property
    def id(self) -> str:
        return self.clip_id

    def open(self) -> "SyntheticSource":
        return SyntheticSource(self)


def make_clip_specs(n_clips: int, seed: int = 0, **overrides) -> list[SyntheticSpec]:
    """``n_clips`` varied, deterministic clips ``synthetic-0000``...; overrides apply to all."""
    seeds = np.random.SeedSequence(seed).generate_state(max(n_clips, 1))
    return [
        SyntheticSpec(**{"clip_id": f"synthetic-{i:04d}", "seed": int(seeds[i]), **overrides})
        for i in range(n_clips)
    ]


# ----------------------------------------------------------------------------- small math


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


def _phase(u: float, a: float, b: float) -> float:
    return _smoothstep((u - a) / (b - a))


def _rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _rz(a: float) -> np.ndarray:
    return Rotation.from_euler("z", a).as_matrix()


# ----------------------------------------------------------------------------- object


@dataclass(frozen=True)
class ObjectModel:
    kind: Literal["box", "cylinder"]
    half: tuple[float, float, float]  # box half extents, or (radius, radius, half height)
    rgb: tuple[float, float, float]

    def mesh(self) -> trimesh.Trimesh:
        """Object-frame mesh, origin at the centre, z up (the oracle for object_mesh)."""
        if self.kind == "box":
            return trimesh.creation.box(extents=2 * np.array(self.half))
        return trimesh.creation.cylinder(radius=self.half[0], height=2 * self.half[2], sections=64)

    def sdf(self, p: np.ndarray) -> np.ndarray:
        """Exact signed distance (object frame) used to close the fingers on the surface."""
        if self.kind == "box":
            q = np.abs(p) - np.array(self.half)
            return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(axis=-1), 0)
        d = np.stack([np.linalg.norm(p[..., :2], axis=-1) - self.half[0], np.abs(p[..., 2]) - self.half[2]], -1)
        return np.linalg.norm(np.maximum(d, 0), axis=-1) + np.minimum(d.max(axis=-1), 0)


_SKIN_TONES = np.array([  # sRGB, light to dark
    (0.94, 0.78, 0.68), (0.87, 0.66, 0.53), (0.76, 0.55, 0.40), (0.58, 0.40, 0.28), (0.42, 0.28, 0.20),
])


def _skin_tone(rng: np.random.Generator) -> np.ndarray:
    x = rng.uniform(0, len(_SKIN_TONES) - 1)
    i = min(int(x), len(_SKIN_TONES) - 2)
    rgb = _SKIN_TONES[i] * (1 - (x - i)) + _SKIN_TONES[i + 1] * (x - i)
    return np.clip(rgb * rng.uniform(0.97, 1.03, 3), 0, 1)


_OBJECT_COLOURS = np.array([
    (0.80, 0.12, 0.10), (0.10, 0.35, 0.75), (0.12, 0.55, 0.25), (0.92, 0.75, 0.12),
    (0.92, 0.45, 0.08), (0.55, 0.20, 0.60), (0.85, 0.85, 0.82), (0.10, 0.60, 0.65),
])


def _sample_object(rng: np.random.Generator) -> ObjectModel:
    rgb = np.clip(_OBJECT_COLOURS[rng.integers(len(_OBJECT_COLOURS))] * rng.uniform(0.85, 1.1), 0, 1)
    if rng.random() < 0.5:
        half = (rng.uniform(0.022, 0.03), rng.uniform(0.028, 0.036), rng.uniform(0.06, 0.08))
        return ObjectModel("box", tuple(float(x) for x in half), tuple(float(x) for x in rgb))
    r = rng.uniform(0.026, 0.038)
    return ObjectModel("cylinder", (float(r), float(r), float(rng.uniform(0.06, 0.08))), tuple(float(x) for x in rgb))


# ----------------------------------------------------------------------------- plan


@dataclass(frozen=True)
class ClipPlan:
    """Everything random about a clip, drawn once from the seed (pure numpy, picklable)."""

    intr: Intrinsics
    geom: hm.HandGeom
    skin_rgb: np.ndarray
    obj: ObjectModel
    world_from_object0: np.ndarray
    world_from_hand_grasp: np.ndarray
    hand_start_rot: np.ndarray  # (3,3) world_from_hand rotation at u=0
    hand_start_pos: np.ndarray
    pregrasp_offset: np.ndarray  # world offset of the wrist at u=APPROACH_END
    open_pose: hm.HandPose
    grasp_pose: hm.HandPose
    lift: np.ndarray  # world translation of hand+object at u=1
    elbow: np.ndarray  # world point the forearm points at (out of view, near the body)
    eye: np.ndarray
    target: np.ndarray
    sway_amp: np.ndarray  # (3,)
    sway_freq: np.ndarray  # (3,)
    sway_phase: np.ndarray  # (3,)
    tremor: np.ndarray  # (3,3) amp, freq, phase of the approach tremor
    key_dir: np.ndarray  # key light direction (towards the scene)
    key_rgb: np.ndarray
    key_intensity: float
    lamp_pos: np.ndarray
    lamp_intensity: float
    ambient: float
    light_phase: float
    table_seed: int
    still: bool = False  # SyntheticSpec.still
    sleeve_rgb: np.ndarray | None = None  # (3,) sRGB cloth colour (SyntheticSpec.sleeve), else no sleeve
    sleeve_start: float = 0.0  # metres past the wrist where the sleeve begins


def _hand_world_rot(yaw: float, roll: float, pitch: float) -> np.ndarray:
    """Grasp orientation: fingers forward (+y), thumb up, palm facing -x, then small tilts."""
    base = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # columns x_h, y_h, z_h
    return _rz(yaw) @ base @ Rotation.from_euler("xz", [roll, pitch]).as_matrix()


def _open_pose(rng: np.random.Generator) -> hm.HandPose:
    d = np.deg2rad
    spreads = d(np.array([9.0, 0.0, -8.0, -17.0]) + rng.uniform(-2, 2, 4))
    fingers = [hm.finger_pose(s, tuple(d(np.array([4.0, 8.0, 5.0]) + rng.uniform(-3, 3, 3)))) for s in spreads]
    thumb = hm.thumb_pose(hm.THUMB_OPEN, tuple(d(np.array([0.0, 5.0, 5.0]))), azimuth=d(50.0))
    return hm.HandPose((thumb, *fingers))


@dataclass(frozen=True)
class _Grasp:
    score: float
    object_in_hand: np.ndarray  # (3,) object centre in the hand frame
    pose: hm.HandPose


def _close_hand(geom: hm.HandGeom, sdf: hm.SdfFn, rng_spread: np.ndarray) -> tuple[hm.HandPose, float]:
    """Close all digits on the object; score = summed fingertip distance + penetration."""
    d = np.deg2rad
    digits, score = [], 0.0
    # Thumb: oppose (lift out of the palm plane) at most until just before contact, then
    # flex; of a few opposition angles keep the one whose tip ends nearest the surface.
    flex0 = (0.0, d(5.0), d(5.0))
    betas = np.arange(hm.THUMB_OPEN, hm.THUMB_OPPOSED + 1e-9, d(2.0))
    beta = betas[0]
    for b in betas:
        if hm.digit_clearance(geom.digits[0], hm.thumb_pose(b, flex0), sdf) < 0.004:
            break
        beta = b
    options = []
    for b in (beta, beta - d(12.0), beta - d(24.0)):
        if b < hm.THUMB_OPEN:
            continue
        tp = hm.thumb_pose(b, flex0)
        flex = hm.close_digit(geom.digits[0], tp.d0, tp.u0, flex0, sdf)
        tip = hm.chain(geom.digits[0], hm.thumb_pose(b, flex))[0][-1]
        options.append((float(abs(sdf(tip[None])[0])), b, flex))
    _, beta, flex = min(options, key=lambda o: o[0])
    digits.append(hm.thumb_pose(beta, flex))
    for g, spread in zip(geom.digits[1:], rng_spread):
        p0 = hm.finger_pose(spread, (0.0, 0.0, 0.0))
        flex = hm.close_digit(g, p0.d0, p0.u0, (0.0, 0.0, 0.0), sdf)
        digits.append(hm.finger_pose(spread, flex))
    pose = hm.HandPose(tuple(digits))
    kp, _ = hm.hand_keypoints(geom, pose)
    tips = np.clip(sdf(kp[[4, 8, 12, 16, 20]]), 0, None)
    score += float(tips.sum() + 10.0 * np.clip(tips - 0.012, 0, None).sum())
    score += 0.03 * (1.0 - (beta - hm.THUMB_OPEN) / (hm.THUMB_OPPOSED - hm.THUMB_OPEN))  # prefer an opposed thumb
    for g, p in zip(geom.digits, digits):
        score += 20.0 * max(0.0, -hm.digit_clearance(g, p, sdf))
    return pose, score


def _plan_grasp(geom: hm.HandGeom, obj: ObjectModel, R_wh: np.ndarray, R_wo: np.ndarray,
                obj_pos: np.ndarray, spread: np.ndarray) -> _Grasp:
    """Search where the object sits against the palm so all five digits wrap onto it."""
    R_ho = R_wh.T @ R_wo
    best: _Grasp | None = None
    top = np.array([0.0, 0.0, 1.0])
    # lid ~6.5 cm above the wrist axis (thumb on the side), ulnar edge clear of the table
    y_mid = min(0.065 * geom.scale - obj.half[2], obj.half[2] - 0.055 * geom.scale)
    def evaluate(x_c: float, y_c: float) -> _Grasp:
        def sdf_at(z_c: float):
            c = np.array([x_c, y_c, z_c])
            return lambda p: obj.sdf((p - c) @ R_ho)

        lo, hi = -0.15, 0.0  # bisection: palm 2 mm from the surface
        for _ in range(16):
            mid = 0.5 * (lo + hi)
            if hm.palm_clearance(geom, sdf_at(mid)) > 0.002:
                lo = mid
            else:
                hi = mid
        pose, score = _close_hand(geom, sdf_at(lo), spread)
        c = np.array([x_c, y_c, lo])
        kp, _ = hm.hand_keypoints(geom, pose)
        wrist = obj_pos - R_wh @ c
        low = (np.concatenate([kp, geom.palm_spheres[:, :3]]) @ R_wh.T + wrist)[:, 2].min()
        score += 3.0 * max(0.0, 0.01 - low)  # keep the hand above the table
        thumb_tip_obj = (kp[4] - c) @ R_ho  # a thumb resting on the lid is not a side grasp
        score += 5.0 * max(0.0, thumb_tip_obj @ top - (obj.half[2] - 0.012))
        return _Grasp(score, c, pose)

    step = 0.011 * geom.scale
    best = min((evaluate(x, y_mid) for x in np.arange(0.05, 0.111, step) * 1.0), key=lambda g: g.score)
    x0 = best.object_in_hand[0]
    for x, y in ((x0 - step / 2, y_mid), (x0 + step / 2, y_mid), (x0, y_mid - 0.006), (x0, y_mid + 0.006)):
        g = evaluate(x, y)
        if g.score < best.score:
            best = g
    return best


def make_plan(spec: SyntheticSpec) -> ClipPlan:
    """Draw the whole clip from the seed (object, hand, grasp, motion, camera, lights)."""
    rng = np.random.default_rng(spec.seed)
    d = np.deg2rad
    intr = Intrinsics.default_for(spec.width, spec.height, hfov_deg=float(rng.uniform(62.0, 72.0)))
    geom = hm.make_hand_geom(float(rng.uniform(0.97, 1.03)))
    skin = _skin_tone(rng)
    obj = _sample_object(rng)

    yaw = d(rng.uniform(-20.0, 15.0))
    R_wh = _hand_world_rot(yaw, d(rng.uniform(-12.0, 8.0)), d(rng.uniform(-6.0, 4.0)))
    R_wo = _rz(yaw + np.pi / 2 + d(rng.uniform(-6.0, 6.0)))
    obj_pos = np.array([rng.uniform(-0.04, 0.03), rng.uniform(-0.02, 0.04), obj.half[2]])
    spread = d(np.array([3.0, 0.0, -4.0, -9.0]) + rng.uniform(-1.5, 1.5, 4))
    grasp = _plan_grasp(geom, obj, R_wh, R_wo, obj_pos, spread)
    wrist = obj_pos - R_wh @ grasp.object_in_hand

    # approach from closer to the body, to the right and higher, palm turned down
    start_rot = R_wh @ Rotation.from_euler("xz", [d(-40.0), d(-10.0)]).as_matrix()
    start_pos = wrist + _rz(yaw) @ np.array([rng.uniform(0.07, 0.12), -rng.uniform(0.12, 0.17), rng.uniform(0.06, 0.1)])
    pregrasp = R_wh @ np.array([-0.02, 0.0, 0.035])
    lift = np.array([rng.uniform(-0.02, 0.02), -rng.uniform(0.0, 0.05), rng.uniform(0.09, 0.13)])

    elbow = obj_pos * [1, 1, 0] + _rz(yaw) @ np.array([rng.uniform(0.16, 0.24), -rng.uniform(0.3, 0.36), 0.0])
    elbow[2] = rng.uniform(0.05, 0.09)
    eye = obj_pos * [1, 1, 0] + np.array([rng.uniform(0.0, 0.07), rng.uniform(-0.36, -0.28), rng.uniform(0.36, 0.44)])
    target = obj_pos * [1, 1, 0] + np.array([rng.uniform(0.02, 0.06), rng.uniform(-0.01, 0.04), 0.05])
    az, el = rng.uniform(0, 2 * np.pi), d(rng.uniform(50.0, 75.0))
    key_dir = -np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
    lamp = obj_pos * [1, 1, 0] + np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.2, 0.5), rng.uniform(0.7, 1.0)])
    return ClipPlan(
        intr=intr, geom=geom, skin_rgb=np.clip(skin, 0, 1), obj=obj,
        world_from_object0=_rt(R_wo, obj_pos), world_from_hand_grasp=_rt(R_wh, wrist),
        hand_start_rot=start_rot, hand_start_pos=start_pos, pregrasp_offset=pregrasp,
        open_pose=_open_pose(rng), grasp_pose=grasp.pose, lift=lift, elbow=elbow, eye=eye, target=target,
        sway_amp=rng.uniform(0.004, 0.012, 3), sway_freq=rng.uniform(0.4, 1.3, 3),
        sway_phase=rng.uniform(0, 2 * np.pi, 3),
        tremor=np.stack([rng.uniform(0.001, 0.003, 3), rng.uniform(1.5, 3.0, 3), rng.uniform(0, 2 * np.pi, 3)]),
        key_dir=key_dir / np.linalg.norm(key_dir), key_rgb=np.array([1.0, rng.uniform(0.88, 1.0), rng.uniform(0.75, 0.95)]),
        key_intensity=float(rng.uniform(1.5, 2.3)), lamp_pos=lamp, lamp_intensity=float(rng.uniform(0.8, 1.6)),
        ambient=float(rng.uniform(0.15, 0.28)), light_phase=float(rng.uniform(0, 2 * np.pi)),
        table_seed=int(rng.integers(2**31)), still=spec.still, **_sleeve(spec),
    )


def _sleeve(spec: SyntheticSpec) -> dict:
    """The sleeve's colour and start, from a stream of their own (a clip without a sleeve draws
    exactly what it drew before sleeves existed)."""
    if not spec.sleeve:
        return {}
    rng = np.random.default_rng([spec.seed, 5])
    rgb = np.asarray(SLEEVE_COLOURS[int(rng.integers(len(SLEEVE_COLOURS)))]) * rng.uniform(0.9, 1.1, 3)
    return {"sleeve_rgb": np.clip(rgb, 0, 1), "sleeve_start": float(rng.uniform(0.025, 0.06))}


# ----------------------------------------------------------------------------- per-frame state


@dataclass(frozen=True)
class FrameState:
    world_from_camera: np.ndarray
    world_from_hand: np.ndarray
    world_from_forearm: np.ndarray
    world_from_object: np.ndarray
    hand_pose: hm.HandPose
    key_pose: np.ndarray
    key_intensity: float
    lamp_pos: np.ndarray
    lamp_intensity: float


def _lift_offset(plan: ClipPlan, u: float) -> np.ndarray:
    return plan.lift * _phase(u, LIFT_START, 1.0)


def _hand_transform(plan: ClipPlan, u: float) -> np.ndarray:
    grasp = plan.world_from_hand_grasp
    if u >= CONTACT_END:
        return _rt(grasp[:3, :3], grasp[:3, 3] + _lift_offset(plan, u))
    pre = grasp[:3, 3] + plan.pregrasp_offset
    if u >= APPROACH_END:
        w = _phase(u, APPROACH_END, CONTACT_END)
        return _rt(grasp[:3, :3], (1 - w) * pre + w * grasp[:3, 3])
    w = _phase(u, 0.0, APPROACH_END)
    rots = Rotation.from_matrix(np.stack([plan.hand_start_rot, grasp[:3, :3]]))
    R = Slerp([0.0, 1.0], rots)(w).as_matrix()
    amp, freq, phase = plan.tremor
    tremor = amp * np.sin(2 * np.pi * freq * u + phase) * (1.0 - w)
    return _rt(R, (1 - w) * plan.hand_start_pos + w * pre + tremor)


def _forearm_transform(world_from_hand: np.ndarray, elbow: np.ndarray) -> np.ndarray:
    """Forearm from the wrist towards an elbow that stays near the body, below the view."""
    R = world_from_hand[:3, :3]
    z = elbow - world_from_hand[:3, 3]
    z /= np.linalg.norm(z)
    x = R[:, 1] - (R[:, 1] @ z) * z
    x /= np.linalg.norm(x)
    return _rt(np.stack([x, np.cross(z, x), z], axis=1), world_from_hand[:3, 3])


def frame_state(plan: ClipPlan, t: int, n_frames: int) -> FrameState:
    """The scene at frame t: a pure function of (plan, t), so chunks render independently."""
    u = t / max(n_frames - 1, 1)
    m = STILL_AT if plan.still else u  # where the hand and object are in the script
    T_wh = _hand_transform(plan, m)
    hand_pose = hm.blend_pose(plan.open_pose, plan.grasp_pose, _phase(m, CLOSE_START, CLOSE_END))
    T_wo = plan.world_from_object0.copy()
    T_wo[:3, 3] += _lift_offset(plan, m)

    sway = plan.sway_amp * np.sin(2 * np.pi * plan.sway_freq * u + plan.sway_phase)
    follow = np.array([0.0, 0.0, 0.5]) * _lift_offset(plan, m)[2]
    T_wc = look_at(plan.eye + sway, plan.target + 0.6 * sway[[1, 2, 0]] + follow)

    wobble = Rotation.from_euler("xy", 0.08 * np.sin(2 * np.pi * 0.7 * u + plan.light_phase + np.array([0, 1]))).as_matrix()
    zl = -(wobble @ plan.key_dir)
    xl = np.cross([0.0, 0.0, 1.0], zl)
    xl /= np.linalg.norm(xl)
    key_pose = _rt(np.stack([xl, np.cross(zl, xl), zl], axis=1), np.zeros(3))
    flicker = 1.0 + 0.08 * np.sin(2 * np.pi * 0.9 * u + plan.light_phase)
    lamp = plan.lamp_pos + 0.05 * np.array([np.sin(2 * np.pi * 0.5 * u + plan.light_phase), np.cos(2 * np.pi * 0.4 * u), 0.0])
    return FrameState(T_wc, T_wh, _forearm_transform(T_wh, plan.elbow), T_wo, hand_pose, key_pose,
                      plan.key_intensity * flicker, lamp, plan.lamp_intensity * (2.0 - flicker))


def arm_joints(plan: ClipPlan, state: FrameState) -> np.ndarray:
    """(3,3) world elbow, shoulder, clavicle (keypoints.ARM_JOINTS): the elbow at the forearm's
    end; the others are not modelled (a source marks them untracked)."""
    elbow = state.world_from_forearm @ np.array([0.0, 0.0, plan.geom.forearm_length, 1.0])
    return np.stack([elbow[:3], np.zeros(3), np.zeros(3)])


def frame_keypoints(plan: ClipPlan, state: FrameState) -> np.ndarray:
    """21 joints in the world frame (metres)."""
    kp, _ = hm.hand_keypoints(plan.geom, state.hand_pose)
    return kp @ state.world_from_hand[:3, :3].T + state.world_from_hand[:3, 3]


# ----------------------------------------------------------------------------- table texture


_WOODS = (
    ((0.50, 0.33, 0.19), (0.74, 0.55, 0.35)),  # oak
    ((0.28, 0.17, 0.10), (0.48, 0.32, 0.19)),  # walnut
    ((0.66, 0.54, 0.40), (0.86, 0.75, 0.60)),  # birch
    ((0.42, 0.40, 0.38), (0.60, 0.58, 0.55)),  # grey laminate
)


def _fbm(rng: np.random.Generator, size: int, base: int, octaves: int, aspect: int = 1) -> np.ndarray:
    """Periodic (tileable) fractal noise in [-1, 1] by spectral synthesis; ``aspect`` > 1
    stretches features along y (wood fibres run along the planks)."""
    fy = np.fft.fftfreq(size)[:, None] * size * aspect
    fx = np.fft.fftfreq(size)[None, :] * size
    f = np.hypot(fx, fy)
    lo, hi = base, base * 2**octaves
    amp = np.where((f >= lo * 0.5) & (f <= hi), 1.0 / np.maximum(f, 1e-6) ** 1.2, 0.0)
    spec = np.fft.fft2(rng.standard_normal((size, size))) * amp
    out = np.real(np.fft.ifft2(spec)).astype(np.float32)
    return out / np.abs(out).max()


def wood_texture(seed: int, size: int = 512) -> np.ndarray:
    """Planked wood (or laminate) RGB uint8 texture: fibres, soft growth rings, plank seams."""
    rng = np.random.default_rng(seed)
    dark, light = (np.array(c) for c in _WOODS[rng.integers(len(_WOODS))])
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    planks = 4
    idx = np.floor(xx * planks).astype(int)
    offs = rng.uniform(0, 10, planks)[idx]
    warp, warp2 = _fbm(rng, size, 1, 2), _fbm(rng, size, 3, 2, aspect=3)
    c = xx * planks * rng.uniform(4.0, 7.0) + offs + 1.0 * warp + 0.15 * warp2
    rings = (0.5 + 0.5 * np.sin(2 * np.pi * c)) ** 4  # thin dark latewood lines
    fibres = _fbm(rng, size, 48, 3, aspect=24)  # stretched along the planks
    tone = rng.uniform(-0.08, 0.08, planks)[idx]
    w = np.clip(0.62 - 0.35 * rings + 0.22 * fibres + 0.12 * warp + tone, 0, 1)[..., None]
    rgb = dark * (1 - w) + light * w
    rgb *= 1.0 + 0.025 * rng.standard_normal((size, size, 1)).astype(np.float32)
    seam = np.abs((xx * planks) - np.round(xx * planks)) < 0.003
    rgb[seam] *= 0.6
    return (np.clip(rgb, 0, 1) * 255).astype(np.uint8)


# ----------------------------------------------------------------------------- scene


@dataclass
class _Scene:
    scene: "pyrender.Scene"
    camera: "pyrender.Node"
    key: "pyrender.Node"
    lamp: "pyrender.Node"
    palm: "pyrender.Node"
    segments: list
    nails: list
    forearm: list  # the forearm and its sleeve, posed together
    obj: "pyrender.Node"
    hand_meshes: list
    seg_map: dict
    table: "pyrender.Mesh"


def _linear(srgb) -> np.ndarray:
    """Material factors and vertex colours are linear; the shader applies gamma 2.2."""
    return np.clip(np.asarray(srgb, float), 0.0, 1.0) ** 2.2


def _skin_mesh(pyrender, mesh: trimesh.Trimesh, rgb: np.ndarray, dorsal: np.ndarray, rng, tint=None):
    """Smooth-shaded skin with per-vertex colour (pyrender's from_trimesh drops vertex
    colours when a material is given, so the primitive is built directly)."""
    colours = hm.skin_colors(mesh, rgb, dorsal, rng, *(() if tint is None else (tint,)))
    mat = pyrender.MetallicRoughnessMaterial(baseColorFactor=(1.0, 1.0, 1.0, 1.0), metallicFactor=0.0,
                                             roughnessFactor=0.62)
    prim = pyrender.Primitive(positions=np.asarray(mesh.vertices, np.float32),
                              normals=np.asarray(mesh.vertex_normals, np.float32),
                              indices=np.asarray(mesh.faces), color_0=colours.astype(np.float32) / 255.0,
                              material=mat)
    return pyrender.Mesh([prim])


def _table_mesh(pyrender, seed: int) -> "pyrender.Mesh":
    half, tile = 4.0, 0.6
    pos = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], np.float32)
    uv = (pos[:, :2] + half) / tile
    tex = pyrender.Texture(source=wood_texture(seed), source_channels="RGB")
    mat = pyrender.MetallicRoughnessMaterial(baseColorTexture=tex, metallicFactor=0.0, roughnessFactor=0.8)
    prim = pyrender.Primitive(positions=pos, normals=np.tile([0, 0, 1.0], (4, 1)).astype(np.float32),
                              texcoord_0=uv.astype(np.float32), indices=np.array([[0, 1, 2], [0, 2, 3]]),
                              material=mat)
    return pyrender.Mesh([prim])


def _build_scene(plan: ClipPlan) -> _Scene:
    """One scene per clip and thread; per frame only node poses and light values change."""
    import pyrender

    from handedit.render.gl import Scene

    rng = np.random.default_rng(plan.table_seed + 1)
    scene = Scene(bg_color=(0, 0, 0, 0.0), ambient_light=np.full(3, plan.ambient))
    table = _table_mesh(pyrender, plan.table_seed)
    scene.add(table)

    obj_tm = plan.obj.mesh()
    obj_mat = pyrender.MetallicRoughnessMaterial(baseColorFactor=(*_linear(plan.obj.rgb), 1.0), metallicFactor=0.0,
                                                 roughnessFactor=0.45)
    obj_mesh = pyrender.Mesh.from_trimesh(obj_tm.smooth_shaded if plan.obj.kind == "cylinder"
                                          else obj_tm, material=obj_mat, smooth=plan.obj.kind == "cylinder")
    obj = scene.add(obj_mesh)

    g, skin = plan.geom, _linear(plan.skin_rgb)
    palm_mesh = _skin_mesh(pyrender, hm.palm_mesh(g), skin, np.array([0, 0, 1.0]), rng)
    palm = scene.add(palm_mesh)
    seg_meshes = [_skin_mesh(pyrender, m, skin, np.array([0, 1.0, 0]), rng) for m in hm.segment_meshes(g)]
    segments = [scene.add(m) for m in seg_meshes]
    nail_rgb = _linear(plan.skin_rgb * np.array([1.05, 0.98, 0.98]) + 0.12)
    nail_meshes = [_skin_mesh(pyrender, m, nail_rgb, np.array([0, 1.0, 0]), rng, np.ones(3)) for m in hm.nail_meshes(g)]
    nails = [scene.add(m) for m in nail_meshes]
    arm_mesh = _skin_mesh(pyrender, hm.forearm_mesh(g), skin * 0.95, np.array([0, 1.0, 0]), rng,
                          np.ones(3))
    forearm = scene.add(arm_mesh)
    arm_meshes, arm_nodes = [arm_mesh], [forearm]
    if plan.sleeve_rgb is not None:
        arm_meshes.append(_cloth_mesh(pyrender, hm.sleeve_mesh(g, plan.sleeve_start), _linear(plan.sleeve_rgb), plan.table_seed))
        arm_nodes.append(scene.add(arm_meshes[-1]))

    i = plan.intr
    cam = scene.add(pyrender.IntrinsicsCamera(i.fx, i.fy, i.cx, i.cy, znear=0.01, zfar=10.0))
    key = scene.add(pyrender.DirectionalLight(color=plan.key_rgb, intensity=plan.key_intensity))
    lamp = scene.add(pyrender.PointLight(color=np.ones(3), intensity=plan.lamp_intensity))
    seg_map = {n: _SEG_HAND for n in [palm, *segments, *nails]}
    seg_map.update({n: _SEG_ARM for n in arm_nodes})
    seg_map[obj] = _SEG_OBJ
    return _Scene(scene, cam, key, lamp, palm, segments, nails, arm_nodes, obj,
                  [palm_mesh, *seg_meshes, *nail_meshes, *arm_meshes], seg_map, table)


def _cloth_mesh(pyrender, mesh: trimesh.Trimesh, rgb: np.ndarray, seed: int):
    """Matte cloth with per-vertex colour: a woven stripe across the sleeve and fold shading."""
    rng = np.random.default_rng([seed, 7])
    v = mesh.vertices
    weave = 0.07 * np.sin(v[:, 2] * rng.uniform(250, 400)) + 0.05 * np.sin(np.arctan2(v[:, 1], v[:, 0]) * 9)
    fold = 0.10 * np.sin(v[:, 2] * rng.uniform(25, 45) + rng.uniform(0, 2 * np.pi))
    colours = np.clip(rgb[None] * (1.0 + weave + fold)[:, None], 0, 1)
    rgba = np.concatenate([colours, np.ones((len(v), 1))], axis=1).astype(np.float32)
    mat = pyrender.MetallicRoughnessMaterial(baseColorFactor=(1.0, 1.0, 1.0, 1.0), metallicFactor=0.0,
                                             roughnessFactor=0.95)
    prim = pyrender.Primitive(positions=np.asarray(v, np.float32), normals=np.asarray(mesh.vertex_normals, np.float32),
                              indices=np.asarray(mesh.faces), color_0=rgba, material=mat)
    return pyrender.Mesh([prim])


def _pose_scene(s: _Scene, plan: ClipPlan, st: FrameState) -> None:
    T = st.world_from_hand
    _, frames = hm.hand_keypoints(plan.geom, st.hand_pose)
    s.scene.set_pose(s.palm, T)
    for node, F in zip(s.segments, frames):
        s.scene.set_pose(node, T @ F)
    for k, node in enumerate(s.nails):
        s.scene.set_pose(node, T @ frames[3 * k + 2])
    for node in s.forearm:
        s.scene.set_pose(node, st.world_from_forearm)
    s.scene.set_pose(s.obj, st.world_from_object)
    s.scene.set_pose(s.camera, st.world_from_camera @ CV_TO_GL)
    s.scene.set_pose(s.key, st.key_pose)
    s.key.light.intensity = st.key_intensity
    s.scene.set_pose(s.lamp, _rt(np.eye(3), st.lamp_pos))
    s.lamp.light.intensity = st.lamp_intensity


_RENDERERS: dict[tuple[int, int], "pyrender.OffscreenRenderer"] = {}
_SCENES = Lru(max_items=4)  # (process, thread, clip fingerprint) -> _Scene
_RENDERERS_LOCK = threading.Lock()


def _renderer(width: int, height: int) -> "pyrender.OffscreenRenderer":
    """One EGL renderer per (process, thread): a GL context belongs to the thread that made it."""
    import pyrender

    key = (os.getpid(), threading.get_ident())
    r = _RENDERERS.get(key)
    if r is None:
        r = pyrender.OffscreenRenderer(width, height)
        with _RENDERERS_LOCK:
            _RENDERERS[key] = r
    r.viewport_width, r.viewport_height = width, height
    return r


def _scene_for(fingerprint: str, plan: ClipPlan) -> _Scene:
    key = (os.getpid(), threading.get_ident(), fingerprint)
    s = _SCENES.get(key, None)
    return _SCENES.put(key, _build_scene(plan)) if s is None else s


@dataclass
class RenderedFrame:
    rgb: np.ndarray
    background: np.ndarray
    hand_mask: np.ndarray
    handarm_mask: np.ndarray
    object_mask: np.ndarray


def _set_visible(meshes: list, visible: bool) -> None:
    for m in meshes:
        m.is_visible = visible


def _render(s: _Scene, r: "pyrender.OffscreenRenderer") -> RenderedFrame:
    """Background (no hand), a hand layer (no table, RGBA) and labels (aliased, depth-tested).

    The frame is the MSAA hand layer composited over the background with its coverage
    alpha, only near labelled hand pixels: identical to rendering everything at once up to
    rounding, but the full-screen table is shaded once instead of twice. ``handarm_mask``
    is the labelled pixels plus every pixel the hand tinted, so ``frame == background``
    holds exactly outside it.
    """
    import pyrender

    _set_visible(s.hand_meshes, False)
    try:
        bg, _ = r.render(s.scene)
    finally:
        _set_visible(s.hand_meshes, True)
    s.table.is_visible = False
    try:
        layer, _ = r.render(s.scene, flags=pyrender.RenderFlags.RGBA)
    finally:
        s.table.is_visible = True
    seg, _ = r.render(s.scene, flags=pyrender.RenderFlags.SEG, seg_node_map=s.seg_map)
    hand_px, arm_px, obj_px = seg[..., 0] > 127, seg[..., 1] > 127, seg[..., 2] > 127
    kernel = np.ones((3, 3), np.uint8)
    near = cv2.dilate((hand_px | arm_px).astype(np.uint8), kernel).astype(bool)
    alpha = layer[..., 3:].astype(np.float32) / 255.0
    comp = np.clip(layer[..., :3] + (1.0 - alpha) * bg + 0.5, 0, 255).astype(np.uint8)  # premultiplied over
    rgb = np.where(near[..., None], comp, bg)
    tinted = np.any(rgb != bg, axis=-1)
    handarm = hand_px | arm_px | tinted
    near_hand = cv2.dilate(hand_px.astype(np.uint8), kernel).astype(bool)
    hand = hand_px | (tinted & ~arm_px & near_hand)
    return RenderedFrame(rgb, bg.copy(), hand, handarm, obj_px)


# ----------------------------------------------------------------------------- source


class SyntheticSource:
    """Renders frames of a ``SyntheticSpec``; pickles as its spec (GL state is per process)."""

    def __init__(self, spec: SyntheticSpec):
        if spec.width < 16 or spec.height < 16 or spec.n_frames < 1 or spec.fps <= 0:
            raise SourceError(f"synthetic spec {spec.clip_id}: need width/height >= 16, n_frames >= 1, fps > 0")
        self.spec = spec
        self._plan: ClipPlan | None = None

    def __getstate__(self) -> dict:
        return {"spec": self.spec}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["spec"])

    @property
    def plan(self) -> ClipPlan:
        if self._plan is None:
            self._plan = make_plan(self.spec)
        return self._plan

    @property
    def fingerprint(self) -> str:
        # fields at their defaults that came later are left out: the clips made before they existed keep theirs
        dump = self.spec.model_dump_json(exclude={k for k in ("still", "sleeve") if not getattr(self.spec, k)} or None)
        return hashlib.sha256((dump + GENERATOR_VERSION).encode()).hexdigest()

    def info(self) -> ClipInfo:
        s = self.spec
        return ClipInfo(
            clip_id=s.clip_id, n_frames=s.n_frames, height=s.height, width=s.width, fps=s.fps,
            intrinsics=self.plan.intr, has_keypoints=True, has_object=True, fingerprint=self.fingerprint,
            meta={"dataset": "synthetic", "generator": GENERATOR_VERSION, "seed": s.seed, "object": self.plan.obj.kind},
            ground_truth=GROUND_TRUTH, hands=("right",), keypoints_exact=True, has_arm=s.sleeve,
            world={"up": [0.0, 0.0, 1.0], "support_plane": [0.0, 0.0, 1.0, 0.0], "origin": "the table top (z = 0)"},
        )

    def object_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        m = self.plan.obj.mesh()
        return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)

    def read(self, start: int, stop: int) -> ClipChunk:
        n_total = self.spec.n_frames
        if not (0 <= start <= stop <= n_total):
            raise SourceError(f"synthetic clip {self.spec.clip_id}: frame range [{start}, {stop}) "
                              f"outside [0, {n_total}]")
        plan, W, H, n = self.plan, self.spec.width, self.spec.height, stop - start
        out = {
            "frames": np.zeros((n, H, W, 3), np.uint8), "background": np.zeros((n, H, W, 3), np.uint8),
            "hand": np.zeros((n, H, W), bool), "handarm": np.zeros((n, H, W), bool),
            "obj": np.zeros((n, H, W), bool),
        }
        T_wc = np.zeros((n, 4, 4))
        T_co = np.zeros((n, 4, 4))
        kps = np.zeros((n, 1, 21, 3), np.float32)  # one hand: the right
        valid = np.zeros((n, 1, 21), bool)
        arm_kps, arm_valid = np.zeros((n, 1, 3, 3), np.float32), np.zeros((n, 1, 3), bool)
        if n:
            r, s = _renderer(W, H), _scene_for(self.fingerprint, plan)
            for i, t in enumerate(range(start, stop)):
                st = frame_state(plan, t, n_total)
                _pose_scene(s, plan, st)
                f = _render(s, r)
                out["frames"][i], out["background"][i] = f.rgb, f.background
                out["hand"][i], out["handarm"][i], out["obj"][i] = f.hand_mask, f.handarm_mask, f.object_mask
                T_wc[i] = st.world_from_camera
                cam_from_world = np.linalg.inv(st.world_from_camera)
                T_co[i] = cam_from_world @ st.world_from_object
                kp = frame_keypoints(plan, st) @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
                valid[i, 0] = kp[:, 2] > 0.01
                kps[i, 0] = np.where(valid[i, 0][:, None], kp, 0.0)
                arm_kps[i, 0] = arm_joints(plan, st) @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
                arm_valid[i, 0, 0] = True  # the elbow, even behind the camera (EgoDex's too)
        return ClipChunk(
            start=start, frames=out["frames"], world_from_camera=T_wc, keypoints=kps, keypoints_valid=valid,
            frame_ok=np.ones(n, bool), object_mask=out["obj"], object_pose=T_co,
            object_depth=object_depth(*self.object_mesh(), T_co, plan.intr),
            gt={"hand_mask": out["hand"], "handarm_mask": out["handarm"], "background": out["background"]},
            **({"arm_keypoints": np.where(arm_valid[..., None], arm_kps, 0.0), "arm_valid": arm_valid} if self.spec.sleeve else {}),
        )
