"""Where a changed region stands (streetcd.detect.locate): the scene of tests/test_sweep.py,
a textured plate 5 m in front of a textured wall 10 m away, seen by a view and two
neighbours 1 m to each side; the old surface is the wall."""

from __future__ import annotations

import numpy as np
from test_sweep import HALF, INTR, PLATE_Z, WALL_Z, _pose, _render

from streetcd.config import LocateParams
from streetcd.detect.locate import region_depth_fractions, working_set

ARGS = dict(min_gain=0.03, min_pixels=20, max_samples=1500, occlusion_tolerance_m=0.3)
FRACTIONS = LocateParams().fractions()


def _labels() -> np.ndarray:
    """Region 1: the plate (rows/cols 45-75 / 65-95, 2 px inside its edge); region 2: a
    patch of the wall beside it; region 3: three pixels of the wall."""
    half_px = int(INTR.fx * HALF / PLATE_Z)
    labels = np.zeros((INTR.height, INTR.width), np.int32)
    labels[60 - half_px + 2 : 60 + half_px - 2, 80 - half_px + 2 : 80 + half_px - 2] = 1
    labels[40:80, 5:30] = 2
    labels[100, 130:133] = 3
    return labels


def _fractions(plate: bool = True, neighbours_at=(-1.0, 1.0), **kw) -> np.ndarray:
    depth = np.full((INTR.height, INTR.width), WALL_Z, np.float32)
    nbs = [(_render(x, plate), depth, INTR, _pose(x), None) for x in neighbours_at]
    working = working_set(
        _render(0.0, plate), depth, INTR, nbs, window_px=3, scale=1.0, max_work_px=4000
    )
    if working is None:
        return np.full(3, np.nan)
    args = {**ARGS, "fractions": FRACTIONS, **kw}
    return region_depth_fractions(working, _labels(), 3, _pose(0.0), **args)


def test_an_added_plate_stands_where_it_is_and_the_wall_on_the_wall():
    f = _fractions()
    assert abs(f[0] - PLATE_Z / WALL_Z) < 0.03  # 5 m of the wall's 10 m
    assert np.isnan(f[1])  # the old surface explains the wall best: no depth in front
    assert np.isnan(f[2])  # fewer pixels than min_pixels


def test_one_neighbour_is_enough_and_none_gives_nothing():
    assert abs(_fractions(neighbours_at=(1.0,))[0] - 0.5) < 0.03
    depth = np.full((INTR.height, INTR.width), WALL_Z, np.float32)
    assert (
        working_set(_render(0.0, True), depth, INTR, [], window_px=3, scale=1.0, max_work_px=99)
        is None
    )


def test_at_a_quarter_of_the_resolution_the_plate_stands_where_it_is():
    depth = np.full((INTR.height, INTR.width), WALL_Z, np.float32)
    nbs = [(_render(x, True), depth, INTR, _pose(x), None) for x in (-1.0, 1.0)]
    working = working_set(
        _render(0.0, True), depth, INTR, nbs, window_px=3, scale=0.25, max_work_px=4000
    )
    assert working is not None and working.view.shape == (30, 40, 3)
    f = region_depth_fractions(
        working, _labels(), 3, _pose(0.0), fractions=FRACTIONS, **{**ARGS, "min_pixels": 5}
    )
    assert abs(f[0] - 0.5) < 0.05 and np.isnan(f[1])


def test_a_gain_too_small_gives_no_depth():
    assert np.isnan(_fractions(min_gain=2.0)).all()  # colour distances are at most 1


def test_the_fractions_tried_end_at_the_old_surface():
    fr = LocateParams(min_fraction=0.2, steps=5).fractions()
    assert np.allclose(fr, [0.2, 0.4, 0.6, 0.8, 1.0]) and fr[-1] == 1.0
