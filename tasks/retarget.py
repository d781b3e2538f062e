"""retarget: robot joint trajectories and root poses of every hand in one chunk (hand-only)
or in the whole clip (hand-arm: the virtual base is fixed per sequence)."""

from __future__ import annotations

import numpy as np
import zarr
from prefect import task

from handedit.camera import Intrinsics
from handedit.reasons import Reason, combine, gate, per_frame
from handedit.retarget import RetargetConfig
from handedit.retarget.sides import SidesResult, preview_intrinsics, retarget_hand_arm_sides, retarget_sides
from handedit.storage import Unit, open_store, read_chunk
from handedit.storage.store import write_previews
from handedit.tasks._options import stage_options
from handedit.tasks.common import ChunkJob, StageOutput, execute


def _inputs(root: zarr.Group, job: ChunkJob, extra: tuple[str, ...] = ()) -> dict:
    clip = job.unit.clip
    arm = job.context.get("has_arm", False) and job.context.get("track") == "hand_arm"
    src = read_chunk(root, Unit("ingest", clip), ["status", *extra, *(["arm_valid"] if arm else [])], job.start, job.stop)
    reg = read_chunk(root, Unit("registration", clip), ["keypoints", "keypoints_valid", "hand_status", "status",
                                                    *(["arm_keypoints"] if arm else [])], job.start, job.stop)
    seg = read_chunk(root, Unit("segment", clip), ["hand_status"], job.start, job.stop)
    ok = gate(src["status"], reg["status"])
    # a hand is retargeted where it was registered and segmented
    ready = ok[:, None] & (reg["hand_status"] == Reason.OK) & (seg["hand_status"] == Reason.OK)
    return {**src, **{f"reg_{k}": v for k, v in reg.items()}, "seg_hand_status": seg["hand_status"], "ok": ok, "ready": ready}


def _object(root: zarr.Group, job: ChunkJob):
    from handedit.sources import open_source_json

    if not (job.context.get("has_object") and job.context.get("source")):
        return None, None
    mesh = open_source_json(job.context["source"]).object_mesh()
    pose = read_chunk(root, Unit("ingest", job.unit.clip), ["object_pose"], job.start, job.stop)["object_pose"]
    return mesh, pose


def _output(res: SidesResult, inp: dict, method: str, extra: dict) -> StageOutput:
    reg_hs = inp["reg_hand_status"]
    own = np.where(inp["ready"], res.hand_status, Reason.UPSTREAM)
    hand_status = np.where(reg_hs == Reason.ABSENT, Reason.ABSENT, own).astype(np.int16)
    arrays = {"qpos": res.qpos, "root_pose": res.root_pose, "fingertip_error_mm": res.fingertip_error_mm,
              "wrist_error_mm": res.wrist_error_mm}
    return StageOutput(arrays, combine(per_frame(hand_status), inp["ok"]), method=method, hand_status=hand_status,
                       hand_details=res.details,
                       extra={"qc_contact_checked": res.contact_checked, "qc_notes": res.notes, **extra})


def body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    if job.context.get("track") == "hand_arm":
        return _hand_arm_body(root, job)
    inp = _inputs(root, job)
    mesh, pose = _object(root, job)
    sides = tuple(job.context["hands"])
    res = retarget_sides(inp["reg_keypoints"], inp["reg_keypoints_valid"], inp["ready"], sides, job.unit.embodiment,
                         RetargetConfig(**job.params), object_mesh=mesh, object_pose=pose)
    return _output(res, inp, "casadi:ipopt-hybrid", {})


def _hand_arm_body(root: zarr.Group, job: ChunkJob) -> StageOutput:
    """Hand-arm: one job covers the whole clip (the virtual base is fixed per sequence);
    the sequence-level record (all 27 candidate scores per side, the choice and its policy,
    the dual-arm pair) goes to provenance, the top candidates' previews to the store."""
    from handedit.retarget.preview import top_previews

    inp = _inputs(root, job, ("world_from_camera",))
    mesh, pose = _object(root, job)
    sides = tuple(job.context["hands"])
    # operators' choices from `handedit review`, per hand (read fresh: the cached root may predate them)
    reviews = open_store(job.store).get(job.unit.path).attrs.get("reviews") or {}
    choices = {s: reviews[s]["choice"] for s in sides if s in reviews}
    world = job.context.get("world")
    wfc = inp["world_from_camera"] if world else None
    intr = Intrinsics(**job.context["intrinsics"])
    res = retarget_hand_arm_sides(inp["reg_keypoints"], inp["reg_keypoints_valid"], inp["ready"], sides, job.unit.embodiment,
                                  RetargetConfig(**job.params), wfc, world, inp.get("reg_arm_keypoints"), inp.get("arm_valid"),
                                  choices, object_mesh=mesh, object_pose=pose, intr=intr)
    previews = {}
    for k, side in enumerate(sides):
        arm_res = res.arm_results.get(k)
        if arm_res is None:
            continue
        cands, frames, ego, third = top_previews(arm_res, preview_intrinsics(intr, side),
                                                 world_from_camera=None if wfc is None else _side_world(wfc, side),
                                                 up=None if world is None else np.asarray(world["up"], float))
        if side == "left":  # rendered in the mirrored view: flip back
            ego, third = ego[..., ::-1, :], third[..., ::-1, :]
        previews[side] = write_previews(root, job.unit, cands, frames, ego, third, side=side)
    return _output(res, inp, "casadi:ipopt-hybrid+virtual-base", {"virtual_base": res.virtual_base, "previews": previews})


def _side_world(wfc: np.ndarray, side: str) -> np.ndarray:
    from handedit.embodiments.mirror import mirror_world

    return mirror_world(wfc) if side == "left" else wfc


@task(**stage_options("retarget"))
def retarget(job: ChunkJob) -> dict:
    return execute(job, body)
