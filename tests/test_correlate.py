"""Re-projection and raw change (eq. 4–5) on a textured wall seen by cameras side by side.

The wall y = 10 m is perpendicular to every camera's axis, so each camera's depth raster is
exactly 10 m everywhere: the tests feed exact geometry and check the correlation alone.
"""

import cv2
import numpy as np
import pytest

from streetcd import classes
from streetcd.config import CorrelateParams
from streetcd.detect.correlate import (
    Neighbour,
    camera_rays,
    hole_depths,
    occluder_depth,
    pair_lut,
    raw_change,
    registration_radius_px,
    reproject,
    robust_line,
    stretch_histogram,
    stretch_lut,
)
from streetcd.geometry.camera import backproject, look_at, pixel_grid, pixel_rays, project
from streetcd.types import Intrinsics

INTR = Intrinsics(160, 120, 140.0, 140.0, 79.5, 59.5)
WALL_Y = 10.0


def wall_pose(x: float):
    return look_at([x, 0.0, 1.5], [x, WALL_Y, 1.5])


def wall_texture(points: np.ndarray) -> np.ndarray:
    """(N, 3) world points on the wall → (N, 3) float colours in [40, 200]: random 0.5 m
    panels (7 px here, so most pixels are not on a panel edge)."""
    ix = np.floor(points[:, [0, 2]] / 0.5).astype(np.int64)
    h = ((ix[:, 0] * 73856093) ^ (ix[:, 1] * 19349663)) * 2654435761 & 0xFFFFFFFF
    rgb = np.column_stack([h & 255, (h >> 8) & 255, (h >> 16) & 255])
    return 40.0 + rgb * (160.0 / 255.0)


