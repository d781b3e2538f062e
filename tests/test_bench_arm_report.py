"""bench/egodex.py's hand-arm mask measures on a drawn forearm: the mask's half-width and how
far its edge lies from the colour edge beside it (the check behind reading a low 4 cm
coverage as a slim forearm rather than a sleeve left out)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest

from handedit.camera import Intrinsics

BENCH = Path(__file__).resolve().parents[1] / "bench" / "egodex.py"
INTR = Intrinsics(500.0, 500.0, 320.0, 240.0, 640, 480)  # 1 mm per pixel at 0.5 m


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_egodex", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _scene(half_px: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A beige table with a sleeve (a vertical bar, ``half_px`` to each side of u = 320) from
    the wrist down out of the view; the wrist and elbow 0.5 m from the camera."""
    img = np.full((480, 640, 3), (200, 165, 110), np.uint8)
    img[300:, 320 - half_px:320 + half_px + 1] = (60, 110, 70)  # a green jacket's sleeve
    img[300:, 296:305] = (25, 50, 30)  # a dark fold 1.5-2.4 cm left of the axis: edges inside the sleeve
    lab = cv2.cvtColor(cv2.GaussianBlur(img, (5, 5), 0), cv2.COLOR_RGB2LAB).astype(np.float32)
    wrist, elbow = np.array([0.0, 0.08, 0.5]), np.array([0.0, 0.38, 0.5])  # the forearm runs down the image
    mask = np.zeros((480, 640), bool)
    mask[300:, 320 - half_px:320 + half_px + 1] = True
    return lab, mask, wrist, elbow


def test_a_mask_that_follows_the_sleeve_sits_on_its_colour_edge(bench):
    lab, mask, wrist, elbow = _scene(40)
    rows = bench.half_widths(mask, wrist, elbow, INTR, lab)
    assert len(rows) == len(bench.HALF_WIDTH_AT_M)
    for half, offset, gap in rows:
        assert half == pytest.approx(0.040, abs=0.002) and offset == pytest.approx(0.0, abs=0.002)
        assert gap < 0.003  # the fold's edges are not taken for the arm's


def test_a_mask_on_the_skin_alone_lies_off_the_sleeves_edge(bench):
    lab, _, wrist, elbow = _scene(40)
    narrow = np.zeros((480, 640), bool)
    narrow[300:, 300:341] = True  # 2 cm to each side: the sleeve's outer 2 cm left out
    rows = bench.half_widths(narrow, wrist, elbow, INTR, lab)
    assert rows and all(gap == pytest.approx(0.020, abs=0.003) for _, _, gap in rows)
    assert all(np.isnan(gap) for _, _, gap in bench.half_widths(narrow, wrist, elbow, INTR))  # no frame: not measured
