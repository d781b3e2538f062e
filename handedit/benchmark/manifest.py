"""The authors' evaluation-toolkit manifest: JSONL, one object per item, read and written
the way their toolkit (github.com/HandEdit/HandEdit, ``handedit_eval``) does.

Fields::

    id, replacement_scope, target_name, src_path, pred_path, gt_path, gt_mask_path,
    test_mask_path, human_mask_path, robot_mask_path, object_mask_path, bg_mask_path,
    urdf_ref_paths, urdf_mask_paths, dataset, task

Import follows the toolkit: only ``id`` and ``src_path`` (and the ``pred_path`` key, empty
before an editor ran) are required; every other field is optional. Scopes are spelled
``hand-only`` / ``hand-arm`` (also ``hand``, ``handonly``, ``handarm``, ``arm-hand``, ``_``
for ``-``) and stored here as ``hand`` / ``hand_arm``. Aliases: ``scope``, ``robot_name``,
``urdf_ref_path`` / ``urdf_mask_path`` (one path, a list, or a JSON-encoded list),
``pred_mask_path`` / ``test_mask_paths`` (``test_mask_path``), ``gt_mask_paths``,
``contact_mask_path`` (``object_mask_path``). Target names are canonicalised with the
toolkit's alias table (``inspire`` is RH56DFX) and mapped to a roster embodiment.

Semantics: ``gt_mask_path`` is the pseudo-GT robot mask; ``test_mask_path`` is the robot
mask of the *prediction* (the toolkit crops the prediction with it for CLIP and Lab, falling
back to ``gt_mask_path``, then the whole image), empty when the editor gave none; the
evaluation ROI is ``human_mask | robot_mask`` (the whole image without them).

Paths: the toolkit opens them as given (absolute, or relative to the working directory):
``relative_to="cwd"``; the project's own test sets write them relative to the manifest's
folder so that a benchmark folder can move: ``relative_to="manifest"``. Export writes the
toolkit's spellings, with absolute paths on request. Extra keys (``embodiment``,
``instruction``, ``description``, ``clip``, ``frame``) are handedit extensions that the
toolkit ignores.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

TOOLKIT_FIELDS = ("id", "replacement_scope", "target_name", "src_path", "pred_path", "gt_path", "gt_mask_path",
                  "test_mask_path", "human_mask_path", "robot_mask_path", "object_mask_path",
                  "urdf_ref_paths", "urdf_mask_paths")
REQUIRED = ("id", "src_path")  # and the pred_path key (empty until an editor ran)
PATH_FIELDS = ("src_path", "pred_path", "gt_path", "gt_mask_path", "test_mask_path", "human_mask_path",
               "robot_mask_path", "object_mask_path", "bg_mask_path")
SCOPES = ("hand", "hand_arm")
TOOLKIT_SCOPE = {"hand": "hand-only", "hand_arm": "hand-arm"}
# the toolkit's aliases -> this manifest's field (first one present wins)
ALIASES = {"replacement_scope": ("scope",), "target_name": ("robot_name",), "urdf_ref_paths": ("urdf_ref_path",),
           "urdf_mask_paths": ("urdf_mask_path",), "test_mask_path": ("pred_mask_path", "test_mask_paths"),
           "gt_mask_path": ("gt_mask_paths",), "object_mask_path": ("contact_mask_path",)}


def normalize_scope(text: str) -> str | None:
    """The toolkit's scope spellings -> ``hand`` | ``hand_arm`` (None when unknown)."""
    t = (text or "").lower().replace("_", "-").strip()
    if t in ("hand", "hand-only", "handonly"):
        return "hand"
    if t in ("hand-arm", "handarm", "arm-hand"):
        return "hand_arm"
    return None


def _path_list(value) -> list[str]:
    """One path, a list, or a JSON-encoded list -> a list (as the toolkit reads them)."""
    import json

    if value is None:
        return []
    if isinstance(value, (list, tuple)):
        return [str(v) for v in value if v]
    text = str(value).strip()
    if text.startswith("["):
        try:
            parsed = json.loads(text)
            if isinstance(parsed, list):
                return [str(v) for v in parsed if v]
        except ValueError:
            pass
    return [text] if text else []


class ManifestError(ValueError):
    """A manifest line that is not a valid item; the message names the line and field."""