def render_wall(pose, intr=INTR) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) uint8 image and (H, W) float32 depth of the wall (exact: depth = 10 m).

    Rendered at 3× and area-averaged, as a camera integrates over its pixels: point-sampled
    panel edges would alias, and resampling them would show as change.
    """
    fine = intr.scaled(3.0)
    rays = pixel_rays(pixel_grid(fine.height, fine.width), fine) @ pose.R
    t = (WALL_Y - pose.center[1]) / rays[:, 1]
    points = pose.center + rays * t[:, None]
    image = wall_texture(points).reshape(fine.height, fine.width, 3).astype(np.float32)
    image = cv2.resize(image, (intr.width, intr.height), interpolation=cv2.INTER_AREA)
    depth = np.full((intr.height, intr.width), WALL_Y, dtype=np.float32)
    return image.round().astype(np.uint8), depth


def neighbour(x: float, gain: float = 1.0) -> Neighbour:
    image, depth = render_wall(wall_pose(x))
    image = np.clip(image * gain, 0, 255).astype(np.uint8)
    return Neighbour(stretch_histogram(image), depth, INTR, wall_pose(x))


def test_stretch_cancels_per_channel_gain_and_offset():
    rng = np.random.default_rng(0)
    image = rng.integers(40, 180, size=(60, 80, 3)).astype(np.uint8)
    other = np.clip(image * np.array([0.8, 1.1, 0.9]) + np.array([10, -20, 5]), 0, 255)
    a = stretch_histogram(image, (1, 99))
    b = stretch_histogram(other.round().astype(np.uint8), (1, 99))
    assert a.dtype == np.float32 and a.min() >= 0 and a.max() <= 255
    assert np.abs(a - b).max() < 3.5  # rounding of the gained uint8 image, ≤ 1 level × gain


def test_camera_rays_with_distortion_match_exact_back_projection():
    # interpolation error in pixels grows as step² / f: check at a street camera's f
    intr = Intrinsics(1203, 301, 1000.0, 990.0, 600.3, 150.2, (-0.2, 0.05, 0.001, -0.002, 0.0))
    rays = camera_rays(intr)
    exact = pixel_rays(pixel_grid(intr.height, intr.width), intr)[:, :2]
    assert rays.shape == (301, 1203, 2) and rays.dtype == np.float32
    assert np.abs(rays.reshape(-1, 2) - exact).max() * intr.fx < 0.02  # pixels


def test_reproject_equals_project_of_back_projected_points():
    pose_p, pose_q = wall_pose(0.0), wall_pose(0.7)
    depth = np.random.default_rng(1).uniform(4, 20, (INTR.height, INTR.width)).astype(np.float32)
    depth[5, 7] = np.nan
    mu, mv, zq = reproject(depth, camera_rays(INTR), pose_p, INTR, pose_q)
    pts = backproject(pixel_grid(INTR.height, INTR.width), depth.ravel(), INTR, pose_p)
    uv, z = project(pts, INTR, pose_q)
    ok = np.isfinite(z)
    assert np.allclose(mu.ravel()[ok], uv[ok, 0], atol=2e-3)
    assert np.allclose(mv.ravel()[ok], uv[ok, 1], atol=2e-3)
    assert np.allclose(zq.ravel()[ok], z[ok], rtol=1e-5)
    assert np.isnan(mu[5, 7]) and np.isnan(zq[5, 7])


def test_no_change_gives_almost_no_raw_change_even_with_exposure_difference():
    image, depth = render_wall(wall_pose(0.0))
    cls = np.full(depth.shape, classes.BUILDING, np.uint8)
    nbs = [neighbour(-0.6, gain=0.7), neighbour(0.6, gain=1.2)]
    change, support = raw_change(stretch_histogram(image), depth, cls, INTR, wall_pose(0.0), nbs)
    assert change.dtype == np.float32 and change.shape == depth.shape
    assert (support == 2).mean() > 0.85  # the rest lies outside one neighbour's image
    # only panel edges (bilinear resampling of a hard edge) differ; the S-curve midpoint is 0.24
    assert np.mean(change > 0.24) < 0.02
    assert np.median(change[support > 0]) < 0.02


def test_new_object_in_the_image_gives_raw_change_there():
    image, depth = render_wall(wall_pose(0.0))
    image[40:80, 60:100] = [200, 40, 200]  # a board not in the cloud (nor in q's image)
    cls = np.full(depth.shape, classes.BUILDING, np.uint8)
    change, _ = raw_change(
        stretch_histogram(image),
        depth,
        cls,
        INTR,
        wall_pose(0.0),
        [neighbour(-0.6), neighbour(0.6)],
    )
    assert np.mean(change[42:78, 62:98] > 0.24) > 0.9
    outside = np.ones(depth.shape, bool)
    outside[38:82, 58:102] = False
    assert np.mean(change[outside] > 0.24) < 0.02


def test_minimum_over_neighbours_needs_every_neighbour_to_disagree():
    """Eq. 5: a difference that only one neighbour shows is not a change."""
    image, depth = render_wall(wall_pose(0.0))
    cls = np.full(depth.shape, classes.BUILDING, np.uint8)
    stretched = stretch_histogram(image)
    good, bad = neighbour(-0.6), neighbour(0.6)
    spoiled = Neighbour(255 - bad.image, bad.depth, INTR, bad.pose)  # disagrees everywhere

    def change_with(*nbs):
        return raw_change(stretched, depth, cls, INTR, wall_pose(0.0), list(nbs))

    c_good, s_good = change_with(good)
    c_bad, s_bad = change_with(spoiled)
    c_both, s_both = change_with(spoiled, good)
    both = (s_good == 1) & (s_bad == 1)
    assert np.array_equal(s_both, s_good + s_bad)
    assert np.array_equal(c_both[both], np.minimum(c_good, c_bad)[both])
    assert np.median(c_bad[both]) > 0.5 and np.median(c_both[both]) < 0.02


def test_the_registration_radius_scales_with_the_width_and_its_floor_holds_it_up():
    default = CorrelateParams()
    assert [registration_radius_px(w, default) for w in (320, 1280, 1920, 4000)] == [0, 1, 2, 4]
    floored = CorrelateParams(registration_floor_px=2.0)
    assert [registration_radius_px(w, floored) for w in (320, 1280, 1920, 4000)] == [2, 2, 2, 4]
    # no tolerance at all stays none, floor or not: the paper's pixel difference
    off = CorrelateParams(registration_tolerance_px=0.0, registration_floor_px=2.0)
    assert registration_radius_px(1280, off) == 0


def test_second_smallest_needs_two_of_three_neighbours_to_agree():
    """Our addition: where three neighbours see a pixel, one that matches by chance does not
    decide alone (the second-smallest difference counts); where two see it, the minimum."""
    image, depth = render_wall(wall_pose(0.0))
    cls = np.full(depth.shape, classes.BUILDING, np.uint8)
    stretched = stretch_histogram(image)
    good, bad, worse = neighbour(-0.6), neighbour(0.6), neighbour(0.3)
    spoiled = Neighbour(255 - bad.image, bad.depth, INTR, bad.pose)
    spoiled2 = Neighbour(255 - worse.image, worse.depth, INTR, worse.pose)
    second = CorrelateParams(second_smallest=True)
    paper = CorrelateParams(second_smallest=False)

    def change_with(params, *nbs):
        return raw_change(stretched, depth, cls, INTR, wall_pose(0.0), list(nbs), params)

    c_one, s_one = change_with(second, spoiled)
    c_two, s_two = change_with(second, spoiled2)
    c_min, s_min = change_with(paper, good, spoiled, spoiled2)
    c_2nd, s_2nd = change_with(second, good, spoiled, spoiled2)
    assert np.array_equal(s_min, s_2nd)
    three = s_2nd == 3
    assert three.mean() > 0.7
    # two neighbours disagree, one matches: the paper's minimum sees nothing, ours a change
    assert np.median(c_min[three]) < 0.02
    assert np.array_equal(c_2nd[three], np.minimum(c_one, c_two)[three])
    assert np.median(c_2nd[three]) > 0.5
    # only two see the pixel: the minimum, as eq. 5
    two = s_2nd == 2
    assert two.any() and np.array_equal(c_2nd[two], c_min[two])
    # one neighbour that disagrees among three is no change either way
    c_one_bad, _ = change_with(second, good, neighbour(0.3), spoiled)
    assert np.median(c_one_bad[three]) < 0.02


def test_occluded_pixels_give_no_evidence():
    image, depth = render_wall(wall_pose(0.0))
    cls = np.full(depth.shape, classes.BUILDING, np.uint8)
    nb = neighbour(0.6)
    q_depth = nb.depth.copy()
    q_depth[:, :80] = 3.0  # q sees something 7 m closer over its left half
    inverted = 255 - nb.image  # and would disagree everywhere
    change, support = raw_change(
        stretch_histogram(image),
        depth,
        cls,
        INTR,
        wall_pose(0.0),
        [Neighbour(inverted, q_depth, INTR, nb.pose)],
    )
    mu, _, _ = reproject(depth, camera_rays(INTR), wall_pose(0.0), INTR, nb.pose)
    hidden = np.round(mu) < 80
    assert np.all(support[hidden] == 0) and np.all(change[hidden] == 0)
    assert np.mean(change[~hidden & (support == 1)] > 0.24) > 0.5


def test_pixels_without_surface_or_neighbours_get_zero():
    image, depth = render_wall(wall_pose(0.0))
    depth[:20] = np.nan
    cls = np.full(depth.shape, classes.BUILDING, np.uint8)
    inverted = neighbour(0.6)
    inverted = Neighbour(255 - inverted.image, inverted.depth, INTR, inverted.pose)
    change, support = raw_change(
        stretch_histogram(image), depth, cls, INTR, wall_pose(0.0), [inverted]
    )
    assert np.all(change[:20] == 0) and np.all(support[:20] == 0)
    change, support = raw_change(stretch_histogram(image), depth, cls, INTR, wall_pose(0.0), [])
    assert not change.any() and not support.any()


@pytest.mark.parametrize("weight", [0.0, 0.2, 1.0])
def test_tree_and_road_pixels_are_down_weighted(weight):
    image, depth = render_wall(wall_pose(0.0))
    cls = np.full(depth.shape, classes.BUILDING, np.uint8)
    cls[:, :40] = classes.VEGETATION
    cls[:, 40:60] = classes.ROAD
    inverted = neighbour(0.0)
    inverted = Neighbour(255 - inverted.image, inverted.depth, INTR, inverted.pose)
    params = CorrelateParams(low_class_weight=weight)
    change, _ = raw_change(
        stretch_histogram(image), depth, cls, INTR, wall_pose(0.0), [inverted], params
    )
    full, _ = raw_change(
        stretch_histogram(image),
        depth,
        cls,
        INTR,
        wall_pose(0.0),
        [inverted],
        CorrelateParams(low_class_weight=1.0),
    )
    assert np.allclose(change[:, :60], weight * full[:, :60], atol=1e-6)
    assert np.array_equal(change[:, 60:], full[:, 60:])


def test_fused_kernel_matches_the_remap_reference_with_distortion_and_occlusion():
    """raw_change (one numba pass) = min over warp_neighbour + color_distance (cv2.remap)."""
    from streetcd.detect.correlate import color_distance, warp_neighbour

    distorted = Intrinsics(160, 120, 140.0, 140.0, 79.5, 59.5, (-0.15, 0.02, 0.001, 0.0, 0.0))
    image, depth = render_wall(wall_pose(0.0))
    depth[:10] = np.nan
    pose_q = wall_pose(0.5)
    image_q, depth_q = render_wall(pose_q, distorted)
    depth_q[:, :30] = 4.0  # an occluder in q
    nb = Neighbour(stretch_histogram(image_q), depth_q, distorted, pose_q)
    cls = np.full(depth.shape, classes.BUILDING, np.uint8)
    stretched = stretch_histogram(image)
    change, support = raw_change(stretched, depth, cls, INTR, wall_pose(0.0), [nb])
    warped, valid = warp_neighbour(nb, depth, camera_rays(INTR), wall_pose(0.0), 0.3)
    reference = np.where(valid, color_distance(stretched, warped), 0.0)
    edge = (
        np.abs(
            np.round(reproject(depth, camera_rays(INTR), wall_pose(0.0), distorted, pose_q)[0])
            - 29.5
        )
        < 1.5
    )  # nearest-pixel ties at the occluder
    assert np.array_equal(support[~edge] == 1, valid[~edge])
    assert valid.mean() > 0.5 and not valid[:10].any()
    # cv2.remap quantises its interpolation weights to 1/32 px
    assert np.percentile(np.abs(change - reference)[~edge], 99) < 0.01


@pytest.mark.parametrize("radius", [0, 1, 3])
def test_stretched_envelope_equals_the_envelope_of_the_stretched_image(radius):
    """Guards the shortcut detect_view takes for neighbours (erode/dilate on uint8, then the
    stretch): the stretch is non-decreasing per channel, so the result is bit-identical."""
    from streetcd.detect.correlate import colour_envelope, stretch_histogram, stretched_envelope

    image = np.random.default_rng(3).integers(0, 256, (61, 83, 3), dtype=np.uint8)
    image[..., 2] = 7  # a flat channel: passed through unchanged
    got = stretched_envelope(image, radius, (2.0, 97.0))
    want = colour_envelope(stretch_histogram(image, (2.0, 97.0)), radius)
    assert got[0].dtype == np.float32
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


@pytest.mark.parametrize("tolerance_px", [0.0, 75.0])  # 75 at 4000 px: 3 px here
def test_uint8_envelope_with_lut_gives_the_same_raw_change_as_the_float_envelope(tolerance_px):
    """Guards the path detect_view takes for neighbours: the uint8 envelope
    (envelope_levels) stretched through its look-up table as raw_change samples it equals
    the float32 envelope of the stretched image, bit for bit."""
    from streetcd.detect.correlate import (
        envelope_levels,
        registration_radius_px,
        stretched_envelope,
    )

    params = CorrelateParams(registration_tolerance_px=tolerance_px)
    image_p, depth_p = render_wall(wall_pose(0.0))
    image_q, depth_q = render_wall(wall_pose(0.4))
    image_q = np.clip(image_q * 0.8 + 20, 0, 255).astype(np.uint8)
    image_q[40:70, 50:90] = (250, 20, 20)  # something the view does not show
    radius = registration_radius_px(INTR.width, params)
    assert (radius > 0) == (tolerance_px > 0)
    lo, hi = stretched_envelope(image_q, radius)
    flo, fhi, lut = envelope_levels(image_q, radius)
    assert flo.dtype == np.uint8 and lut.shape == (1, 256, 3)
    pose_q = wall_pose(0.4)
    float_nb = Neighbour(lo, depth_q, INTR, pose_q, envelope=(lo, hi))
    lut_nb = Neighbour(flo, depth_q, INTR, pose_q, envelope=(flo, fhi), lut=lut)
    cls = np.full(depth_p.shape, classes.BUILDING, np.uint8)
    args = (stretch_histogram(image_p), depth_p, cls, INTR, wall_pose(0.0))
    want, want_support = raw_change(*args, [float_nb], params)
    got, got_support = raw_change(*args, [lut_nb], params)
    assert want.max() > 0.3  # the red patch shows
    assert np.array_equal(got, want) and np.array_equal(got_support, want_support)


def test_pair_lut_maps_the_neighbours_levels_onto_the_views_on_shared_pixels():
    """q is p's wall 0.5 m to the side, darker and offset (0.7 v + 30), and shows a white
    sign over its right third where p has no surface. q's own stretch is pulled by the sign
    and no longer meets p's; the pair fit, taken on the shared wall only, does."""
    image_p, depth_p = render_wall(wall_pose(0.0))
    image_q, depth_q = render_wall(wall_pose(0.5))
    image_q = np.clip(0.7 * image_q.astype(np.float64) + 30, 0, 255).astype(np.uint8)
    image_q[:, 110:] = 250
    depth_p = depth_p.copy()
    u_sign = 110 + 0.5 * 140.0 / WALL_Y  # q's column 110 as p sees it (7 px of parallax)
    depth_p[:, int(u_sign) - 2 :] = np.nan  # p has no surface there
    lut = pair_lut(
        image_p, depth_p, INTR, wall_pose(0.0), image_q, depth_q, INTR, wall_pose(0.5), step=2
    )
    own_p, own_q = stretch_lut(image_p), stretch_lut(image_q)
    shared = image_p[:, 10:100].reshape(-1, 3)  # p's wall; as q records it, 0.7 v + 30
    as_q = np.clip(0.7 * shared.astype(np.float64) + 30, 0, 255).round().astype(np.int64)
    for c in range(3):
        want = own_p[0, shared[:, c], c]
        assert np.median(np.abs(lut[0, as_q[:, c], c] - want)) < 4.0
        assert np.median(np.abs(own_q[0, as_q[:, c], c] - want)) > 15.0
    assert np.all(np.diff(lut[0], axis=0) >= 0)  # monotone: it commutes with the envelope


