"""The see-through test (streetcd.detect.seethrough): a railing of thin bars 2 m in front of a
textured wall, seen by a view and two neighbours 2 m to each side. Its old surface is what a
sparse scan leaves (the bars, patches of wall between them, holes next to every bar). A railing
still standing there is not a change; a hedge where it stood is."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from streetcd.config import Config, DetectParams, TextureParams
from streetcd.detect.seethrough import blur_groups, see_through_change
from streetcd.errors import InputError
from streetcd.types import Intrinsics, Pose

RNG = np.random.default_rng(11)
INTR = Intrinsics(320, 240, 400.0, 400.0, 159.5, 119.5)
WALL_Z, RAIL_Z, HEDGE_Z = 10.0, 8.0, 7.0
RAIL_X, RAIL_Y = (-1.2, 1.2), (-0.3, 0.5)  # metres, y downwards as the image's rows
BAR_M, GAP_M = 0.02, 0.12  # bars 2 cm wide every 12 cm: 1 and 6 px at 8 m
RAILING, BUILDING = 66, 6


def _texture(seed: int) -> np.ndarray:
    """A random pattern over 12 × 12 m, 1 cm texels, blurred to blobs of about 5 cm (leaves,
    bricks), grey levels of mean 128 and standard deviation 40."""
    rng = np.random.default_rng(seed)
    blobs = cv2.GaussianBlur(rng.normal(0, 1, (1200, 1200)).astype(np.float32), (0, 0), 5.0)
    return 128 + 40 * blobs / blobs.std()


WALL, HEDGE = _texture(1), _texture(2)


def _rays() -> tuple[np.ndarray, np.ndarray]:
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float32)
    return (u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy


def _on(texture: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return cv2.remap(texture, x * 100 + 600, y * 100 + 600, cv2.INTER_LINEAR)


def _scene(center_x: float, hedge: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A camera at (center_x, 0, 0) looking down +z: its image (H, W, 3) uint8 of the scene
    (the railing, or a hedge where it stood), and the old cloud's surface as a sparse scan
    leaves it: depth (H, W) float32 (NaN = hole) and classes (H, W) uint8."""
    rx, ry = _rays()
    x_rail, y_rail = center_x + rx * RAIL_Z, ry * RAIL_Z
    in_rail = (
        (x_rail > RAIL_X[0]) & (x_rail < RAIL_X[1]) & (y_rail > RAIL_Y[0]) & (y_rail < RAIL_Y[1])
    )
    on_bar = in_rail & (np.mod(x_rail - RAIL_X[0], GAP_M) < BAR_M)
    grey = _on(WALL, center_x + rx * WALL_Z, ry * WALL_Z)
    if hedge:
        x_h, y_h = center_x + rx * HEDGE_Z, ry * HEDGE_Z
        in_hedge = (x_h > RAIL_X[0]) & (x_h < RAIL_X[1]) & (y_h > RAIL_Y[0]) & (y_h < RAIL_Y[1])
        grey = np.where(in_hedge, _on(HEDGE, x_h, y_h) * 0.6, grey)
    else:
        grey = np.where(on_bar, 20.0, grey)
    image = np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, axis=2)
    depth = np.full(grey.shape, WALL_Z, np.float32)
    classes = np.full(grey.shape, BUILDING, np.uint8)
    near_bar = cv2.dilate(on_bar.view(np.uint8), np.ones((1, 5), np.uint8)).view(bool)
    depth[near_bar & ~on_bar] = np.nan  # the triangles from a bar to the wall are dropped
    classes[near_bar & ~on_bar] = 0
    depth[on_bar], classes[on_bar] = RAIL_Z, RAILING
    return image, depth, classes