@dataclass
class ManifestItem:
    id: str
    replacement_scope: str
    target_name: str
    src_path: str
    pred_path: str = ""
    gt_path: str = ""
    gt_mask_path: str = ""
    test_mask_path: str = ""
    human_mask_path: str = ""
    robot_mask_path: str = ""
    object_mask_path: str = ""
    urdf_ref_paths: list[str] = field(default_factory=list)
    urdf_mask_paths: list[str] = field(default_factory=list)
    extra: dict = field(default_factory=dict)

    @property
    def embodiment(self) -> str | None:
        return self.extra.get("embodiment")

    @property
    def instruction(self) -> str:
        return str(self.extra.get("instruction", ""))

    @property
    def bg_mask_path(self) -> str:
        return str(self.extra.get("bg_mask_path", "") or "")

    def to_record(self, base: Path | None = None, absolute: bool = False) -> dict:
        """The JSON object of one line in the toolkit's spellings; paths relative to ``base``
        when given, or absolute (``absolute``)."""
        rec = asdict(self)
        extra = rec.pop("extra")
        rec["replacement_scope"] = TOOLKIT_SCOPE.get(rec["replacement_scope"], rec["replacement_scope"])

        def fix(p: str) -> str:
            if absolute:
                return str(Path(p).absolute()) if p else ""
            return _rel(p, base) if base is not None else p

        for k in PATH_FIELDS:
            if k in rec:
                rec[k] = fix(rec[k])
        if extra.get("bg_mask_path"):
            extra = {**extra, "bg_mask_path": fix(extra["bg_mask_path"])}
        rec["urdf_ref_paths"] = [fix(p) for p in rec["urdf_ref_paths"]]
        rec["urdf_mask_paths"] = [fix(p) for p in rec["urdf_mask_paths"]]
        return {**extra, **rec}

    @classmethod
    def from_record(cls, obj: dict, base: Path | None = None, where: str = "") -> "ManifestItem":
        """One line (toolkit or handedit spelling); ``base``: the folder relative paths are
        resolved against (None: the working directory, as the toolkit does)."""
        from handedit.benchmark.targets import resolve_target

        obj = dict(obj)
        for name, aliases in ALIASES.items():
            if obj.get(name) in (None, "", []):
                for a in aliases:
                    if obj.get(a) not in (None, "", []):
                        obj[name] = obj[a]
                        break
        missing = [k for k in REQUIRED if not obj.get(k)] + ([] if "pred_path" in obj else ["pred_path"])
        if missing:
            raise ManifestError(f"{where}missing required field(s) {', '.join(missing)}")
        if not isinstance(obj["id"], str):
            raise ManifestError(f"{where}'id' must be a string")
        target = str(obj.get("target_name") or "")
        scope = normalize_scope(str(obj.get("replacement_scope") or ""))
        if obj.get("replacement_scope") and scope is None:
            raise ManifestError(f"{where}replacement_scope {obj['replacement_scope']!r} is not a scope: use hand-only "
                                f"or hand-arm")
        emb = resolve_target(target, scope)
        if scope is None:
            scope = emb.track if emb is not None else None
        if scope is None:
            raise ManifestError(f"{where}no replacement_scope, and target_name {target!r} does not name a roster "
                                f"embodiment to infer it from")
        for k in ("gt_mask_path", "test_mask_path"):
            if isinstance(obj.get(k), list):
                obj[k] = obj[k][0] if obj[k] else ""
        for k in PATH_FIELDS:
            v = obj.get(k)
            if v is None:
                obj[k] = ""
            elif not isinstance(v, str):
                raise ManifestError(f"{where}{k} must be a string path, got {type(v).__name__}")
        refs, masks = _path_list(obj.get("urdf_ref_paths")), _path_list(obj.get("urdf_mask_paths"))
        kw = {k: obj[k] for k in TOOLKIT_FIELDS if k in PATH_FIELDS}
        kw.update(id=obj["id"], replacement_scope=scope, target_name=target, urdf_ref_paths=refs, urdf_mask_paths=masks)
        if base is not None:
            for k in kw:
                if k in PATH_FIELDS:
                    kw[k] = _abs(kw[k], base)
            kw["urdf_ref_paths"] = [_abs(p, base) for p in refs]
            kw["urdf_mask_paths"] = [_abs(p, base) for p in masks]
        skip = set(TOOLKIT_FIELDS) | {a for al in ALIASES.values() for a in al}
        extra = {k: v for k, v in obj.items() if k not in skip}
        if extra.get("bg_mask_path") and base is not None:
            extra["bg_mask_path"] = _abs(extra["bg_mask_path"], base)
        if emb is not None:
            extra.setdefault("embodiment", emb.id)
        return cls(**kw, extra=extra)

    def missing_inputs(self) -> list[str]:
        """Optional inputs this item lacks (each disables only the metrics that need it)."""
        names = {"gt_path": "pseudo-GT", "human_mask_path": "human mask", "robot_mask_path": "robot mask",
                 "object_mask_path": "object mask"}
        out = [n for k, n in names.items() if not getattr(self, k)]
        return out + ([] if self.urdf_ref_paths else ["reference renders"])


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
