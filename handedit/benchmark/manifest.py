"""The authors' evaluation-toolkit manifest: JSONL, one object per item.

Toolkit fields (all required on import; ``pred_path`` may be empty before an editor ran)::

    id, replacement_scope, target_name, src_path, pred_path, gt_path, gt_mask_path,
    test_mask_path, human_mask_path, robot_mask_path, object_mask_path,
    urdf_ref_paths, urdf_mask_paths

Conventions: ``replacement_scope`` is ``hand`` or ``hand_arm``; ``gt_mask_path`` is the
pseudo-GT robot foreground (= ``robot_mask_path``, M_r); ``test_mask_path`` is the
evaluation ROI M = M_h | M_r; ``object_mask_path`` may be empty (no object). Paths are
written relative to the manifest's folder and resolved against it on import (absolute
paths are kept). Extra keys (``embodiment``, ``instruction``, ``description``, ``clip``,
``frame``) are handedit extensions that the toolkit ignores.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

TOOLKIT_FIELDS = ("id", "replacement_scope", "target_name", "src_path", "pred_path", "gt_path", "gt_mask_path",
                  "test_mask_path", "human_mask_path", "robot_mask_path", "object_mask_path",
                  "urdf_ref_paths", "urdf_mask_paths")
PATH_FIELDS = ("src_path", "pred_path", "gt_path", "gt_mask_path", "test_mask_path", "human_mask_path",
               "robot_mask_path", "object_mask_path")
SCOPES = ("hand", "hand_arm")


class ManifestError(ValueError):
    """A manifest line that is not a valid item; the message names the line and field."""


@dataclass
class ManifestItem:
    id: str
    replacement_scope: str
    target_name: str
    src_path: str
    pred_path: str
    gt_path: str
    gt_mask_path: str
    test_mask_path: str
    human_mask_path: str
    robot_mask_path: str
    object_mask_path: str
    urdf_ref_paths: list[str] = field(default_factory=list)
    urdf_mask_paths: list[str] = field(default_factory=list)
    extra: dict = field(default_factory=dict)

    @property
    def embodiment(self) -> str | None:
        return self.extra.get("embodiment")

    @property
    def instruction(self) -> str:
        return str(self.extra.get("instruction", ""))

    def to_record(self, base: Path | None = None) -> dict:
        """The JSON object of one line, paths relative to ``base`` when given."""
        rec = asdict(self)
        extra = rec.pop("extra")
        if base is not None:
            for k in PATH_FIELDS:
                rec[k] = _rel(rec[k], base)
            rec["urdf_ref_paths"] = [_rel(p, base) for p in rec["urdf_ref_paths"]]
            rec["urdf_mask_paths"] = [_rel(p, base) for p in rec["urdf_mask_paths"]]
        return {**extra, **rec}

    @classmethod
    def from_record(cls, obj: dict, base: Path | None = None, where: str = "") -> "ManifestItem":
        missing = [k for k in TOOLKIT_FIELDS if k not in obj]
        if missing:
            raise ManifestError(f"{where}missing field(s) {', '.join(missing)}")
        if not isinstance(obj["id"], str) or not obj["id"]:
            raise ManifestError(f"{where}'id' must be a non-empty string")
        if obj["replacement_scope"] not in SCOPES:
            raise ManifestError(f"{where}replacement_scope must be one of {SCOPES}, got {obj['replacement_scope']!r}")
        for k in PATH_FIELDS:
            if obj[k] is None:
                obj[k] = ""
            if not isinstance(obj[k], str):
                raise ManifestError(f"{where}{k} must be a string path, got {type(obj[k]).__name__}")
        for k in ("urdf_ref_paths", "urdf_mask_paths"):
            if not isinstance(obj[k], list) or not all(isinstance(p, str) for p in obj[k]):
                raise ManifestError(f"{where}{k} must be a list of paths")
        if len(obj["urdf_ref_paths"]) != len(obj["urdf_mask_paths"]):
            raise ManifestError(f"{where}urdf_ref_paths and urdf_mask_paths differ in length")
        kw = {k: obj[k] for k in TOOLKIT_FIELDS}
        if base is not None:
            for k in PATH_FIELDS:
                kw[k] = _abs(kw[k], base)
            kw["urdf_ref_paths"] = [_abs(p, base) for p in kw["urdf_ref_paths"]]
            kw["urdf_mask_paths"] = [_abs(p, base) for p in kw["urdf_mask_paths"]]
        extra = {k: v for k, v in obj.items() if k not in TOOLKIT_FIELDS}
        return cls(**kw, extra=extra)


def _rel(p: str, base: Path) -> str:
    if not p:
        return ""
    try:
        return os.path.relpath(p, base)
    except ValueError:
        return str(p)


def _abs(p: str, base: Path) -> str:
    if not p:
        return ""
    q = Path(p)
    return str(q if q.is_absolute() else (base / q))