def _see_through(
    hedge: bool, params: TextureParams, min_blur_px: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """S_p of the view at the origin with neighbours 2 m to each side, and the footprint."""
    image, depth, classes = _scene(0.0, hedge)
    nbs = []
    for x in (-2.0, 2.0):
        im, d, _ = _scene(x, hedge)
        nbs.append((im, d, INTR, Pose.from_center(np.eye(3), np.array([x, 0.0, 0.0])), None))
    own = classes == RAILING
    inside = cv2.morphologyEx(own.view(np.uint8), cv2.MORPH_CLOSE, np.ones((9, 9), np.uint8))
    inside = inside.view(bool)
    valid = np.isfinite(depth)
    pose = Pose(np.eye(3), np.zeros(3))
    change = see_through_change(
        image, depth, own, valid, inside, INTR, pose, nbs, params, 0.3, 9, min_blur_px
    )
    return change, inside


PARAMS = TextureParams(scale=1.0, window_px=15, max_global_shift_px=0.0, see_through_classes=(66,))


UNBLURRED = TextureParams(
    scale=1.0,
    window_px=15,
    max_global_shift_px=0.0,
    see_through_classes=(66,),
    see_through_blur_m=0.0,
)


def _core(inside: np.ndarray) -> np.ndarray:
    """The footprint's inner part, away from the railing's ends (which the neighbours see
    past)."""
    core = cv2.erode(inside.view(np.uint8), np.ones((9, 9), np.uint8)).view(bool)
    core[:, :40] = core[:, -40:] = False
    return core


def test_a_railing_still_standing_is_no_change_and_a_hedge_where_it_stood_is():
    standing, inside = _see_through(False, PARAMS)
    hedge, _ = _see_through(True, PARAMS)
    core = _core(inside)
    assert core.sum() > 2000
    assert np.median(standing[core]) < 0.1 and (standing[core] > 0.5).mean() < 0.05
    assert np.median(hedge[core]) > 0.3 and np.mean(hedge[core]) > 0.35
    assert not standing[~inside].any() and not hedge[~inside].any()


def test_without_the_low_pass_the_bars_make_a_standing_railing_look_changed():
    blurred, inside = _see_through(False, PARAMS)
    sharp, _ = _see_through(False, UNBLURRED)
    core = _core(inside)
    assert np.mean(sharp[core]) > 2 * np.mean(blurred[core]) + 0.05


def test_the_low_pass_has_a_floor_in_working_pixels():
    """Without the metric blur the bars make the standing railing look changed; a floor of
    3 px (more than the metric blur's 1.6 px here) takes them away, and the hedge where the
    railing stood is still found through it. A floor under the metric blur changes nothing."""
    sharp, inside = _see_through(False, UNBLURRED)
    floored, _ = _see_through(False, UNBLURRED, min_blur_px=3.0)
    hedge, _ = _see_through(True, UNBLURRED, min_blur_px=3.0)
    core = _core(inside)
    assert np.mean(sharp[core]) > 2 * np.mean(floored[core]) + 0.05
    assert np.median(hedge[core]) > 0.3
    metric, _ = _see_through(False, PARAMS)
    assert np.array_equal(_see_through(False, PARAMS, min_blur_px=0.5)[0], metric)


def test_footprints_are_blurred_by_their_own_depth():
    inside = np.zeros((40, 60), bool)
    inside[5:15, 5:20] = inside[25:35, 30:55] = True  # two railings, 4 m and 16 m away
    depth = np.where(np.arange(60)[None, :] < 25, 4.0, 16.0).astype(np.float32) * np.ones((40, 1))
    depth = depth.astype(np.float32)
    groups = list(blur_groups(inside, inside, depth, 400.0, 0.04))
    assert len(groups) == 2
    (far_sigma, far), (near_sigma, near) = groups  # ascending blur
    assert abs(near_sigma - 4.0) / 4.0 < 0.12 and abs(far_sigma - 1.0) / 1.0 < 0.12
    assert near[10, 10] and not near[30, 40] and far[30, 40] and not far[10, 10]
    # a footprint without a pixel of the object's own surface is left out
    own = inside.copy()
    own[:20] = False
    assert [m[10, 10] for _, m in blur_groups(inside, own, depth, 400.0, 0.04)] == [False]


def test_the_see_through_test_is_on_by_default_and_off_hashes_as_before_it():
    assert TextureParams().see_through_classes == (RAILING,)
    off = Config(DetectParams(texture=TextureParams(see_through_classes=())))
    off_too = Config(
        DetectParams(texture=TextureParams(see_through_classes=(), see_through_blur_m=0.07))
    )
    on = Config(DetectParams(texture=TextureParams(see_through_blur_m=0.07)))
    assert off.results_hash() == off_too.results_hash() != Config().results_hash()
    assert on.results_hash() not in (Config().results_hash(), off.results_hash())
    # the coloured clouds' floor (thirty-third round, left off) is in the hash when on
    floor_on = Config(DetectParams(texture=TextureParams(see_through_colour_blur_px=1.5)))
    assert floor_on.results_hash() not in (Config().results_hash(), off.results_hash())
    with pytest.raises(InputError, match="see_through_colour_blur_px"):
        TextureParams(see_through_colour_blur_px=-1.0)
