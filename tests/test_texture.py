"""The texture cue (streetcd.detect.texture): exact NCC on small arrays, and a textured wall
seen by two cameras 1 m apart, where a removed object's old surface is found and the wall is not."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from streetcd.config import DetectParams, TextureParams
from streetcd.detect.correlate import camera_rays
from streetcd.detect.texture import (
    _best_ncc,
    _best_ncc_in,
    _best_ncc_on,
    _tiles_near,
    foreshortening,
    global_shift,
    grey,
    grey_u8,
    local_ncc,
    near_layer,
    surface_normals,
    surface_points,
    texture_change,
    work_size,
)
from streetcd.errors import InputError
from streetcd.types import Intrinsics, Pose

RNG = np.random.default_rng(5)
INTR = Intrinsics(160, 120, 150.0, 150.0, 79.5, 59.5)
WALL_Z = 10.0


def test_ncc_is_one_for_gain_and_offset_and_minus_one_for_a_negative():
    a = RNG.uniform(0, 255, (20, 20)).astype(np.float32)
    valid = np.ones(a.shape, bool)
    for b, want in ((a, 1.0), (2 * a + 5, 1.0), (255 - a, -1.0)):
        ncc, textured = local_ncc(a, b.astype(np.float32), valid, 5, 1.0)
        assert textured[2:-2, 2:-2].all()
        assert np.allclose(ncc[2:-2, 2:-2], want, atol=1e-4)


def test_ncc_matches_its_definition_and_flat_windows_give_no_evidence():
    a = RNG.uniform(0, 255, (15, 15)).astype(np.float32)
    b = RNG.uniform(0, 255, (15, 15)).astype(np.float32)
    valid = np.ones(a.shape, bool)
    valid[0, :] = False
    ncc, textured = local_ncc(a, b, valid, 5, 1.0)
    wa, wb = a[5:10, 5:10].ravel(), b[5:10, 5:10].ravel()
    want = np.mean((wa - wa.mean()) * (wb - wb.mean())) / (wa.std() * wb.std())
    assert ncc[7, 7] == pytest.approx(want, abs=1e-4)
    flat = np.full(a.shape, 100.0, np.float32)
    ncc, textured = local_ncc(flat, b, valid, 5, 4.0)
    assert not textured.any() and not ncc.any()


def _shifted(x: np.ndarray, dy: int, dx: int, fill: float | bool) -> np.ndarray:
    """out[r, c] = x[r - dy, c - dx], fill outside."""
    out = np.full_like(x, fill)
    h, w = x.shape
    out[max(dy, 0) : h + min(dy, 0), max(dx, 0) : w + min(dx, 0)] = x[
        max(-dy, 0) : h + min(-dy, 0), max(-dx, 0) : w + min(-dx, 0)
    ]
    return out


def _sparse_case(shape=(90, 130)):
    """A view, a neighbour that is the view moved by (1, -2) px plus noise, holes in both."""
    a = cv2.GaussianBlur(RNG.uniform(0, 255, shape).astype(np.float32), (3, 3), 0)
    b = _shifted(a, 1, -2, 0.0) * 0.8 + 20 + RNG.normal(0, 3, shape).astype(np.float32)
    valid = RNG.uniform(size=shape) > 0.05
    valid[:, :10] = False
    return a, b.astype(np.float32), valid


def test_best_ncc_is_the_best_local_ncc_over_the_shifts():
    a, b, valid = _sparse_case()
    params = TextureParams(window_px=7, min_std=2.0)
    best, textured = _best_ncc(a, b, valid, params, radius=2)
    want = np.full(a.shape, -1.0, np.float32)
    want_textured = np.zeros(a.shape, bool)
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            b_s, v_s = _shifted(b, dy, dx, 0.0), _shifted(valid, dy, dx, False)
            ncc, t = local_ncc(a, b_s, v_s & valid, 7, 2.0)
            want = np.maximum(want, np.where(t, ncc, -1.0))
            want_textured |= t
    want[~want_textured] = 0.0
    assert (textured == want_textured).all()
    assert np.abs(best - want).max() < 1e-3
    # the neighbour is the view moved by (1, -2): that shift finds it, almost everywhere
    assert np.median(best[textured]) > 0.95


@pytest.mark.parametrize(("window", "shape"), [(4, (40, 50)), (8, (30, 6)), (7, (5, 60))])
def test_best_ncc_matches_local_ncc_for_even_windows_and_arrays_smaller_than_a_window(
    window, shape
):
    # the window sums are swept along rows and columns as OpenCV's box filter anchors them:
    # an even window has one pixel more before its centre than after it
    rng = np.random.default_rng(window)
    a = rng.normal(100, 30, shape).astype(np.float32)
    b = (a + rng.normal(0, 10, shape)).astype(np.float32)
    valid = rng.random(shape) < 0.9
    params = TextureParams(window_px=window, min_std=2.0)
    best, textured = _best_ncc_in(a, b, valid, params, 1, (0, 1))
    want = np.full(shape, -1.0, np.float32)
    want_textured = np.zeros(shape, bool)
    for dy in range(-1, 2):
        for dx in range(0, 3):
            b_s, v_s = _shifted(b, dy, dx, 0.0), _shifted(valid, dy, dx, False)
            ncc, t = local_ncc(a, b_s, v_s & valid, window, 2.0)
            want = np.maximum(want, np.where(t, ncc, -1.0))
            want_textured |= t
    want[~want_textured] = 0.0
    assert want_textured.any()
    assert (textured == want_textured).all()
    assert np.abs(best - want).max() < 1e-4


@pytest.mark.parametrize("seed", range(6))
def test_best_ncc_over_the_valid_pixels_box_is_the_whole_arrays_to_the_bit(seed):
    rng = np.random.default_rng(seed)
    h, w = (int(n) for n in rng.integers(40, 120, 2))
    a = rng.normal(100, 30, (h, w)).astype(np.float32)
    b = (a + rng.normal(0, 10, (h, w))).astype(np.float32)
    valid = np.zeros((h, w), bool)
    y0, x0 = int(rng.integers(0, h - 20)), int(rng.integers(0, w - 20))
    valid[y0 : y0 + int(rng.integers(8, 40)), x0 : x0 + int(rng.integers(8, 40))] = True
    valid &= rng.random((h, w)) < 0.9
    params = TextureParams(window_px=7, min_std=2.0)
    offset = (int(rng.integers(-2, 3)), int(rng.integers(-2, 3)))
    boxed = _best_ncc(a, b, valid, params, 2, offset)
    whole = _best_ncc_in(a, b, valid, params, 2, offset)
    assert whole[1].any()
    assert np.array_equal(boxed[0], whole[0]) and np.array_equal(boxed[1], whole[1])


def test_best_ncc_without_a_valid_pixel_is_nothing():
    a = np.random.default_rng(0).normal(100, 30, (30, 40)).astype(np.float32)
    best, textured = _best_ncc(a, a, np.zeros(a.shape, bool), TextureParams(), 2)
    assert not textured.any() and not best.any()


def test_the_cue_on_tiles_near_the_wanted_pixels_equals_the_cue_everywhere_there():
    a, b, valid = _sparse_case((150, 210))
    where = np.zeros(a.shape, bool)
    where[20:25, 30:33] = where[100:140, 180:182] = where[149, 0] = True
    params = TextureParams(window_px=11, min_std=2.0)
    box = (slice(0, 150), slice(0, 210))
    tiles = _tiles_near(where, (210, 150), box, reach=11 // 2 + 2)
    assert 0 < len(tiles.origins) < 35  # 7 x 5 tiles of 32 px in all: only some are computed
    full = _best_ncc(a, b, valid, params, radius=2)
    tiled = _best_ncc_on(tiles, a, b, valid, params, radius=2)
    near = cv2.dilate(where.view(np.uint8), np.ones((5, 5), np.uint8)).view(bool)
    for got, want in zip(tiled, full, strict=True):
        assert (got[near] == want[near]).all()
    # the tiles that hold a pixel of a smaller mask give the same NCC there, from fewer tiles
    layer = np.zeros(a.shape, bool)
    layer[100:110, 181] = True
    held = tiles.holding(layer)
    assert len(held.origins) == 1 and held.reach == tiles.reach
    for got, want in zip(_best_ncc_on(held, a, b, valid, params, radius=2), full, strict=True):
        assert (got[layer] == want[layer]).all()


def _wall_texture() -> np.ndarray:
    """A random pattern on the wall plane z = WALL_Z, 1 cm per texel, blurred a little."""
    return cv2.GaussianBlur(RNG.uniform(0, 255, (1200, 1200)).astype(np.float32), (0, 0), 1.5)


def _render(texture: np.ndarray, center_x: float) -> np.ndarray:
    """(H, W, 3) uint8 of a camera at (center_x, 0, 0) looking down +z at the wall."""
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float32)
    x = center_x + (u - INTR.cx) / INTR.fx * WALL_Z  # world X, Y where each ray meets the wall
    y = (v - INTR.cy) / INTR.fy * WALL_Z
    grey = cv2.remap(texture, x * 100 + 600, y * 100 + 600, cv2.INTER_LINEAR)
    return np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, axis=2)


def _two_cameras_on_the_wall() -> tuple[np.ndarray, np.ndarray, Pose, Pose, np.ndarray]:
    """The view at the origin and a neighbour 1 m aside, both looking at the textured wall:
    their images, poses and the wall's depth (H, W) float32."""
    texture = _wall_texture()
    view, other = _render(texture, 0.0), _render(texture, 1.0)
    pose_p = Pose(np.eye(3), np.zeros(3))
    pose_q = Pose.from_center(np.eye(3), np.array([1.0, 0.0, 0.0]))
    return view, other, pose_p, pose_q, np.full((INTR.height, INTR.width), WALL_Z, np.float32)


