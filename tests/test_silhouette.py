"""The near-depth hypothesis next to near objects (streetcd.detect.silhouette)."""

import numpy as np

from streetcd.detect.silhouette import WORK_STEP_PX, near_depth_hypothesis


def wall_with_a_pole(pole_depth: float = 2.0) -> np.ndarray:
    """(200, 400) depth: a wall at 10 m, a pole 8 px wide at columns 196–203, a hole at the
    left edge (no surface)."""
    depth = np.full((200, 400), 10.0, np.float32)
    depth[:, 196:204] = pole_depth
    depth[:, :20] = np.nan
    return depth


def test_the_wall_within_reach_of_a_near_pole_gets_the_poles_depth():
    depth = wall_with_a_pole()
    near = near_depth_hypothesis(depth, focal_px=1000.0, margin_m=0.2, min_gap_m=0.5)
    reach = 1000.0 * 0.2 / 2.0  # 100 px at 2 m
    cols = np.arange(400)
    distance = np.maximum(196 - cols, cols - 203)  # px from the pole's nearest column
    inside = (distance > 0) & (distance <= reach - WORK_STEP_PX)
    outside = distance > reach + 2 * WORK_STEP_PX
    assert np.all(near[:, inside] == 2.0)
    assert np.all(np.isnan(near[:, outside]))
    assert np.all(np.isnan(near[:, 196:204]))  # the pole itself is the near surface
    assert np.all(np.isnan(near[:, :20]))  # no surface: stays without


def test_a_far_object_reaches_less_and_a_small_depth_step_not_at_all():
    far = near_depth_hypothesis(wall_with_a_pole(8.0), 1000.0, 0.2, 0.5)
    covered = np.isfinite(far[100])
    assert 0 < covered.sum() <= 2 * (25 + 2 * WORK_STEP_PX)  # 25 px reach at 8 m
    step = near_depth_hypothesis(wall_with_a_pole(9.7), 1000.0, 0.2, 0.5)
    assert np.isnan(step).all()  # 0.3 m in front of the wall: the same surface


def test_a_flat_view_has_no_hypothesis():
    depth = np.full((64, 64), 5.0, np.float32)
    assert np.isnan(near_depth_hypothesis(depth, 500.0, 0.2, 0.5)).all()
    assert np.isnan(
        near_depth_hypothesis(np.full((8, 8), np.nan, np.float32), 500.0, 0.2, 0.5)
    ).all()