def test_robust_line_fits_the_pairs_where_quartile_matching_jumps_between_colour_modes():
    """Two colour modes (a wall at level 65, 76 % of the pairs, and one at 150, 24 %), q
    recorded at 1/1.1 of p's levels, 3 % of the pairs moved to the other mode by
    misregistration at the walls' boundary and 8 % changed. The upper quartile sits at the
    edge of the lower mode, and the swaps push q's across the gap, so matching quartiles
    (the first pair fit) gives a gain far from 1.1; the paired fit does not."""
    rng = np.random.default_rng(0)
    n = 20_000
    level_p = np.where(rng.random(n) < 0.76, 65.0, 150.0) + rng.normal(0, 3, n)
    level_q = level_p / 1.1 + rng.normal(0, 1.5, n)
    swap = rng.random(n) < 0.03  # q's sample landed on the other wall
    level_q[swap] = np.where(level_p[swap] < 100, 150.0, 65.0) / 1.1
    changed = rng.random(n) < 0.08
    level_q[changed] = rng.uniform(0, 255, changed.sum())
    gain, offset = robust_line(level_q, level_p)
    assert gain == pytest.approx(1.1, abs=0.02) and abs(offset) < 2.0
    p25, p75 = np.percentile(level_p, [25, 75])
    q25, q75 = np.percentile(level_q, [25, 75])
    assert abs((p75 - p25) / (q75 - q25) - 1.1) > 0.2  # what quartile matching gets


