"""A contact sheet of a curated store: source | masks | restored background | pseudo-GT.

    .venv/bin/python bench/figure.py STORE_DIR [--embodiment allegro] [--per-clip 2] --out sheet.png

Left hands' masks are blue, right hands' red; kept frames only. The masks and background are
those of the embodiment's track (hand, or hand-arm: the whole arm removed). Used for the README's
synthetic-clip figure and by ``bench/egodex.py --figure`` (a figure of EgoDex frames is
made at run time only: the EgoDex licence, CC BY-NC-ND, does not allow committing it).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def contact_sheet(root, clips: list[str], emb: str, out: Path, per_clip: int = 2, width: int = 2400) -> Path | None:
    import cv2
    import numpy as np

    from handedit.embodiments.roster import get_embodiment
    from handedit.reasons import Reason
    from handedit.storage import Unit
    from handedit.storage.layout import SCOPE_MASK

    scope = get_embodiment(emb).track  # the masks and background this embodiment's composites used
    rows = []
    for clip in clips:
        kept = np.flatnonzero(root[Unit("qc", clip, embodiment=emb).path]["status"][:] == Reason.OK)
        for t in kept[np.linspace(0, len(kept) - 1, min(per_clip, len(kept))).astype(int)] if len(kept) else []:
            f = root[Unit("ingest", clip).path]["frames"][t]
            hands = root[Unit("ingest", clip).path].attrs.get("hands") or ["right"]
            masks = f.astype(np.float32)
            seg = root[Unit("segment", clip).path][SCOPE_MASK[scope]][t]
            for k, side in enumerate(hands):
                col = np.array((40, 80, 255) if side == "left" else (255, 60, 40))
                masks[seg[k]] = 0.5 * masks[seg[k]] + 0.5 * col
            bg = root[Unit("restore_background", clip, scope=scope).path]["background"][t]
            gt = root[Unit("harmonize", clip, embodiment=emb).path]["image"][t]
            rows.append(np.hstack([f, masks.astype(np.uint8), bg, gt]))
    if not rows:
        return None
    grid = np.vstack(rows)
    s = min(1.0, width / grid.shape[1])
    grid = cv2.resize(grid, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store")
    ap.add_argument("--embodiment", default="allegro")
    ap.add_argument("--per-clip", type=int, default=2)
    ap.add_argument("--width", type=int, default=2400)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    from handedit.storage import open_store
    from handedit.storage.summary import curated_clips

    root = open_store(args.store)
    path = contact_sheet(root, curated_clips(root), args.embodiment, Path(args.out), args.per_clip, args.width)
    print(f"wrote {path}" if path else "no kept frame to show")


if __name__ == "__main__":
    main()
