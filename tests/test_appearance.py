"""Reference-colour check (streetcd.detect.appearance): colour transfer, the illumination-tolerant
distance and where it is checked, on small exact images."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from streetcd import classes as cls
from streetcd.config import AppearanceParams
from streetcd.detect.appearance import (
    appearance_change,
    channel_map,
    colour_distance,
    fill_nearest,
    footprint,
    reference_distance,
    transfer_colours,
    white_balance_luts,
)
from streetcd.detect.surface import rasterise, rgb8
from streetcd.errors import InputError

H, W = 100, 100


def _scene():
    """A grey wall (building) with a red board (sign, 2 % of the view, as a board 10–20 m
    away is in a street view: the colour transfer assumes changes are a small part of the
    view); a textured wall so the transfer has a distribution to match."""
    ref = np.full((H, W, 3), (150, 150, 140), np.uint8)
    ref[:, ::7] = (120, 110, 100)  # mortar lines
    ref[40:50, 40:60] = (200, 40, 40)
    classes = np.full((H, W), cls.BUILDING, np.uint8)
    classes[40:50, 40:60] = cls.SIGN
    return ref, classes


def test_transfer_cancels_exposure_and_white_balance():
    ref, _ = _scene()
    image = np.clip(ref.astype(np.float32) * (0.7, 0.8, 1.1) + 10, 0, 255).astype(np.uint8)
    mapped = transfer_colours(ref, image, np.ones((H, W), bool))
    assert np.abs(mapped.astype(int) - image.astype(int)).max() <= 1


def test_the_log_transfer_cancels_an_exposure_and_a_gamma_and_keeps_dark_levels():
    rng = np.random.default_rng(0)
    ref = rng.integers(5, 250, 4000).astype(np.float64)
    # another camera: 1 + y = e^b (1 + x)^g, a gamma of 1.3 and an exposure of 0.18
    image = np.round(np.expm1(np.log(0.18) + 1.3 * np.log1p(ref)))
    mapped = channel_map(ref, image, "log")
    assert np.abs(mapped[ref.astype(int)] - image).max() < 1  # the image's own rounding
    assert np.all(np.diff(mapped) > 0)  # monotone: dark stays darker
    # Reinhard's line through the same samples misses by 17 levels and takes the dark ones
    # below 0 (then 0 in the table)
    linear = channel_map(ref, image, "linear")
    assert np.abs(linear[ref.astype(int)] - image).max() > 10
    assert linear[10] < 0 < mapped[10]
    with pytest.raises(InputError, match="transfer model"):
        channel_map(ref, image, "cubic")
    with pytest.raises(InputError, match="transfer"):
        AppearanceParams(transfer="cubic")


def test_the_linear_transfer_is_reinhards_gain_and_offset():
    ref = np.array([10.0, 50.0, 90.0, 130.0])
    image = 2.0 * ref + 5.0
    assert np.allclose(channel_map(ref, image, "linear"), 2.0 * np.arange(256) + 5.0)


def test_distance_is_zero_for_the_same_colour_and_small_for_a_shadow():
    p = AppearanceParams()
    wall = np.array([[150, 150, 140]], np.uint8)
    shadow = (wall * 0.6).astype(np.uint8)  # a cast shadow: darker, same hue
    board = np.array([[200, 40, 40]], np.uint8)
    assert colour_distance(wall, wall, p)[0] == 0.0
    # well below the S-curve's midpoint b / a ≈ 0.24 of eq. 7
    assert colour_distance(shadow, wall, p)[0] < 0.1
    assert colour_distance(wall, board, p)[0] > 0.5


def test_a_dark_colour_tends_to_grey_so_a_shaded_side_is_no_change_of_hue():
    # the scanner saw a grey pole's side in its shade; a camera on the sidewalk sees it lit
    shaded = np.array([[12, 12, 13]], np.uint8)
    lit = np.array([[140, 140, 150]], np.uint8)
    dark_green = np.array([[10, 40, 12]], np.uint8)  # a dark hedge or railing still has a hue
    p = AppearanceParams(brightness_weight=0.0)
    assert colour_distance(lit, shaded, p)[0] < 0.05
    assert colour_distance(lit, dark_green, p)[0] > 0.5
    # ε on the sum instead (before): black is a colour of its own, far from every grey
    black = dataclasses.replace(p, dark_grey=False)
    assert colour_distance(lit, shaded, black)[0] > 0.5
    # the brightness term is the same either way: dark against lit still counts by brightness
    bright = AppearanceParams(chroma_weight=0.0, brightness_weight=0.3)
    grey_way = colour_distance(lit, shaded, bright)[0]
    assert grey_way > 0.4
    assert grey_way == colour_distance(lit, shaded, dataclasses.replace(bright, dark_grey=False))[0]


def test_reference_distance_moves_each_channel_through_its_own_table():
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (500, 3), dtype=np.uint8)
    reference = rng.integers(0, 256, (500, 3), dtype=np.uint8)
    levels = np.arange(256)
    luts = np.stack([255 - levels, levels // 2, np.minimum(levels * 2, 255)]).astype(np.uint8)
    mapped = np.stack([luts[c][reference[:, c]] for c in range(3)], axis=-1)
    p = AppearanceParams()
    got = reference_distance(image, reference, luts, p)
    assert got.dtype == np.float32 and got.shape == (500,)
    assert np.array_equal(got, colour_distance(image, mapped, p))
    assert not np.array_equal(got, colour_distance(image, reference, p))
    nothing = np.zeros((0, 3), np.uint8)
    assert reference_distance(nothing, nothing, luts, p).shape == (0,)


def test_a_removed_board_is_seen_only_on_the_inventory_class():
    ref, classes = _scene()
    image = ref.copy()
    image[40:50, 40:60] = (150, 150, 140)  # the board is gone: wall behind it
    image[0:8, 0:10] = (40, 40, 200)  # a blue patch on the façade: not an inventory class
    a = appearance_change(image, ref, np.ones((H, W), bool), classes, AppearanceParams())
    board = classes == cls.SIGN
    assert a[board].min() > 0.5
    assert a[~board].max() == 0.0


def test_the_stored_colour_as_well_keeps_a_dark_railing_the_transfer_made_cyan():
    # the scan's red levels spread half as wide as the photograph's: the transfer's gain on
    # red is 2.3, and its offset takes the railing's dark red level (33) to 0
    ref = np.zeros((H, W, 3), np.uint8)
    ref[..., 0] = np.where(np.arange(W) % 2 == 0, 100, 200)[None, :]
    ref[..., 1:] = 120
    image = ref.copy()
    image[..., 0] = np.where(np.arange(W) % 2 == 0, 20, 255)[None, :]
    classes = np.full((H, W), cls.BUILDING, np.uint8)
    classes[40:50, 10:30] = classes[40:50, 60:80] = cls.RAILING
    ref[40:50, 10:30] = ref[40:50, 60:80] = (33, 33, 35)  # a dark grey railing in the scan
    image[40:50, 10:30] = (30, 31, 34)  # still there
    image[40:50, 60:80] = (40, 150, 40)  # a hedge where the other stood
    valid = np.ones((H, W), bool)
    kept, hedge = np.zeros((H, W), bool), np.zeros((H, W), bool)
    kept[40:50, 10:30], hedge[40:50, 60:80] = True, True
    transferred = appearance_change(image, ref, valid, classes, AppearanceParams(gap_px=0))
    both = AppearanceParams(gap_px=0, raw_reference=True)
    nearer = appearance_change(image, ref, valid, classes, both)
    assert np.median(transferred[kept]) > 0.5  # a hue the transfer made up
    assert nearer[kept].max() < 0.1
    assert nearer[hedge].min() > 0.5 and transferred[hedge].min() > 0.5


def test_no_surface_and_unchecked_classes_give_zero():
    ref, classes = _scene()
    image = np.zeros_like(ref)
    valid = np.zeros((H, W), bool)
    assert not appearance_change(image, ref, valid, classes).any()
    off = AppearanceParams(classes=())
    assert not appearance_change(image, ref, np.ones((H, W), bool), classes, off).any()


def test_rasterise_carries_the_colour_of_the_nearest_vertex():
    uv = np.array([[0.0, 0.0], [9.0, 0.0], [0.0, 9.0], [9.0, 9.0]])
    depth = np.full(4, 5.0)
    colours = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [9, 9, 9]], np.uint8)
    tris = np.array([[0, 1, 2], [1, 3, 2]])
    surf = rasterise(uv, depth, np.array([1, 2, 3, 4], np.uint8), tris, (12, 12), colours)
    assert surf.colour is not None
    assert tuple(surf.colour[1, 1]) == (255, 0, 0) and surf.classes[1, 1] == 1
    assert tuple(surf.colour[8, 8]) == (9, 9, 9) and surf.classes[8, 8] == 4
    assert not surf.colour[11, 11].any() and surf.classes[11, 11] == 0  # outside: no surface


def test_rgb8_reads_16_bit_and_8_bit_las_colours():
    assert np.array_equal(rgb8(np.array([[65535, 257, 0]], np.uint16)), [[255, 1, 0]])
    assert np.array_equal(rgb8(np.array([[255, 10, 0]], np.uint16)), [[255, 10, 0]])


def _railing():
    """A railing's bars (every 8th column, 2 px wide) in front of a grey wall, in a 400 px
    wide view; half of the gaps have no surface (the scan saw nothing there)."""
    h, w = 100, 400
    ref = np.full((h, w, 3), (150, 150, 140), np.uint8)
    classes = np.full((h, w), cls.BUILDING, np.uint8)
    valid = np.ones((h, w), bool)
    rows, cols = slice(60, 80), slice(100, 294)  # from the first bar to the last
    classes[rows, cols] = cls.BUILDING
    bars = np.zeros((h, w), bool)
    for c in range(100, 300, 8):
        bars[60:80, c : c + 2] = True
    classes[bars] = cls.RAILING
    ref[bars] = (60, 60, 60)
    valid[60:80, 100:200] = bars[60:80, 100:200]  # no surface in the left half's gaps
    ref[~valid] = 0
    return ref, classes, valid, (rows, cols)


def test_a_hedge_in_place_of_a_railing_is_seen_in_the_gaps_too():
    ref, classes, valid, (rows, cols) = _railing()
    image = ref.copy()
    image[~valid] = (150, 150, 140)  # the wall the scan missed behind the gaps
    unchanged = appearance_change(image, ref, valid, classes)
    # gaps without a surface take a bar's colour, so an unchanged railing is not 0 there, but
    # weighted it stays below eq. 7's midpoint b / a = 11 / 45
    weight = AppearanceParams().weight
    assert unchanged[rows, cols].max() * weight < 11 / 45
    image[rows, cols] = (40, 110, 40)  # a hedge stands where the railing stood
    a = appearance_change(image, ref, valid, classes)
    # bars, gaps with a surface and gaps without one: past the midpoint once weighted (the
    # closing disc rounds the gaps' ends: their first and last rows stay out)
    assert a[62:78, cols].min() * weight > 11 / 45
    outside = np.ones(a.shape, bool)
    outside[55:85, 95:305] = False
    assert a[outside].max() == 0.0
    only_bars = appearance_change(image, ref, valid, classes, AppearanceParams(gap_px=0))
    assert only_bars[rows, cols][classes[rows, cols] != cls.RAILING].max() == 0.0


def test_fill_nearest_takes_the_closest_surface_colour():
    ref = np.zeros((3, 5, 3), np.uint8)
    ref[:, 0] = (10, 0, 0)
    ref[:, 4] = (0, 20, 0)
    valid = np.zeros((3, 5), bool)
    valid[:, [0, 4]] = True
    out = fill_nearest(ref, valid, np.ones((3, 5), bool))
    assert tuple(out[1, 1]) == (10, 0, 0) and tuple(out[1, 3]) == (0, 20, 0)
    assert np.array_equal(out[:, [0, 4]], ref[:, [0, 4]])


def test_holes_between_sparse_bars_join_the_railing_footprint():
    """A railing's surface is mostly holes: the triangles between its thin bars and the wall
    behind are dropped. Bars 60 px apart leave gaps twice as wide as a 31 px closing disc;
    the holes next to them count as the railing when ``hole_reach`` > 0."""
    classes = np.full((120, 400), cls.BUILDING, np.uint8)
    holes = np.zeros(classes.shape, bool)
    holes[40:80, 20:380] = True
    for c in range(20, 380, 60):
        classes[40:80, c : c + 2] = cls.RAILING
        holes[40:80, c : c + 2] = False
    between = (slice(46, 74), slice(22, 320))
    plain = footprint(classes, (cls.RAILING,), 31)
    assert plain[between].mean() < 0.05
    joined = footprint(classes, (cls.RAILING,), 31, holes=holes, hole_reach=1.0)
    assert joined[between].mean() > 0.95
    assert not joined[:30].any() and not joined[90:].any() and not joined[:, 395:].any()


def test_holes_join_the_footprint_only_near_the_hole_classes():
    """The holes around a pole (the sky and the street behind its thin outline) stay out
    when ``hole_classes`` leaves poles out; a railing's still join."""
    classes = np.full((120, 400), cls.BUILDING, np.uint8)
    holes = np.zeros(classes.shape, bool)
    holes[:, 20:380] = True
    for c in range(20, 200, 60):  # railing bars 60 px apart, on the left
        classes[40:80, c : c + 2] = cls.RAILING
        holes[40:80, c : c + 2] = False
    classes[10:110, 300:304] = cls.POLE  # a pole 4 px wide, on the right
    holes[10:110, 300:304] = False
    checked = (cls.POLE, cls.RAILING)
    railing_gap, beside_pole = (slice(46, 74), slice(22, 140)), (slice(20, 100), slice(312, 318))
    anywhere = footprint(classes, checked, 31, holes=holes, hole_reach=1.0)
    assert anywhere[railing_gap].mean() > 0.95 and anywhere[beside_pole].all()
    not_poles = footprint(
        classes, checked, 31, holes=holes, hole_reach=1.0, hole_classes=(cls.RAILING,)
    )
    assert not_poles[railing_gap].mean() > 0.95 and not not_poles[beside_pole].any()
    assert not_poles[10:110, 300:304].all()  # the pole's own pixels stay checked
    # a role among hole_classes that is not checked brings no holes (the ground, when the
    # colour check leaves it out)
    classes[10:110, 240:244] = cls.GROUND
    holes[10:110, 240:244] = False
    beside_ground = (slice(20, 100), slice(250, 256))
    ground_too = footprint(
        classes, checked, 31, holes=holes, hole_reach=1.0, hole_classes=(cls.GROUND, cls.RAILING)
    )
    assert not ground_too[beside_ground].any() and ground_too[railing_gap].mean() > 0.95