def test_robust_line_recovers_an_offset_and_falls_back_to_the_ratio_on_one_level():
    x = np.linspace(10, 240, 500)
    assert robust_line(x, 0.7 * x + 30) == pytest.approx((0.7, 30.0), abs=1e-6)
    flat = np.full(500, 80.0)  # one level only: no slope to fit, the gain-only ratio
    assert robust_line(flat, flat * 1.2 + np.random.default_rng(1).normal(0, 1, 500)) == (
        pytest.approx(1.2, abs=0.01),
        0.0,
    )


def test_occluder_depth_fills_holes_near_a_surface_with_its_nearest_minimum_only():
    depth = np.full((40, 60), np.nan, np.float32)
    depth[:, 30:] = 10.0  # a wall on the right half
    depth[5:35:6, 10:20] = 2.0  # a near pole: thin streaks of surface with holes between
    filled = occluder_depth(depth, 4)
    have = np.isfinite(depth)
    assert np.array_equal(filled[have], depth[have])  # pixels with a surface keep their depth
    assert np.all(filled[8, 10:20] == 2.0)  # the pole's gaps (3 px from a streak) are hidden
    assert np.all(filled[20, 26:30] == 10.0)  # the wall's edge reaches 4 px into the hole
    assert np.all(filled[20, 6:10] == 2.0) and np.isnan(filled[20, 25])  # and no further
    assert np.isnan(filled[20, 0]) and occluder_depth(depth, 0) is depth


