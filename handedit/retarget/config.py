"""Retargeting configuration (hashable: it keys the per-process solver cache)."""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field

from handedit.vision.arm import MAX_OFF_ARM

SEARCH_HAND_HIDDEN = 0.25  # composite's MAX_HAND_HIDDEN (0.2) as the search's keypoint-hull estimate reads it


class VirtualBaseConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")
    VERSION: ClassVar[int] = 11  # 3: head-torso keep-out, critical tolerance, refinement grid, plausibility ranking;
    # 4: the footprint is the links' visual hulls, and frames composite would drop as off-arm count against a base;
    # 5: candidates discarded for body collisions alone are a last resort (their frames fail, not the sequence);
    # 6: a candidate's first frame tries Newton from its neighbour's solution before any cold IPOPT;
    # 7: the hand's own wrist joints (Shadow, ORCA) are arm joints of the IK (``arm.ArmModel``); the dual-arm
    # check tries the best dual_arm_candidates of each side, not 3; a candidate past its critical tolerance is not
    # solved further (its remaining frames read NO_VALID_BASE); previews are rendered when asked for (``previews``);
    # 8: frames where the robot's own arm would hide its hand (composite's HAND_HIDDEN) count against a base too;
    # the second grid is searched when the best of the 27 lies off the human arm, not only when none survives;
    # 9: a wrist flip (a joint step past max_joint_step) rejects the frames outside the longest run, not the base;
    # 10: a first frame no seed reaches tries no body seeds and hints no neighbour;
    # 11: a yawed candidate on its yaw mate's branch is the mate's track, first joint turned back (``share_yaw``)

    init_back: float = Field(0.55, description="base distance behind the wrist centre, in L_r")
    init_up: float = Field(0.10, description="base height above the wrist centre, in L_r")
    init_shoulder_drop: float = Field(0.25, description="with shoulder keypoints: the arm's first joint this far below the "
                                      "human shoulder, in L_r (a robot shoulder at head height would fill the view)")
    virtual_shoulder_drop_m: float = Field(0.20, ge=0, description="sources without shoulder keypoints: the operator's "
                                           "shoulders this far below the head camera")
    virtual_shoulder_back_m: float = Field(0.05, ge=0, description="and this far behind it (horizontally)")
    virtual_shoulder_half_width_m: float = Field(0.18, ge=0, description="and this far to each side")
    body_radius_m: float = Field(0.08, ge=0, description="the operator's head and torso: a capsule of this radius (m) that no "
                                 "arm link may enter (0: no check)")
    head_back_m: float = Field(0.08, ge=0, description="the head's centre: this far behind the head camera (horizontally)")
    torso_length_m: float = Field(0.60, ge=0, description="the body axis runs this far down from the head along world up")
    torso_back_m: float = Field(0.15, ge=0, description="and its lower end this much further back (the chest stays behind "
                                "the eyes of someone looking down at a table)")
    pos_tol_mm: float = Field(10.0, gt=0, description="IK position error above which a frame is infeasible")
    rot_tol_deg: float = Field(5.0, gt=0)
    link_radius: float = Field(0.035, gt=0, description="capsule radius of arm links (m)")
    plane_margin: float = Field(0.005, ge=0, description="clearance required above the support plane (m)")
    max_joint_step: float = Field(0.5, gt=0, description="largest joint change between frames (rad) before a discontinuity")
    joint_limit_tol: float = Field(1e-6, ge=0)
    smooth: float = Field(1e-2, ge=0)
    n_seeds: int = Field(6, ge=1, description="IK restarts on the first frame of a candidate")
    share_yaw: bool = Field(True, description="a candidate that differs from the one before it by the base's yaw alone, "
                            "and whose first frame lands on that one's branch, takes that one's joint track with the first "
                            "joint turned back by the yaw (every link where it was) instead of solving the rest (six-joint arms "
                            "whose first joint turns about the base's z axis, while that joint stays in its range)")
    critical_tolerance: float = Field(0.02, ge=0, le=1, description="share of a sequence's critical frames a candidate may "
                                      "fail (those frames are rejected on their own) before it is discarded")
    min_reachability: float = Field(0.5, ge=0, le=1, description="a candidate that keeps fewer of the sequence's valid frames "
                                    "than this (body collisions, failures off the critical frames) is discarded; when only "
                                    "body collisions discard every candidate of both grids, those are kept as a last resort")
    refine_reach_frac: float = Field(0.65, gt=0, le=1, description="when none of the 27 survive: a second grid whose centre puts "
                                     "the wrist targets this share of L_r from the arm's first joint")
    refine_off_corridor: float = Field(0.15, ge=0, le=1, description="the second grid is searched too when the best of the "
                                       "27 has more than this share of its footprint outside the human arm's corridor")
    refine_forearm_deg: float = Field(30.0, ge=0, le=180, description="or its forearm more than this many degrees off the "
                                      "human forearm")
    plausibility_frames: int = Field(8, ge=0, description="frames per candidate on which the footprint and forearm measures "
                                     "are taken (0: plausibility not ranked)")
    max_off_arm: float = Field(MAX_OFF_ARM, ge=0, le=1, description="a sampled frame whose footprint lies more than this share "
                               "outside the human arm's corridor counts as lost, as composite's OFF_ARM screen "
                               "(its max_off_arm) would drop it")
    max_hand_hidden: float = Field(SEARCH_HAND_HIDDEN, ge=0, le=1, description="a sampled frame where the robot's own arm "
                                   "covers more than this share of the human hand's keypoint hull counts as lost, as "
                                   "composite's HAND_HIDDEN screen would drop it (the hull is smaller than the hand's "
                                   "mask: 0.25 here reads as composite's 0.2)")
    body_seeds: int = Field(10, ge=0, description="first frame: random IK restarts added when no seed's arm keeps clear of "
                            "the operator's body (and some seed reached the target)")
    review: Literal["auto_top1", "manual"] = "auto_top1"
    top_k: int = Field(3, ge=1)
    dual_arm_candidates: int = Field(9, ge=1, description="the dual-arm check tries pairs of each side's best this many "
                                     "bases (a lower-ranked one is taken only where the better ones collide)")
    replay_frames: int = Field(24, ge=3, description="review: manual: frames of each top candidate's replay preview, evenly "
                               "spaced over the sequence (auto_top1 keeps stills of the first, middle and last frame)")
    previews: bool | None = Field(None, description="store the top candidates' previews for `handedit review --previews` "
                                  "(None: under review: manual only, where a person chooses from them; rendering them "
                                  "was a third of a hand-arm's retarget time on EgoDex's 32-frame windows)")

    def wants_previews(self) -> bool:
        return self.review == "manual" if self.previews is None else self.previews

    def preview_frames(self) -> int:
        """Frames stored per top candidate for review: a short replay where a person will choose."""
        return self.replay_frames if self.review == "manual" else 3