def test_registration_bands_are_opened_away_and_objects_kept():
    ref, classes = _scene()
    valid = np.ones((H, W), bool)
    shifted = np.empty_like(ref)
    shifted[:, 2:] = ref[:, :-2]  # the same street, registered 2 px off
    shifted[:, :2] = ref[:, :2]
    sharp = appearance_change(shifted, ref, valid, classes)
    assert sharp[42:48, 40:42].min() > 0.5  # the wall where the scan has the board's edge
    assert appearance_change(shifted, ref, valid, classes, registration_px=2).max() == 0.0
    changed = shifted.copy()
    changed[40:50, 40:60] = (40, 40, 200)  # the board is now blue: a change 20 × 10 px
    a = appearance_change(changed, ref, valid, classes, registration_px=2)
    assert a[40:50, 40:60].min() > 0.5  # keeps its whole extent


def test_a_bench_on_the_pavement_is_seen_only_when_the_ground_is_checked():
    """fuse_appearance with ``ground``: the ground role is checked as well (an added bench in
    front of the pavement); without it, and on the road, it is not."""
    from streetcd.config import DetectParams
    from streetcd.detect.chain import fuse_appearance
    from streetcd.detect.surface import ViewSurface
    from streetcd.types import Intrinsics, Pose, View

    ref = np.full((H, W, 3), (140, 135, 130), np.uint8)
    ref[::5] = (110, 105, 100)  # paving joints: a distribution for the transfer
    classes = np.full((H, W), cls.GROUND, np.uint8)
    classes[:, 60:] = cls.ROAD
    image = ref.copy()
    image[40:46, 20:36] = (200, 40, 40)  # a red bench on the pavement
    image[40:46, 70:86] = (40, 40, 200)  # a blue car on the road
    surf = ViewSurface(np.full((H, W), 10.0, np.float32), classes, np.ones((H, W), bool), ref)
    view = View("v", Intrinsics(W, H, 80.0, 80.0, W / 2, H / 2), Pose(np.eye(3), np.zeros(3)))
    params = DetectParams()
    zero = np.zeros((H, W), np.float32)
    fused, a = fuse_appearance(image, surf, zero, view, params, ground=True)
    assert a is not None
    assert a[42:44, 24:32].min() > 0.5 and fused[42:44, 24:32].min() > 0.3
    assert a[:, 60:].max() == 0.0  # the road is never checked
    _, off = fuse_appearance(image, surf, zero, view, params)
    assert off is not None and off.max() == 0.0
    none = dataclasses.replace(params, appearance=AppearanceParams(ground_classes=()))
    _, empty = fuse_appearance(image, surf, zero, view, none, ground=True)
    assert empty is not None and empty.max() == 0.0