def test_an_old_object_in_front_of_a_textured_wall_is_found_and_the_wall_is_not():
    view, other, pose_p, pose_q, depth_q = _two_cameras_on_the_wall()
    depth_p = depth_q.copy()
    removed = np.zeros(depth_p.shape, bool)
    removed[40:80, 60:100] = True
    depth_p[removed] = 5.0  # the old cloud still has an object 5 m away: the photos do not
    params = TextureParams(enabled=True, scale=1.0, window_px=9)
    change, support = texture_change(
        view, depth_p, INTR, pose_p, [(other, depth_q, INTR, pose_q, None)], params, 0.3
    )
    inner = np.zeros_like(removed)
    inner[45:75, 65:95] = True
    wall = ~removed & (support > 0)
    wall[:, :10] = wall[:, -10:] = False
    assert np.median(change[inner]) > 0.6  # shifted by f·b·(1/5 − 1/10) = 15 px: decorrelated
    assert np.median(change[wall]) < 0.05 and (change[wall] > 0.5).mean() < 0.02
    # a cue computed only where asked is zero elsewhere and the same there
    only, _ = texture_change(
        view,
        depth_p,
        INTR,
        pose_p,
        [(other, depth_q, INTR, pose_q, None)],
        params,
        0.3,
        where=removed,
    )
    assert not only[~removed].any() and np.allclose(only[inner], change[inner], atol=1e-5)


