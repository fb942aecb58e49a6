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


def test_the_band_ends_at_the_near_objects_outline_in_the_view():
    """The pole's scanned surface is 8 px wide (columns 196–203), its outline in the view 36
    px (180–215: its unscanned sides); a new thin pole stands at 250–256, within the pole's
    100 px reach. With the view's edges the band keeps inside the outline (the blocks holding
    the outline's edges excepted) and leaves the thin pole and the wall beyond it; without,
    it covers them too."""
    depth = wall_with_a_pole()
    grey = np.full(depth.shape, 120, np.uint8)  # the wall
    grey[:, 180:216] = 60  # the near pole, both of its sides
    grey[:, 250:257] = 200  # a thin pole beside it
    reach_only = near_depth_hypothesis(depth, 1000.0, 0.2, 0.5)
    bounded = near_depth_hypothesis(depth, 1000.0, 0.2, 0.5, grey=grey, edge_threshold=100.0)
    inside = np.r_[184:196, 204:212]  # the outline's blocks without its edges (4 px blocks)
    beyond = np.r_[120:176, 220:300]
    assert np.all(reach_only[:, inside] == 2.0) and np.all(reach_only[:, beyond] == 2.0)
    assert np.all(bounded[:, inside] == 2.0)
    assert np.all(np.isnan(bounded[:, beyond]))  # the thin pole (250–256) among them
    assert np.all(np.isnan(bounded[:, 196:204]))  # the pole itself is still the near surface
    # no edge anywhere: the band is the reach
    flat = near_depth_hypothesis(
        depth, 1000.0, 0.2, 0.5, grey=np.full(depth.shape, 120, np.uint8), edge_threshold=100.0
    )
    np.testing.assert_array_equal(flat, reach_only)


def test_a_surface_left_out_of_bounded_keeps_its_whole_reach():
    """The ground's band (no unscanned side) is its reach whatever the view's edges: the pole
    of the test above, marked as such a surface, reaches past its outline."""
    depth = wall_with_a_pole()
    grey = np.full(depth.shape, 120, np.uint8)
    grey[:, 180:216] = 60
    grey[:, 250:257] = 200
    bounded = np.ones(depth.shape, bool)
    bounded[:, 196:204] = False  # the pole's surface pixels
    near = near_depth_hypothesis(
        depth, 1000.0, 0.2, 0.5, grey=grey, edge_threshold=100.0, bounded=bounded
    )
    np.testing.assert_array_equal(near, near_depth_hypothesis(depth, 1000.0, 0.2, 0.5))


def test_the_outline_needs_a_grey_image_of_the_depths_shape():
    import pytest

    with pytest.raises(ValueError, match="shape"):
        near_depth_hypothesis(
            wall_with_a_pole(),
            1000.0,
            0.2,
            0.5,
            grey=np.zeros((10, 10), np.uint8),
            edge_threshold=1,
        )