def test_a_wall_behind_a_near_poles_holes_gives_no_evidence_from_that_neighbour():
    """q has a near pole 2 m in front of it that the old cloud holds only as sparse streaks
    (the rest of it is surface holes); q's image shows the pole, p sees the wall behind it.
    With holes hiding nothing, the pole's colour is compared with the wall: strong change.
    With the holes filled for the occlusion test, q gives no evidence there."""
    image_p, depth_p = render_wall(wall_pose(0.0))
    image_q, depth_q = render_wall(wall_pose(0.6))
    wall_levels = stretch_lut(image_q)  # q's stretch without the pole (the view's levels)
    image_q[:, 60:100] = (20, 60, 30)  # the pole in q's image
    depth_q[:, 60:100] = np.nan
    depth_q[::8, 60:100] = 2.0  # its streaks of surface
    cls = np.full(depth_p.shape, classes.BUILDING, np.uint8)
    args = (stretch_histogram(image_p), depth_p, cls, INTR, wall_pose(0.0))
    behind = np.zeros(depth_p.shape, bool)
    behind[:, 72:108] = True  # p's pixels that land in the pole's columns of q (6 px parallax)
    behind[::8] = False
    stretched_q = cv2.LUT(image_q, wall_levels)
    holes = Neighbour(stretched_q, depth_q, INTR, wall_pose(0.6))
    change, support = raw_change(*args, [holes])
    assert np.median(change[behind & (support > 0)]) > 0.3
    assert (support[behind] > 0).mean() > 0.8
    read = Neighbour(holes.image, depth_q, INTR, wall_pose(0.6), holes=hole_depths(depth_q, 6))
    change, support = raw_change(*args, [read])
    assert (support[behind] > 0).mean() < 0.05
    assert np.median(change[support > 0]) < 0.02  # the wall beside the pole still compared
    # the kernel's block lookup is the filled raster, read as it is
    filled = Neighbour(holes.image, occluder_depth(depth_q, 6), INTR, wall_pose(0.6))
    want, want_support = raw_change(*args, [filled])
    assert np.array_equal(change, want) and np.array_equal(support, want_support)