def test_a_fine_texture_half_a_pixel_off_decorrelates_and_the_blur_restores_it():
    # blocks of 6 cm on the wall 10 m away: about one pixel each, finer than the cue's
    # whole-pixel search; the neighbour's pose is off by half a pixel at the wall
    blocks = RNG.uniform(0, 255, (180, 180)).astype(np.float32)
    fine = cv2.resize(blocks, (1200, 1200), interpolation=cv2.INTER_NEAREST)
    view, other = _render(fine, 0.0), _render(fine, 1.0)
    depth = np.full((INTR.height, INTR.width), WALL_Z, np.float32)
    pose_p = Pose(np.eye(3), np.zeros(3))
    inner = np.zeros(depth.shape, bool)
    inner[12:-12, 12:-12] = True
    medians = {}
    for off_px in (0.0, 0.5):
        centre = np.array([1.0 + off_px * WALL_Z / INTR.fx, 0.0, 0.0])
        seen = [(other, depth, INTR, Pose.from_center(np.eye(3), centre), None)]
        for blur in (0.0, 1.5):
            params = TextureParams(scale=1.0, window_px=9, max_global_shift_px=0.0, blur_px=blur)
            change, support = texture_change(
                view, depth, INTR, pose_p, seen, params, 0.3, blur_px=params.blur_px
            )
            medians[off_px, blur] = float(np.median(change[inner & (support > 0)]))
    assert medians[0.0, 0.0] < 0.02 and medians[0.0, 1.5] < 0.02  # in register: the same wall
    assert medians[0.5, 0.0] > 0.2  # half a pixel off: the blocks decorrelate
    assert medians[0.5, 1.5] < 0.08  # low-passed first: the wall again