def test_the_holes_beside_a_pole_join_it_only_where_the_roles_are_inferred():
    """fuse_appearance: the holes beside a pole are left out of the colour check
    (``appearance.hole_classes``) when the cloud's own classes give the roles, and join the
    pole when the roles are inferred (``inferred``): the near points' fill, which closes a
    near pole, is off then."""
    from streetcd.config import DetectParams
    from streetcd.detect.chain import fuse_appearance
    from streetcd.detect.surface import ViewSurface
    from streetcd.types import Intrinsics, Pose, View

    h, w = 120, 800  # wide enough for the footprint's reach (0.6 x a 27 px closing)
    ref = np.full((h, w, 3), (120, 120, 120), np.uint8)
    ref[::4] = (100, 100, 100)  # some texture for the colour transfer
    classes = np.full((h, w), cls.BUILDING, np.uint8)
    valid = np.ones((h, w), bool)
    classes[:, 400:406] = cls.POLE
    valid[:, 406:420] = False  # holes right of the pole: what stands behind it
    image = ref.copy()
    image[:, 406:420] = (60, 90, 200)  # the image shows blue there
    surf = ViewSurface(np.full((h, w), 10.0, np.float32), classes, valid, ref)
    view = View("v", Intrinsics(w, h, 400.0, 400.0, w / 2, h / 2), Pose(np.eye(3), np.zeros(3)))
    zero = np.zeros((h, w), np.float32)
    params = DetectParams()
    beside = (slice(20, 100), slice(408, 412))
    _, own = fuse_appearance(image, surf, zero, view, params)
    _, inferred = fuse_appearance(image, surf, zero, view, params, inferred=True)
    assert own is not None and inferred is not None
    assert own[beside].max() == 0.0
    assert inferred[beside].min() > 0.5


