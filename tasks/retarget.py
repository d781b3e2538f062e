"""retarget: robot joint trajectory and root pose for one chunk of hand keypoints."""

from __future__ import annotations

import zarr
from prefect import task

from handedit.reasons import combine, gate
from handedit.retarget import RetargetConfig, retarget as retarget_keypoints
from handedit.camera import Intrinsics
from handedit.storage import Unit, open_store, read_chunk
from handedit.storage.store import write_previews
from handedit.tasks._options import stage_options
from handedit.tasks.common import ChunkJob, StageOutput, execute


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    if job.context.get("track") == "hand_arm":
        return _hand_arm_body(root, job)
    src = read_chunk(root, Unit("ingest", job.unit.clip), ["keypoints", "keypoints_valid", "status"], job.start, job.stop)
    cfg = RetargetConfig(**job.params)
    result = retarget_keypoints(src["keypoints"], src["keypoints_valid"], job.unit.embodiment, cfg)
    qc = _qc(root, job, result, src["keypoints"], src["keypoints_valid"], cfg, job.start, job.stop)
    arrays = {
        "qpos": result.qpos,
        "root_pose": result.root_pose,
        "fingertip_error_mm": result.fingertip_error_mm,
        "wrist_error_mm": result.wrist_error_mm,
    }
    return StageOutput(arrays, combine(qc.status, gate(src["status"])), method="casadi:ipopt-hybrid",
                       details=qc.details, extra={"qc_contact_checked": qc.contact_checked, "qc_notes": qc.notes})


def _qc(root: zarr.Group, job: ChunkJob, result, keypoints, valid, cfg: RetargetConfig, start: int, stop: int):
    """Retargeting QC of frames [start, stop); contact/penetration against the object when the
    source has one (mesh from the source, pose from ingest)."""
    from handedit.retarget.qc import RetargetQCConfig, retarget_qc
    from handedit.sources import open_source_json

    mesh = pose = None
    if job.context.get("has_object") and job.context.get("source"):
        mesh = open_source_json(job.context["source"]).object_mesh()
        pose = read_chunk(root, Unit("ingest", job.unit.clip), ["object_pose"], start, stop)["object_pose"]
    return retarget_qc(result, keypoints, valid, job.unit.embodiment, RetargetQCConfig.from_retarget(cfg),
                       cfg, object_mesh=mesh, object_pose=pose)


def _hand_arm_body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    """Hand-arm: one job covers the whole clip (the virtual base is fixed per sequence);
    the sequence-level record (all 27 candidate scores, the choice and its policy) goes to
    provenance."""
    from handedit.retarget.hand_arm import merge_hand_qc, retarget_hand_arm
    from handedit.retarget.preview import top_previews

    src = read_chunk(root, Unit("ingest", job.unit.clip), ["keypoints", "keypoints_valid", "world_from_camera", "status"],
                     job.start, job.stop)
    # an operator's choice from `handedit review` (read fresh: the cached root may predate it)
    review = (open_store(job.store).attrs.get("reviews") or {}).get(f"{job.unit.clip}/{job.unit.embodiment}")
    cfg = RetargetConfig(**job.params)
    res = retarget_hand_arm(src["keypoints"], src["keypoints_valid"], job.unit.embodiment, cfg,
                            world_from_camera=src["world_from_camera"], choice=None if review is None else review["choice"])
    qc = _qc(root, job, res.hand, src["keypoints"], src["keypoints_valid"], cfg, job.start, job.stop)
    status, details = merge_hand_qc(res, qc)
    previews = write_previews(root, job.unit, *top_previews(res, Intrinsics(**job.context["intrinsics"]),
                                                              world_from_camera=src["world_from_camera"]))
    arrays = {"qpos": res.qpos, "root_pose": res.root_pose,
              "fingertip_error_mm": res.fingertip_error_mm, "wrist_error_mm": res.wrist_error_mm}
    return StageOutput(arrays, combine(status, gate(src["status"])), method="casadi:ipopt-hybrid+virtual-base",
                       details=details,
                       extra={"virtual_base": res.summary(), "previews": previews,
                              "qc_contact_checked": qc.contact_checked, "qc_notes": qc.notes})


@task(**stage_options("retarget"))
def retarget(job: ChunkJob) -> dict:
    return execute(job, body)