def test_foreshortening_is_the_ratio_of_the_two_cameras_cosines_on_the_surface():
    depth = np.full((INTR.height, INTR.width), WALL_Z, np.float32)
    depth[:20, :30] = np.nan  # no surface there: no judgement
    points = surface_points(depth, camera_rays(INTR))
    normals = surface_normals(points)
    # the wall z = 10 faces the view; a camera 3 m aside sees it more obliquely
    ratio = foreshortening(points, normals, np.array([3.0, 0.0, 0.0]))
    x, y = points[..., 0], points[..., 1]
    cos_p = WALL_Z / np.sqrt(x * x + y * y + WALL_Z**2)
    cos_q = WALL_Z / np.sqrt((x - 3.0) ** 2 + y * y + WALL_Z**2)
    want = np.minimum(cos_p, cos_q) / np.maximum(cos_p, cos_q)
    inner = np.zeros(depth.shape, bool)
    inner[22:-2, 32:-2] = True
    np.testing.assert_allclose(ratio[inner], want[inner], rtol=1e-4)
    assert np.all(ratio[:20, :30] == 1.0) and np.all(ratio[:, :2] == 1.0)  # unknown: 1
    # a camera in the wall's plane sees it edge-on
    edge_on = foreshortening(points, normals, np.array([30.0, 0.0, WALL_Z]))
    assert np.all(edge_on[inner] < 0.01)


def test_a_neighbour_that_sees_the_surface_much_more_obliquely_gives_no_texture_evidence():
    view, other, pose_p, pose_q, depth = _two_cameras_on_the_wall()
    nbs = [(other, depth, INTR, pose_q, None)]
    base = TextureParams(enabled=True, scale=1.0, window_px=9)
    _, support = texture_change(view, depth, INTR, pose_p, nbs, base, 0.3)
    # 1 m aside at 10 m: the wall's foreshortening differs by < 1 % (ratio ≥ 0.99)
    loose = TextureParams(enabled=True, scale=1.0, window_px=9, min_foreshortening=0.9)
    _, support_loose = texture_change(view, depth, INTR, pose_p, nbs, loose, 0.3)
    assert support.sum() > 0.5 * support.size
    np.testing.assert_array_equal(support_loose, support)
    strict = TextureParams(enabled=True, scale=1.0, window_px=9, min_foreshortening=0.999)
    _, support_strict = texture_change(view, depth, INTR, pose_p, nbs, strict, 0.3)
    assert support_strict.sum() < 0.2 * support.sum()


def test_a_texture_cue_that_is_off_changes_no_hash():
    from streetcd.config import Config

    off = Config(DetectParams(texture=TextureParams(enabled=False, weight=0.2)))
    off_too = Config(DetectParams(texture=TextureParams(enabled=False)))
    on = Config(DetectParams(texture=TextureParams(enabled=True)))
    assert off.results_hash() == off_too.results_hash() != on.results_hash()
    assert on.results_hash() == Config().results_hash()  # on by default


def test_global_shift_finds_the_shift_of_the_whole_image_to_a_pixel():
    a = cv2.GaussianBlur(RNG.uniform(0, 255, (200, 260)).astype(np.float32), (0, 0), 1.2)
    valid = RNG.uniform(size=a.shape) > 0.1
    valid[:, :30] = valid[80:120] = False  # holes, alike in both images
    for dy, dx in ((5, -7), (0, 0), (-6, 3), (2, 1)):
        b = _shifted(a, dy, dx, 0.0) * 0.7 + 30 + RNG.normal(0, 3, a.shape).astype(np.float32)
        got = global_shift(a, b.astype(np.float32), valid, 8)
        # b[y - s] = a[y] for s = -(dy, dx): the convention of _best_ncc's shifts
        assert abs(got[0] + dy) <= 1 and abs(got[1] + dx) <= 1, (dy, dx, got)
    # beyond the search range: the largest shift allowed, never more
    b = _shifted(a, 12, 0, 0.0)
    assert abs(global_shift(a, b, valid, 8)[0]) <= 8