def test_the_colour_check_of_a_12_mp_view_runs_at_the_cell_scale_and_finds_the_same_board():
    """fuse_appearance on a view 4,000 px wide computes the check where a superpixel cell
    is ~24 px (about half size) and upsamples it: a removed board is still found over its
    whole inside and nothing is made up on the wall; at 1,920 px it is the full-size check
    to the bit."""
    from streetcd.config import DetectParams
    from streetcd.detect.chain import fuse_appearance
    from streetcd.detect.correlate import registration_radius_px
    from streetcd.detect.surface import ViewSurface
    from streetcd.types import Intrinsics, Pose, View

    params = DetectParams()
    for width, height in ((4000, 240), (1920, 240)):
        ref = np.full((height, width, 3), (150, 150, 140), np.uint8)
        ref[:, ::7] = (120, 110, 100)  # mortar lines
        classes = np.full((height, width), cls.BUILDING, np.uint8)
        board = np.s_[80:160, 1000:1200]
        ref[board] = (200, 40, 40)
        classes[board] = cls.SIGN
        image = ref.copy()
        image[board] = (150, 150, 140)  # the board is gone
        valid = np.ones((height, width), bool)
        surf = ViewSurface(np.full((height, width), 10.0, np.float32), classes, valid, ref)
        intr = Intrinsics(width, height, 0.8 * width, 0.8 * width, width / 2, height / 2)
        view = View("v", intr, Pose(np.eye(3), np.zeros(3)))
        zero = np.zeros((height, width), np.float32)
        _, a = fuse_appearance(image, surf, zero, view, params)
        assert a is not None and a.shape == (height, width)
        assert a[90:150, 1010:1190].min() > 0.5
        assert a[:, :900].max() == 0.0 and a[:, 1300:].max() == 0.0
        radius = registration_radius_px(width, params.correlate)
        full = appearance_change(image, ref, valid, classes, params.appearance, radius)
        if width == 1920:
            np.testing.assert_array_equal(a, full)
        else:  # within 0.05 of the full-size check over the board's inside
            assert np.abs(a[90:150, 1010:1190] - full[90:150, 1010:1190]).max() < 0.05