def test_the_compiled_pinhole_reprojection_is_numpys_to_the_bit():
    from streetcd.detect.correlate import camera_rays, reproject
    from streetcd.types import Pose

    rng = np.random.default_rng(0)
    intr = Intrinsics(64, 36, 50.0, 50.5, 31.5, 17.5)
    depth = rng.uniform(0.5, 60, (36, 64)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = np.nan
    rot, _ = cv2.Rodrigues(rng.normal(0, 0.3, 3))
    pose_p, pose_q = Pose(np.eye(3), np.zeros(3)), Pose.from_center(rot, rng.normal(0, 2, 3))
    rays = camera_rays(intr)
    got = reproject(depth, rays, pose_p, intr, pose_q)
    # numpy's float32 operations, as reproject computes them for a distorted camera
    r = (pose_q.R @ pose_p.R.T).astype(np.float32)
    t = (pose_q.t - pose_q.R @ pose_p.R.T @ pose_p.t).astype(np.float32)
    x, y = rays[..., 0] * depth, rays[..., 1] * depth
    xq, yq, zq = (r[i, 0] * x + r[i, 1] * y + r[i, 2] * depth + t[i] for i in range(3))
    zq[~(zq > 1e-3)] = np.nan
    u = (np.float32(intr.fx) * (xq / zq) + np.float32(intr.cx)).astype(np.float32)
    v = (np.float32(intr.fy) * (yq / zq) + np.float32(intr.cy)).astype(np.float32)
    for a, b in zip(got, (u, v, zq), strict=True):
        assert a.dtype == np.float32 and np.array_equal(a, b, equal_nan=True)
    assert np.isnan(got[0]).any() and np.isfinite(got[0]).any()
