"""Automatic QC of hand retargeting (paper, "Quality-control criteria", hand retargeting row).

Per frame, first failing check wins:
  JOINT_LIMIT      qpos outside the URDF limits;
  FINGERTIP_ERROR  mean fingertip error > 50 mm;   WRIST_ERROR  wrist error > 50 mm;
  PENETRATION      robot surface more than ``penetration_mm`` inside the object ("severe");
  CONTACT_LOSS     the human touches the object but no robot fingertip does;
  CONTACT_DISTANCE a finger the human has in contact ends > 20 mm from the object surface.

Contact is measured against the object's mesh and per-frame pose when the source has them
(``Source.object_mesh()``, ``ClipChunk.object_pose``); otherwise the contact and
penetration checks are not possible and the report says so (``contact_checked=False``,
``notes``) instead of passing silently. Robot surface points are sampled once per URDF
from its visual meshes (cached per process).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import trimesh
from pydantic import BaseModel, ConfigDict, Field

from handedit.embodiments.kinematics import get_kinematics
from handedit.embodiments.roster import get_embodiment, resolve_asset
from handedit.embodiments.urdf import load_urdf, resolve_mesh_filename
from handedit.keypoints import FINGERTIPS
from handedit.reasons import STATUS_DTYPE, Reason
from handedit.retarget.api import RetargetResult, get_retargeter
from handedit.retarget.config import RetargetConfig
from handedit.setup_meter import metered


class RetargetQCConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")
    VERSION: ClassVar[int] = 1

    fingertip_mm: float = Field(50.0, gt=0)
    wrist_mm: float = Field(50.0, gt=0)
    contact_mm: float = Field(10.0, gt=0, description="a fingertip this close to the surface touches it")
    contact_distance_mm: float = Field(20.0, gt=0)
    penetration_mm: float = Field(10.0, gt=0, description="depth of a severe penetration")
    surface_points_per_link: int = Field(64, ge=8)

    @classmethod
    def from_retarget(cls, cfg: RetargetConfig) -> "RetargetQCConfig":
        """The thresholds a curate run sets through its retarget stage config."""
        return cls(fingertip_mm=cfg.fingertip_reject_mm, wrist_mm=cfg.wrist_reject_mm, contact_mm=cfg.contact_mm,
                   contact_distance_mm=cfg.contact_distance_mm, penetration_mm=cfg.penetration_mm)


@dataclass
class RetargetQC:
    status: np.ndarray  # (T,) int16: the retargeting status with QC rejections applied
    details: dict[int, str]  # frame -> text for rejected frames
    contact_checked: bool
    human_contact: np.ndarray  # (T,) bool: the source shows contact (False where unknown)
    contact_distance_mm: np.ndarray  # (T,) max over human-contact fingers of the robot tip distance (nan: n/a)
    penetration_mm: np.ndarray  # (T,) deepest robot point inside the object (nan: n/a)
    notes: list[str] = field(default_factory=list)


@functools.lru_cache(maxsize=16)
@metered
def surface_samples(urdf_path: str, n: int) -> dict[str, np.ndarray]:
    """link -> (n,3) points on its visual meshes, in the link frame."""
    urdf = load_urdf(urdf_path, load_meshes=False)
    rng = np.random.default_rng(0)
    out: dict[str, np.ndarray] = {}
    for link in urdf.robot.links:
        pts = []
        for vis in link.visuals:
            mesh = vis.geometry.mesh if vis.geometry is not None else None
            if mesh is None:
                continue
            m = trimesh.load(str(resolve_mesh_filename(mesh.filename, urdf_path)), force="mesh")
            if mesh.scale is not None:
                m.apply_scale(mesh.scale)
            if vis.origin is not None:
                m.apply_transform(np.asarray(vis.origin, float))
            if len(m.faces):
                p, _ = trimesh.sample.sample_surface(m, n, seed=int(rng.integers(2**31)))
                pts.append(np.asarray(p))
        if pts:
            out[link.name] = np.concatenate(pts)
    return out


def robot_surface(embodiment_id: str, q: np.ndarray, camera_from_root: np.ndarray, n: int = 64) -> np.ndarray:
    """(N,3) surface samples of the robot hand at ``q`` in the camera frame."""
    ra = resolve_asset(get_embodiment(embodiment_id))
    kin = get_kinematics(ra.path)
    samples = surface_samples(str(ra.path), n)
    parts = []
    for link, p in samples.items():
        T = camera_from_root @ kin.fk(q, link)
        parts.append(p @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(parts) if parts else np.zeros((0, 3))


def retarget_qc(
    result: RetargetResult,
    keypoints: np.ndarray,
    keypoints_valid: np.ndarray,
    embodiment_id: str,
    cfg: RetargetQCConfig,
    retarget_cfg: RetargetConfig | None = None,
    object_mesh: tuple[np.ndarray, np.ndarray] | None = None,
    object_pose: np.ndarray | None = None,
) -> RetargetQC:
    """Apply the hand-retargeting QC to a ``retarget`` result (see module doc)."""
    rt = get_retargeter(embodiment_id, retarget_cfg or RetargetConfig())
    kp = np.asarray(keypoints, float)
    valid = np.asarray(keypoints_valid, bool)
    T = len(result.qpos)
    status = np.asarray(result.status, STATUS_DTYPE).copy()
    details: dict[int, str] = {}
    notes: list[str] = []
    contact_d = np.full(T, np.nan)
    pen = np.full(T, np.nan)
    human_contact = np.zeros(T, bool)
    mesh = None
    if object_mesh is not None and object_pose is not None:
        mesh = trimesh.Trimesh(np.asarray(object_mesh[0], float), np.asarray(object_mesh[1], int), process=False)
        lo, hi = mesh.bounds[0] - 1e-3, mesh.bounds[1] + 1e-3
    else:
        notes.append("contact and penetration checks not possible: the source has no object mesh and pose")

    # robot fingertip rows <-> MANO fingertips
    tip_rows = {int(rt.mano_idx[r]): int(r) for r in rt.tip_rows}
    for i in range(T):
        if status[i] != Reason.OK:
            continue
        q = result.qpos[i].astype(float)
        if np.any(q < rt.lower - 1e-6) or np.any(q > rt.upper + 1e-6):
            status[i], details[i] = Reason.JOINT_LIMIT, "joint outside its URDF limits"
            continue
        if result.fingertip_error_mm[i] > cfg.fingertip_mm:
            status[i], details[i] = Reason.FINGERTIP_ERROR, f"fingertip error {result.fingertip_error_mm[i]:.1f} mm > {cfg.fingertip_mm:g}"
            continue
        if result.wrist_error_mm[i] > cfg.wrist_mm:
            status[i], details[i] = Reason.WRIST_ERROR, f"wrist error {result.wrist_error_mm[i]:.1f} mm > {cfg.wrist_mm:g}"
            continue
        if mesh is None:
            continue
        obj_from_cam = np.linalg.inv(np.asarray(object_pose[i], float))

        def to_obj(p):
            return p @ obj_from_cam[:3, :3].T + obj_from_cam[:3, 3]

        pts = to_obj(robot_surface(embodiment_id, q, result.root_pose[i], cfg.surface_points_per_link))
        near = np.all((pts > lo) & (pts < hi), axis=1)  # only points inside the box can be inside the object
        sd = trimesh.proximity.signed_distance(mesh, pts[near]) if near.any() else np.zeros(0)  # > 0 inside
        pen[i] = max(float(sd.max()) * 1000.0, 0.0) if sd.size else 0.0
        tips_h = [f for f in FINGERTIPS if valid[i, f]]
        d_h = np.abs(trimesh.proximity.signed_distance(mesh, to_obj(kp[i, tips_h]))) * 1000.0 if tips_h else np.zeros(0)
        touching = [f for f, d in zip(tips_h, d_h) if d < cfg.contact_mm]
        human_contact[i] = bool(touching)
        robot_tips = rt.robot_points(q, result.root_pose[i])[list(tip_rows.values())]
        d_r = dict(zip(tip_rows, np.abs(trimesh.proximity.signed_distance(mesh, to_obj(robot_tips))) * 1000.0))
        shared = [f for f in touching if f in d_r]
        if shared:
            contact_d[i] = max(d_r[f] for f in shared)
        if pen[i] > cfg.penetration_mm:
            status[i], details[i] = Reason.PENETRATION, f"robot {pen[i]:.1f} mm inside the object > {cfg.penetration_mm:g}"
        elif touching and min(d_r.values(), default=np.inf) >= cfg.contact_mm:
            status[i], details[i] = Reason.CONTACT_LOSS, (
                f"human touches the object with {len(touching)} finger(s); nearest robot fingertip "
                f"{min(d_r.values()):.1f} mm away")
        elif shared and contact_d[i] > cfg.contact_distance_mm:
            status[i], details[i] = Reason.CONTACT_DISTANCE, f"contact distance {contact_d[i]:.1f} mm > {cfg.contact_distance_mm:g}"
    return RetargetQC(status, details, mesh is not None, human_contact, contact_d.astype(np.float32),
                      pen.astype(np.float32), notes)