def test_best_ncc_around_an_offset_is_the_search_moved_there():
    a, b, valid = _sparse_case()
    params = TextureParams(window_px=7, min_std=2.0)
    b_far = _shifted(b, 4, 3, 0.0)  # the neighbour now moved by (5, 1) in all: beyond radius 1
    v_far = _shifted(valid, 4, 3, False)
    near, t_near = _best_ncc(a, b_far, v_far, params, radius=1)
    moved, t_moved = _best_ncc(a, b_far, v_far, params, radius=1, offset=(-5, -1))
    assert np.median(near[t_near]) < 0.5 < 0.95 < np.median(moved[t_moved])


def _yawed(pose: Pose, angle: float) -> Pose:
    rot, _ = cv2.Rodrigues(np.array([0.0, angle, 0.0]))
    return Pose.from_center(rot @ pose.R, pose.center)


def test_a_neighbour_misregistered_beyond_the_window_search_is_aligned_first():
    texture = _wall_texture()
    view, other = _render(texture, 0.0), _render(texture, 1.0)
    pose_p = Pose(np.eye(3), np.zeros(3))
    # the neighbour's pose is wrong by a yaw that moves its pixels by 7 px: its images and
    # poses disagree as a noisy registration's do
    pose_q = _yawed(Pose.from_center(np.eye(3), np.array([1.0, 0.0, 0.0])), 7.0 / INTR.fx)
    depth_q = np.full((INTR.height, INTR.width), WALL_Z, np.float32)
    depth_p = depth_q.copy()
    removed = np.zeros(depth_p.shape, bool)
    removed[40:80, 60:100] = True
    depth_p[removed] = 5.0
    inner = np.zeros_like(removed)
    inner[45:75, 65:95] = True
    nbs = [(other, depth_q, INTR, pose_q, None)]
    change = {}
    for search in (0.0, 12.0):
        params = TextureParams(scale=1.0, window_px=9, max_global_shift_px=search * 4000 / 160)
        change[search], support = texture_change(
            view, depth_p, INTR, pose_p, nbs, params, 0.3, registration_px=2.0
        )
        wall = ~removed & (support > 0)
        wall[:, :20] = wall[:, -20:] = False
        change[search] = (np.median(change[search][wall]), np.median(change[search][inner]))
    assert change[0.0][0] > 0.5  # without the alignment the wall decorrelates
    # with it only the object does (the yaw's perspective leaves the wall a little)
    assert change[12.0][0] < 0.15 and change[12.0][1] > 0.6


def test_the_alignment_does_not_take_a_removed_objects_parallax_for_registration_error():
    texture = _wall_texture()
    view, other = _render(texture, 0.0), _render(texture, 1.0)
    pose_p = Pose(np.eye(3), np.zeros(3))
    pose_q = Pose.from_center(np.eye(3), np.array([1.0, 0.0, 0.0]))
    depth_q = np.full((INTR.height, INTR.width), WALL_Z, np.float32)
    # a sparse cloud: the removed object's old surface is most of what has a surface
    depth_p = np.full(depth_q.shape, np.nan, np.float32)
    depth_p[:25] = WALL_Z
    removed = np.zeros(depth_p.shape, bool)
    removed[40:100, 30:130] = True
    depth_p[removed] = 5.0  # 15 px of parallax against the wall: within the search below
    inner = np.zeros_like(removed)
    inner[45:95, 35:125] = True
    params = TextureParams(scale=1.0, window_px=9, max_global_shift_px=20.0 * 4000 / 160)
    nbs = [(other, depth_q, INTR, pose_q, None)]
    change, _ = texture_change(view, depth_p, INTR, pose_p, nbs, params, 0.3, 2.0, where=removed)
    assert np.median(change[inner]) > 0.6


def test_the_working_size_is_the_scale_capped_at_the_working_width():
    params = TextureParams(scale=0.5, max_work_width_px=1024)
    assert work_size(params, (1080, 1920)) == (960, 540)
    assert work_size(params, (720, 1280)) == (640, 360)
    assert work_size(params, (3000, 4000)) == (1024, 768)


def test_uint8_grey_levels_are_the_float_ones_and_pass_through():
    rgb = np.random.default_rng(0).integers(0, 256, (7, 9, 3), dtype=np.uint8)
    g8 = grey_u8(rgb)
    assert g8.dtype == np.uint8 and g8.shape == (7, 9)
    assert np.array_equal(grey(g8), grey(rgb))
    assert grey_u8(g8) is g8