class RetargetConfig(BaseModel):
    """Weights of the position-retargeting objective and QC thresholds.

    Position residuals enter the cost in centimetres (so weights are O(1) and IPOPT's
    tolerances are meaningful); ``smooth_q`` is per rad^2 of joint change, ``smooth_t`` per
    cm^2 of root translation change and ``smooth_r`` per rad^2 of root rotation change
    (as |R - R_prev|_F^2 / 2), all relative to the previous solved frame.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")
    VERSION: ClassVar[int] = 5  # 3: projected Newton per frame (IPOPT where it does not converge); 4: cold frames too, after a barrier path;
    # 5: contact terms in the solve where the source has an object mesh and pose

    wrist_weight: float = Field(1.0, ge=0)
    fingertip_weight: float = Field(1.0, ge=0)
    mcp_weight: float = Field(0.5, ge=0)
    pip_weight: float = Field(0.25, ge=0)
    dip_weight: float = Field(0.25, ge=0)
    cmc_weight: float = Field(0.0, ge=0)
    smooth_q: float = Field(0.05, ge=0)
    smooth_t: float = Field(0.05, ge=0)
    smooth_r: float = Field(0.5, ge=0)
    reg_q: float = Field(1e-4, ge=0)  # pull towards the neutral pose: resolves redundant joints
    max_iter: int = Field(100, ge=1)
    tol: float = Field(1e-6, gt=0)
    method: Literal["newton", "ipopt"] = Field(
        "newton", description="per-frame solver: projected Newton on the exact casadi Hessian (IPOPT from its point where "
        "it does not converge; cold frames after a log-barrier path), or IPOPT alone")
    hybrid: bool = True  # vector-mode coarse alignment before the position solve on cold frames
    warm_start: bool = True  # primal + multipliers from the previous frame of the chunk
    fingertip_reject_mm: float = Field(50.0, gt=0)
    wrist_reject_mm: float = Field(50.0, gt=0)
    # contact QC (handedit.retarget.qc), applied where the source has an object mesh + pose
    contact_mm: float = Field(10.0, gt=0)
    contact_distance_mm: float = Field(20.0, gt=0)
    penetration_mm: float = Field(10.0, gt=0)
    # contact terms in the solve (handedit.retarget.contact), where the source has an object mesh + pose
    contact: bool = Field(True, description="keep the human's fingertip contacts and push links out of the object in the "
                          "solve (False: positions only, the QC alone judges contact)")
    contact_weight: float = Field(10.0, ge=0, description="per cm^2 of a touching tip's distance off its tangent plane")
    push_weight: float = Field(50.0, ge=0, description="per cm^2 of a link's deepest sample inside its tangent plane")
    push_depth_mm: float = Field(5.0, ge=0, description="a link deeper than this inside the object is pushed back to 1 mm "
                                 "less (the QC rejects beyond penetration_mm; a full push-out moves the whole hand, "
                                 "and its wrist error past wrist_reject_mm)")
    contact_rounds: int = Field(2, ge=0, description="re-solves of a frame with push-out planes added")
    # hand-arm embodiments: the sequence-level virtual-base search and its review policy
    virtual_base: VirtualBaseConfig = Field(default_factory=VirtualBaseConfig)

    def weight(self, kind: str) -> float:
        return float(getattr(self, f"{'fingertip' if kind == 'tip' else kind}_weight"))