def test_shrink_averages_whole_blocks_first():
    import cv2

    from streetcd.detect.chain import shrink

    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (300, 400, 3), np.uint8)
    half = shrink(image, (200, 150))  # a whole factor: the 2 × 2 block means
    blocks = image.reshape(150, 2, 200, 2, 3).astype(np.float64).mean(axis=(1, 3))
    assert np.abs(half.astype(np.float64) - blocks).max() <= 1.0
    assert shrink(image, (192, 144)).shape == (144, 192, 3)
    # less than halved: OpenCV's area resize itself
    np.testing.assert_array_equal(
        shrink(image, (300, 225)), cv2.resize(image, (300, 225), interpolation=cv2.INTER_AREA)
    )


def _street_with_a_hedge():
    """A sunlit pavement (ground) over the upper three quarters and a sunlit green hedge
    (vegetation) below, leaf-textured; the photograph shows the hedge in deep shade (0.3 as
    bright, a little bluer) and a brown bench in front of it."""
    rng = np.random.default_rng(3)
    ref = np.full((H, W, 3), (170, 165, 150), np.uint8)
    ref[::6] = (140, 135, 125)  # paving joints
    hedge = np.array([120.0, 200.0, 90.0]) * rng.uniform(0.8, 1.2, (H // 4, W, 1))
    ref[-(H // 4) :] = np.clip(hedge, 0, 255).astype(np.uint8)
    classes = np.full((H, W), cls.GROUND, np.uint8)
    classes[-(H // 4) :] = cls.VEGETATION
    image = ref.copy()
    image[-(H // 4) :] = np.clip(ref[-(H // 4) :] * (0.3, 0.3, 0.33), 0, 255).astype(np.uint8)
    image[84:94, 30:50] = (120, 80, 50)  # the bench
    return ref, classes, image


def test_a_bench_before_a_hedge_is_seen_by_its_hue_and_the_shaded_hedge_is_not():
    ref, classes, image = _street_with_a_hedge()
    valid = np.ones((H, W), bool)
    green = classes == cls.VEGETATION
    a = appearance_change(image, ref, valid, classes, AppearanceParams(), by_hue=green)
    assert a[86:92, 33:47].min() > 0.5
    hedge = green.copy()
    hedge[82:96, 28:52] = False
    # the shade changes the hedge's brightness, not its hue: k · A stays below the S-curve's
    # middle b / a ≈ 0.24 of eq. 7 (dark colours lose some chroma to ε, hence not 0), where
    # the brightness term would take the median to 0.32
    assert np.median(a[hedge]) < 0.25
    assert a[~green].max() == 0.0  # the ground is not a checked class here
    # without the pixels to check by hue the hedge is not checked at all
    assert not appearance_change(image, ref, valid, classes, AppearanceParams()).any()


def test_the_white_balance_is_a_gain_per_channel_without_an_offset():
    ref, _ = _scene()
    image = np.clip(ref.astype(np.float32) * (0.7, 0.8, 1.1), 0, 255).astype(np.uint8)
    luts = white_balance_luts(ref, image, np.ones((H, W), bool))
    assert (luts[:, 0] == 0).all()  # black stays black: no offset
    mapped = np.stack([luts[c][ref[..., c]] for c in range(3)], axis=-1)
    assert np.abs(mapped.astype(int) - image.astype(int)).max() <= 2
    identity = white_balance_luts(ref, image, np.zeros((H, W), bool))
    assert (identity == np.arange(256)).all()


def test_vegetation_is_checked_only_below_the_camera_and_against_real_colours():
    """fuse_appearance: a level camera looking along the street (local frame z up) checks the
    hedge it looks down on, not the crown above its height; hue_classes () is off."""
    from streetcd.config import DetectParams
    from streetcd.detect.chain import below_camera, fuse_appearance
    from streetcd.detect.surface import ViewSurface
    from streetcd.types import Intrinsics, Pose, View

    ref, classes, image = _street_with_a_hedge()
    classes[:10] = cls.VEGETATION  # a crown at the top of the view, above the camera ...
    image[2:8, 30:50] = (120, 80, 50)  # ... with a brown board in front of it
    # camera axes in the local frame: x right = −y, y down = −z, z forward = +x
    level = Pose(np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]), np.zeros(3))
    view = View("v", Intrinsics(W, H, 80.0, 80.0, W / 2, H / 2), level)
    below = below_camera(view)
    assert below[H // 2 + 1 :].all() and not below[: H // 2].any()
    # a lens with distortion reads the undistorted rays: the horizon stays at the middle row
    # (whose pixel centres lie on it, either side by rounding)
    barrel = Intrinsics(W, H, 80.0, 80.0, W / 2, H / 2, dist=(-0.3, 0.1, 0.0, 0.0, 0.0))
    bent = below_camera(View("d", barrel, level))
    assert bent[H // 2 + 1 :].all() and not bent[: H // 2].any()
    surf = ViewSurface(np.full((H, W), 10.0, np.float32), classes, np.ones((H, W), bool), ref)
    zero = np.zeros((H, W), np.float32)
    params = DetectParams()
    _, a = fuse_appearance(image, surf, zero, view, params)
    assert a is not None
    assert a[86:92, 33:47].min() > 0.5  # the bench before the hedge
    assert a[:10].max() == 0.0  # the crown seen from under it is left alone
    off = dataclasses.replace(params, appearance=AppearanceParams(hue_classes=()))
    _, none = fuse_appearance(image, surf, zero, view, off)
    assert none is not None and none.max() == 0.0
    # a cloud without colours gets the intensity check, which asks no vegetation
    _, intensity = fuse_appearance(image, surf, zero, view, params, "intensity")
    assert intensity is not None and intensity[86:92, 33:47].max() == 0.0


def test_a_board_before_a_wall_is_seen_by_its_hue_and_a_balconys_shadow_is_not():
    """The façade is checked by hue as well (``hue_classes`` holds the building role): a cast
    shadow the scan did not have darkens the wall without changing its hue."""
    from streetcd.config import DetectParams
    from streetcd.detect.chain import fuse_appearance
    from streetcd.detect.surface import ViewSurface
    from streetcd.types import Intrinsics, Pose, View

    ref, _ = _scene()
    ref[40:50, 40:60] = ref[40:50, 20:40]  # no board in the old cloud: wall
    classes = np.full((H, W), cls.BUILDING, np.uint8)
    image = ref.copy()
    image[60:80, 10:90] = (ref[60:80, 10:90] * 0.45).astype(np.uint8)  # a balcony's shadow
    image[86:94, 40:60] = (200, 40, 40)  # a red board before the wall's lower part
    image[86:94, 70:90] = (14, 14, 15)  # a black bench before it too
    level = Pose(np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]), np.zeros(3))
    view = View("v", Intrinsics(W, H, 80.0, 80.0, W / 2, H / 2), level)
    surf = ViewSurface(np.full((H, W), 10.0, np.float32), classes, np.ones((H, W), bool), ref)
    zero = np.zeros((H, W), np.float32)
    _, a = fuse_appearance(image, surf, zero, view, DetectParams())
    assert a is not None
    assert a[88:92, 43:57].min() > 0.5
    assert a[62:78, 12:88].max() < 0.2  # k · A far below eq. 7's middle; with brightness 0.22
    assert a[: H // 2].max() == 0.0  # the upper floors, above the camera, are left alone
    # without a brightness term the hue check keeps darkness a colour (appearance.dark_grey
    # is the inventory's): a black bench differs from the lit wall in nothing else
    assert a[88:92, 73:87].min() > 0.5