BOARD_Z = 5.0
BOARD = (-1.2, 0.6, -0.8, 0.8)  # x0, x1, y0, y1 (m) of a textured board in front of the wall


def _render_board(wall: np.ndarray, board: np.ndarray | None, center_x: float) -> np.ndarray:
    """:func:`_render` with a board at z = BOARD_Z in front of the wall (None: no board)."""
    image = _render(wall, center_x)
    if board is None:
        return image
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float32)
    x = center_x + (u - INTR.cx) / INTR.fx * BOARD_Z
    y = (v - INTR.cy) / INTR.fy * BOARD_Z
    on = (x >= BOARD[0]) & (x < BOARD[1]) & (y >= BOARD[2]) & (y < BOARD[3])
    grey = cv2.remap(board, x * 100 + 600, y * 100 + 600, cv2.INTER_LINEAR)
    image[on] = np.clip(grey, 0, 255).astype(np.uint8)[on][:, None]
    return image


def _board_depth(center_x: float) -> np.ndarray:
    """(H, W) float32 depth of the wall and the board seen from (center_x, 0, 0)."""
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float32)
    x = center_x + (u - INTR.cx) / INTR.fx * BOARD_Z
    y = (v - INTR.cy) / INTR.fy * BOARD_Z
    on = (x >= BOARD[0]) & (x < BOARD[1]) & (y >= BOARD[2]) & (y < BOARD[3])
    return np.where(on, BOARD_Z, WALL_Z).astype(np.float32)


@pytest.mark.parametrize("board_there", [True, False])
def test_a_near_object_off_the_backgrounds_shift_is_aligned_by_its_own_layer(board_there):
    wall, board = _wall_texture(), _wall_texture()
    # the neighbour was taken 0.4 m nearer the view than its pose says: the wall 10 m away moves by
    # f·δ/z = 6 px, which the background's alignment takes out, the board 5 m away by 12 px
    view = _render_board(wall, board if board_there else None, 0.0)
    other = _render_board(wall, board if board_there else None, 0.6)
    pose_p = Pose(np.eye(3), np.zeros(3))
    pose_q = Pose.from_center(np.eye(3), np.array([1.0, 0.0, 0.0]))
    depth_p, depth_q = _board_depth(0.0), _board_depth(1.0)  # the old cloud has the board
    on = depth_p == BOARD_Z
    inner = cv2.erode(on.view(np.uint8), np.ones((11, 11), np.uint8)).astype(bool)
    nbs = [(other, depth_q, INTR, pose_q, None)]
    change = {}
    for near_m in (0.0, 7.0):
        params = TextureParams(
            scale=1.0,
            window_px=9,
            max_global_shift_px=10.0 * 4000 / 160,
            near_layer_m=near_m,
            near_shift_px=16.0 * 4000 / 160,
        )
        near = near_layer(depth_p, None, params)
        got, _ = texture_change(
            view, depth_p, INTR, pose_p, nbs, params, 0.3, 2.0, where=on, near=near
        )
        change[near_m] = float(np.median(got[inner]))
    if board_there:  # off the background's shift by 6 px, beyond the windows' 2 px search
        assert change[0.0] > 0.5 and change[7.0] < 0.15
    else:  # a removed board: the wall behind is 15 px + 6 px off at its depth, past 10 px
        assert change[0.0] > 0.6 and change[7.0] > 0.6


def test_near_layer_settings_are_checked():
    with pytest.raises(InputError, match="near_layer_m"):
        TextureParams(near_layer_m=-1.0)
    with pytest.raises(InputError, match="near_shift_px"):
        TextureParams(near_shift_px=-1.0)


def test_the_near_layer_is_the_near_pixels_but_see_through_objects():
    depth = np.array([[3.0, 11.9, 12.0, np.nan]], np.float32)
    railing = np.array([[False, True, False, False]])
    params = TextureParams(near_layer_m=12.0)
    assert near_layer(depth, None, params).tolist() == [[True, True, False, False]]
    assert near_layer(depth, railing, params).tolist() == [[True, False, False, False]]
    assert near_layer(depth, None, TextureParams(near_layer_m=0.0)) is None
    assert near_layer(depth, None, TextureParams(near_layer_m=2.0)) is None
