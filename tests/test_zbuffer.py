"""Block and weighted-window z-buffers (paper §3.2, eq. 1–3) on synthetic scenes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from streetcd.config import ZBufferParams
from streetcd.detect.zbuffer import (
    _ERASED,
    CHUNK_POINTS,
    _box_outside,
    _normalised_bounds,
    _widen_arc,
    block_zbuffer,
    chunk_boxes,
    project_cloud,
    weighted_zbuffer,
)
from streetcd.errors import InputError
from streetcd.geometry.camera import look_at, project
from streetcd.types import Intrinsics

W, H, F = 400, 300, 400.0
INTR = Intrinsics(W, H, F, F, (W - 1) / 2, (H - 1) / 2)
FRONT_RGB, BACK_RGB = np.array([200, 60, 40]), np.array([60, 120, 200])


def _brute_block(uv, depth, shape, w):
    """Eq. 1 by a dictionary: per cell the smallest depth, ties to the lower index."""
    best: dict[tuple[int, int], int] = {}
    for i, ((u, v), z) in enumerate(zip(uv, depth, strict=True)):
        if not (np.isfinite(u) and np.isfinite(v) and np.isfinite(z) and z > 0):
            continue
        col, row = int(np.floor(u + 0.5)), int(np.floor(v + 0.5))
        if not (0 <= col < shape[1] and 0 <= row < shape[0]):
            continue
        key = (row // w, col // w)
        if key not in best or z < depth[best[key]]:
            best[key] = i
    return np.array(sorted(best.values()), dtype=np.int64)


@pytest.mark.parametrize("w", [1, 3, 5, 10])
def test_block_zbuffer_equals_brute_force(w):
    rng = np.random.default_rng(7)
    n = 3000
    uv = rng.uniform(-3, [63, 43], (n, 2))  # some points fall outside the 60×40 image
    depth = rng.uniform(0.5, 20, n).round(1)  # rounding makes ties
    uv[::97] = np.nan
    depth[::89] = -1.0
    kept = block_zbuffer(uv, depth, (40, 60), w)
    np.testing.assert_array_equal(kept, _brute_block(uv, depth, (40, 60), w))


def test_block_zbuffer_keeps_one_point_per_cell_the_nearest():
    rng = np.random.default_rng(3)
    uv = rng.uniform(-0.5, 49.4, (5000, 2))
    depth = rng.uniform(1, 10, 5000)
    kept = block_zbuffer(uv, depth, (50, 50), 5)
    cells = (np.floor(uv[:, 1] + 0.5) // 5) * 10 + np.floor(uv[:, 0] + 0.5) // 5
    assert len(np.unique(cells[kept])) == len(kept) == 100  # every cell occupied, once
    for c in range(100):
        members = np.flatnonzero(cells == c)
        assert depth[kept[cells[kept] == c][0]] == depth[members].min()


def test_block_zbuffer_assigns_points_to_the_pixel_that_contains_them():
    # u = 4.49 is in pixel 4 (cell 0 for w = 5), u = 4.5 in pixel 5 (cell 1)
    uv = np.array([[4.49, 0.0], [4.5, 0.0], [0.0, 0.0]])
    kept = block_zbuffer(uv, np.array([1.0, 1.0, 2.0]), (5, 10), 5)
    np.testing.assert_array_equal(kept, [0, 1])


def _fence_scene(rng, uniform_image=False):
    """The paper's Fig. 2 setting: a fence of 1 m bars with 0.4 m gaps 8 m in front of the
    camera, a wall 6 m behind it. Front points are 6 px apart, sparser than the 5 px block, so
    BWZB(5) lets wall points through the interspaces; the image shows the bars' colour where
    they cover the wall and the wall's colour in the gaps.

    Returns projected points, image, is_back, occluded (back points hidden by a bar).
    """
    pose = look_at([0, -8, 0], [0, 0, 0])

    def on_bar(x):
        return (np.mod(x, 1.4) < 1.0) & (np.abs(x) < 4.5)

    gx, gz = np.meshgrid(np.arange(-4.5, 4.5, 0.12), np.arange(-3.2, 3.2, 0.12))
    front = np.column_stack([gx.ravel(), np.zeros(gx.size), gz.ravel()])
    front[:, [0, 2]] += rng.uniform(-0.02, 0.02, (len(front), 2))
    front = front[on_bar(front[:, 0])]
    bx, bz = np.meshgrid(np.arange(-7.5, 7.5, 0.05), np.arange(-5.5, 5.5, 0.05))
    back = np.column_stack([bx.ravel(), np.full(bx.size, 6.0), bz.ravel()])
    xyz = np.vstack([front, back])
    is_back = np.r_[np.zeros(len(front), bool), np.ones(len(back), bool)]
    # a wall point is hidden where its ray crosses the fence plane (depth 8 of 14) on a bar
    xf, zf = back[:, 0] * 8 / 14, back[:, 2] * 8 / 14
    occluded = np.r_[np.zeros(len(front), bool), on_bar(xf) & (np.abs(zf + 0.06) < 3.26)]

    v, u = np.mgrid[0:H, 0:W]
    xpix, zpix = (u - INTR.cx) / F * 8, -(v - INTR.cy) / F * 8
    bars = on_bar(xpix) & (zpix > -3.22) & (zpix < 3.22)
    image = np.where(bars[..., None], FRONT_RGB, BACK_RGB) + rng.integers(-1, 2, (H, W, 3))
    if uniform_image:
        image[:] = FRONT_RGB
    points = project_cloud(xyz, np.zeros(len(xyz), np.uint8), INTR, pose, 60.0)
    return points, image.astype(np.uint8), is_back[points.index], occluded[points.index]


@pytest.mark.parametrize("focal_px", [None, F], ids=["paper", "metric"])
def test_weighted_zbuffer_removes_back_face_points_and_keeps_front_points(focal_px):
    points, image, is_back, occluded = _fence_scene(np.random.default_rng(1))
    b5 = block_zbuffer(points.uv, points.depth, (H, W), 5)
    b10 = block_zbuffer(points.uv, points.depth, (H, W), 10)
    ww = weighted_zbuffer(points.uv, points.depth, image, ZBufferParams(), focal_px=focal_px)
    assert set(ww) <= set(b5)
    assert occluded[b5].sum() > 500  # the scene does put wall points through the fence
    assert occluded[ww].sum() <= 0.1 * occluded[b5].sum()  # ≥ 90 % of them removed
    assert (~is_back[ww]).sum() > (~is_back[b10]).sum()  # more fence points than BWZB w = 10
    assert (~is_back[ww]).sum() == (~is_back[b5]).sum()  # a flat fence loses no point
    visible_wall = is_back & ~occluded
    assert visible_wall[ww].sum() >= 0.95 * visible_wall[b5].sum()  # seen through the gaps


def test_weighted_zbuffer_uses_the_image_colour_at_depth_edges():
    # With a uniform image eq. 2 cannot tell the gaps from the bars: wall points seen through
    # the gaps next to a bar are then erased too.
    rng = np.random.default_rng(1)
    points, image, is_back, occluded = _fence_scene(rng)
    points_u, image_u, _, _ = _fence_scene(np.random.default_rng(1), uniform_image=True)
    visible_wall = is_back & ~occluded
    with_colour = visible_wall[weighted_zbuffer(points.uv, points.depth, image, ZBufferParams())]
    without = visible_wall[weighted_zbuffer(points_u.uv, points_u.depth, image_u, ZBufferParams())]
    assert without.sum() < 0.9 * with_colour.sum()


@pytest.mark.parametrize("focal_px", [None, F], ids=["paper", "metric"])
def test_weighted_zbuffer_keeps_ground_seen_at_a_grazing_angle(focal_px):
    # Guards the surround rule of the metric variant: a metric angle alone erases a road seen
    # from 1.6 m (its depth grows faster along the image than sideways).
    rng = np.random.default_rng(5)
    pose = look_at([0, 0, 1.6], [0, 10, 1.6])
    n = 60000
    ground = np.column_stack([rng.uniform(-6, 6, n), rng.uniform(4, 15, n), np.zeros(n)])
    points = project_cloud(ground, np.full(n, 11, np.uint8), INTR, pose, 60.0)
    image = np.full((H, W, 3), 90, np.uint8)
    b5 = block_zbuffer(points.uv, points.depth, (H, W), 5)
    ww = weighted_zbuffer(points.uv, points.depth, image, ZBufferParams(), focal_px=focal_px)
    assert len(b5) > 1000
    np.testing.assert_array_equal(ww, b5)


def test_weighted_zbuffer_erases_a_point_behind_a_supporting_neighbour():
    # Eq. 3 worked by hand: neighbour 3 px away and 4 m nearer → θ = atan(4/3) = 53° > 45°.
    image = np.full((20, 20, 3), 50, np.uint8)
    uv = np.array([[8.0, 10.0], [11.0, 10.0]])  # cells 1 and 2 of w = 5
    assert list(weighted_zbuffer(uv, np.array([10.0, 6.0]), image, ZBufferParams())) == [1]
    # 2 m nearer: θ = atan(2/3) = 34° < 45°, both stay
    assert list(weighted_zbuffer(uv, np.array([10.0, 8.0]), image, ZBufferParams())) == [0, 1]
    # different colour (Δc = 100 ≫ δ): no support, both stay
    image[10, 11] = [150, 50, 50]
    assert list(weighted_zbuffer(uv, np.array([10.0, 6.0]), image, ZBufferParams())) == [0, 1]
    # outside the 15 px window (8 px > 7): both stay
    uv2 = np.array([[8.0, 10.0], [16.0, 10.0]])
    image[:] = 50
    assert list(weighted_zbuffer(uv2, np.array([20.0, 6.0]), image, ZBufferParams())) == [0, 1]


def test_metric_variant_erases_only_a_surrounded_point():
    # Centre 10 m deep; nearer supporters (8 m) 4 px away: metric tan θ = 2 / (4 · 8 / 400) = 25.
    image = np.full((40, 40, 3), 50, np.uint8)
    centre = [[22.0, 22.0]]  # cell (4, 4) of w = 5; the others in cells of their own
    left_right = [[18.0, 22.0], [26.0, 22.0]]  # opposite sides: gap 180° → surrounded
    below = [[18.0, 26.0], [26.0, 26.0]]  # one side only: gap 270° → kept (a slope)
    for others, erased in ((left_right, True), (below, False)):
        uv = np.array(centre + others)
        kept = weighted_zbuffer(
            uv, np.array([10.0, 8.0, 8.0]), image, ZBufferParams(), focal_px=400.0
        )
        assert (0 not in kept) == erased
        assert {1, 2} <= set(kept)


def _near_pole_scene(rng):
    """A pole face 1 m from the camera (0.3 × 0.6 m, points 0.06 m apart: 24 px, wider than
    w1 = 15 px) in front of a wall 8 m away (points 0.05 m apart: 2.5 px). The image shows
    the pole's colour over its silhouette and the wall's elsewhere.

    Returns projected points, image, is_pole, occluded (wall points behind the pole).
    """
    pose = look_at([0, -1, 0], [0, 0, 0])
    px, pz = np.meshgrid(np.linspace(-0.15, 0.15, 6), np.linspace(-0.3, 0.3, 11))
    front = np.column_stack([px.ravel(), np.zeros(px.size), pz.ravel()])
    wx, wz = np.meshgrid(np.arange(-3.0, 3.0, 0.05), np.arange(-2.4, 2.4, 0.05))
    wall = np.column_stack([wx.ravel(), np.full(wx.size, 7.0), wz.ravel()])
    wall[:, [0, 2]] += rng.uniform(-0.01, 0.01, (len(wall), 2))
    xyz = np.vstack([front, wall])
    is_pole = np.r_[np.ones(len(front), bool), np.zeros(len(wall), bool)]
    # a wall point is hidden where its ray crosses the pole plane (depth 1 of 8) on the pole
    hidden = (np.abs(wall[:, 0] / 8) < 0.15) & (np.abs(wall[:, 2] / 8) < 0.3)
    occluded = np.r_[np.zeros(len(front), bool), hidden]
    v, u = np.mgrid[0:H, 0:W]
    # + 0.5 px: a pole point on the silhouette belongs to the pixel that contains it
    on_pole = (np.abs(u - INTR.cx) <= 0.15 * F + 0.5) & (np.abs(v - INTR.cy) <= 0.3 * F + 0.5)
    image = np.where(on_pole[..., None], FRONT_RGB, BACK_RGB) + rng.integers(-1, 2, (H, W, 3))
    points = project_cloud(xyz, np.zeros(len(xyz), np.uint8), INTR, pose, 60.0)
    return points, image.astype(np.uint8), is_pole[points.index], occluded[points.index]


def test_adaptive_window_removes_the_wall_seen_through_a_near_pole():
    points, image, is_pole, occluded = _near_pole_scene(np.random.default_rng(3))
    b5 = block_zbuffer(points.uv, points.depth, (H, W), 5)
    paper = ZBufferParams(point_spacing_m=0.0)
    fixed = weighted_zbuffer(points.uv, points.depth, image, paper, focal_px=F)
    adaptive = weighted_zbuffer(
        points.uv, points.depth, image, ZBufferParams(point_spacing_m=0.06), focal_px=F
    )
    assert occluded[b5].sum() > 300  # BWZB lets the wall through the 24 px interspaces
    # w1 = 15 px reaches no pole point from most of them
    assert occluded[fixed].sum() > 0.5 * occluded[b5].sum()
    assert occluded[adaptive].sum() == 0
    assert is_pole[adaptive].sum() == is_pole[b5].sum() == 66  # the pole keeps its points
    # wall points whose pixel shows the wall all stay (the pixels on the silhouette show the
    # pole: those are not told apart by eq. 2)
    col, row = np.floor(points.uv + 0.5).astype(int).T
    shows_wall = np.abs(image[row, col].astype(int) - BACK_RGB).max(axis=1) <= 1
    seen_wall = ~is_pole & ~occluded & shows_wall
    assert seen_wall[b5].sum() > 1500
    assert seen_wall[adaptive].sum() == seen_wall[b5].sum()


def test_without_reach_colour_a_textured_near_pole_still_hides_the_wall_behind_it():
    # The same pole painted in stripes 0.1 m wide (40 px): its points 24 px apart lie on
    # pixels of other colours, so eq. 2's colour term lets most of them support nothing
    # beyond w1 and the wall shows through; counted within w1 only, it hides the wall again.
    points, image, is_pole, occluded = _near_pole_scene(np.random.default_rng(3))
    col = np.arange(W)
    stripe = ((col - INTR.cx) // (0.1 * F)).astype(int) % 2 == 1
    on_pole = np.all(np.abs(image.astype(int) - FRONT_RGB) <= 1, axis=2)
    image = image.copy()
    image[on_pole & stripe[None, :]] = [40, 160, 60]
    b5 = block_zbuffer(points.uv, points.depth, (H, W), 5)
    # the pole's 0.06 m is the cloud's own measured spacing, sparser than point_spacing_m
    own = np.full(len(points.depth), 0.06)
    colour = ZBufferParams(point_spacing_m=0.01, reach_colour=True)
    kept = weighted_zbuffer(points.uv, points.depth, image, colour, focal_px=F, spacing_m=own)
    assert occluded[kept].sum() > 0.4 * occluded[b5].sum()  # 514 of 1,102
    near = dataclasses.replace(colour, reach_colour=False)
    kept = weighted_zbuffer(points.uv, points.depth, image, near, focal_px=F, spacing_m=own)
    # 41 stay: beside a stripe's edge, the one pole column within reach on that side is
    # within w1 and of the other colour, so eq. 2 still turns it away
    assert occluded[kept].sum() < 0.05 * occluded[b5].sum()
    assert is_pole[kept].sum() == 66  # the pole keeps its points
    col_px, row_px = np.floor(points.uv + 0.5).astype(int).T
    shows_wall = np.abs(image[row_px, col_px].astype(int) - BACK_RGB).max(axis=1) <= 1
    seen_wall = ~is_pole & ~occluded & shows_wall
    assert seen_wall[kept].sum() == seen_wall[b5].sum()  # the wall beside it all stays
    # where point_spacing_m alone reaches as far (a dense cloud), the colour term stays
    dense = ZBufferParams(point_spacing_m=0.06, reach_colour=False)
    kept_dense = weighted_zbuffer(points.uv, points.depth, image, dense, focal_px=F)
    assert occluded[kept_dense].sum() > 0.4 * occluded[b5].sum()


def test_adaptive_window_keeps_a_near_wall_seen_at_an_angle():
    # A plain wall 0.7–2 m away at 45°, points 0.06 m apart (11–35 px): the adaptive window
    # is wide here, the image uniform (every neighbour supports), and depth grows across it;
    # the surround rule must still keep ≥ 99 % of its points.
    rng = np.random.default_rng(4)
    x, z = np.meshgrid(np.arange(-0.6, 1.5, 0.06), np.arange(-0.6, 0.6, 0.06))
    wall = np.column_stack([x.ravel(), x.ravel(), z.ravel()])
    wall += rng.uniform(-0.01, 0.01, wall.shape)
    points = project_cloud(
        wall, np.zeros(len(wall), np.uint8), INTR, look_at([0, -1, 0], [0, 0, 0]), 60.0
    )
    image = np.full((H, W, 3), 90, np.uint8)
    b5 = block_zbuffer(points.uv, points.depth, (H, W), 5)
    adaptive = weighted_zbuffer(
        points.uv, points.depth, image, ZBufferParams(point_spacing_m=0.06), focal_px=F
    )
    assert len(b5) > 300
    assert len(adaptive) >= 0.99 * len(b5)


def test_weighted_zbuffer_rejects_a_grey_image():
    with pytest.raises(InputError, match="uint8 RGB"):
        weighted_zbuffer(np.zeros((1, 2)), np.ones(1), np.zeros((5, 5), np.uint8), ZBufferParams())


def test_project_cloud_keeps_points_in_front_in_range_and_in_the_image():
    rng = np.random.default_rng(11)
    pose = look_at([0, 0, 0], [0, 10, 0])
    xyz = rng.uniform([-30, -30, -30], [30, 80, 30], (20000, 3))
    classes = rng.integers(1, 70, len(xyz)).astype(np.uint8)
    pts = project_cloud(xyz, classes, INTR, pose, 50.0)
    uv, depth = project(xyz, INTR, pose)
    with np.errstate(invalid="ignore"):
        expect = (
            (depth > 0)
            & (np.linalg.norm(xyz, axis=1) <= 50.0)
            & (uv[:, 0] >= -0.5)
            & (uv[:, 0] < W - 0.5)
            & (uv[:, 1] >= -0.5)
            & (uv[:, 1] < H - 0.5)
        )
    np.testing.assert_array_equal(pts.index, np.flatnonzero(expect))
    np.testing.assert_allclose(pts.uv, uv[expect], rtol=0, atol=1e-9)
    np.testing.assert_allclose(pts.depth, depth[expect], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(pts.classes, classes[expect])


@pytest.mark.parametrize(
    "centre, target, max_range",
    [
        ([0, 0, 0], [0, 10, 0], 50.0),
        ([0, 150, 2], [0, 100, 0], 30.0),
        ([5, 60, 1], [40, 60, 1], 45.0),
    ],
)
def test_project_cloud_skips_whole_chunks_without_losing_a_point(centre, target, max_range):
    """A street-like cloud in scan order (sorted along the street), so that runs of
    consecutive points are compact and most runs' boxes lie outside any one view: the
    points kept are exactly those of the per-point test, and boxes were skipped."""
    rng = np.random.default_rng(5)
    xyz = rng.uniform([-15, -20, -1], [15, 220, 20], (120_000, 3))
    xyz = xyz[np.argsort(xyz[:, 1], kind="stable")]
    pose = look_at(centre, target)
    pts = project_cloud(xyz, np.zeros(len(xyz), np.uint8), INTR, pose, max_range)
    uv, depth = project(xyz, INTR, pose)
    with np.errstate(invalid="ignore"):
        expect = (
            (depth > 0)
            & (np.linalg.norm(xyz - np.asarray(centre, float), axis=1) <= max_range)
            & (uv[:, 0] >= -0.5)
            & (uv[:, 0] < W - 0.5)
            & (uv[:, 1] >= -0.5)
            & (uv[:, 1] < H - 0.5)
        )
    np.testing.assert_array_equal(pts.index, np.flatnonzero(expect))
    boxes = chunk_boxes(xyz)
    assert boxes is chunk_boxes(xyz) and len(boxes) == -(-len(xyz) // CHUNK_POINTS)
    bounds = _normalised_bounds(INTR)
    skipped = [_box_outside(b, pose.R, pose.t, max_range**2, bounds) for b in boxes]
    assert 0.3 < np.mean(skipped) < 1.0


def test_project_cloud_drops_points_folded_into_the_image_by_distortion():
    # k1 < 0 makes r_d = r (1 + k1 r²) fall back towards the centre far outside the view.
    intr = Intrinsics(W, H, F, F, (W - 1) / 2, (H - 1) / 2, dist=(-0.2, 0.0, 0.0, 0.0, 0.0))
    pose = look_at([0, 0, 0], [0, 10, 0])
    xyz = np.array([[0.0, 10.0, 0.0], [20.0, 10.0, 0.0]])  # x/z = 2 → x_d = 2 (1 − 0.8) = 0.4
    uv, _ = project(xyz, intr, pose)
    assert 0 <= uv[1, 0] < W  # the 63° off-axis point lands inside the 53° wide image
    pts = project_cloud(xyz, np.zeros(2, np.uint8), intr, pose, 60.0)
    np.testing.assert_array_equal(pts.index, [0])


def _brute_weighted(uv, depth, image, params, focal_px, spacing_m=None):
    """Eq. 2–3 with the metric surround test and the adaptive window, point by point over
    every other BWZB point (no search radius, no cell order): what the kernel must keep."""
    kept = _brute_block(uv, depth, image.shape[:2], params.block_window_px)
    half = params.weighted_window_px // 2
    tan_t = np.tan(np.radians(params.max_angle_deg))
    pix = np.floor(uv[kept] + 0.5).astype(int)
    rgb = image[pix[:, 1], pix[:, 0]].astype(float)
    s = (
        params.point_spacing_m
        if spacing_m is None
        else np.maximum(params.point_spacing_m, spacing_m[kept])
    )
    reach = np.maximum(half, focal_px * s / depth[kept])
    out = []
    for j, c in enumerate(kept):
        dz = depth[c] - depth[kept]
        du, dv = uv[kept, 0] - uv[c, 0], uv[kept, 1] - uv[c, 1]
        dd = np.sqrt(du * du + dv * dv)
        drgb = rgb - rgb[j]
        dc = np.sqrt((drgb * drgb).sum(axis=1))
        shrink = np.where(reach <= half, 1.0, half / reach)
        # without reach_colour, eq. 2's colour term only within the reach point_spacing_m gives
        base = np.maximum(half, focal_px * params.point_spacing_m / depth[kept])
        within = (np.abs(du) <= base) & (np.abs(dv) <= base)
        colour = np.where(within | params.reach_colour, dc / params.delta_color, 0.0)
        support = (
            (dz > 0)
            & (np.abs(du) <= reach)
            & (np.abs(dv) <= reach)
            & (dd * shrink / params.gamma_px + colour < -np.log(params.tau))
        )
        if np.any(support & (dz > tan_t * dd)):
            continue
        steep = support & (dz > tan_t * dd * depth[kept] / focal_px)
        if steep.sum() >= 2:
            a = np.sort(np.arctan2(dv[steep], du[steep]))
            if max(a[0] + 2 * np.pi - a[-1], np.diff(a).max()) <= np.pi + 1e-9:
                continue
        out.append(c)
    return np.array(out, dtype=np.int64)


@pytest.mark.parametrize(
    ("spacing", "own", "reach_colour"),
    [(0.0, False, True), (0.12, False, True), (0.12, True, True), (0.12, True, False)],
)
def test_weighted_zbuffer_equals_brute_force_with_the_adaptive_window(spacing, own, reach_colour):
    # guards the packed, occupied-cells-only scan of _weighted_erase: scattered points at
    # random depths (near ones reach far) on a blocky image, against eq. 2–3 point by point
    rng = np.random.default_rng(11)
    n = 1500
    uv = rng.uniform(-0.5, [119.4, 79.4], (n, 2))
    depth = rng.choice([1.0, 2.0, 3.0, 8.0, 20.0], n) + rng.uniform(0, 0.3, n)
    blocks = rng.integers(0, 4, (8, 12)) * 60
    image = np.repeat(np.repeat(blocks, 10, axis=0), 10, axis=1)[..., None].repeat(3, axis=2)
    image = np.ascontiguousarray(image.astype(np.uint8))
    params = ZBufferParams(point_spacing_m=spacing, reach_colour=reach_colour)
    # own: the cloud's measured spacing per point, sparser than point_spacing_m for some
    spacing_m = rng.choice([0.0, 0.3], n) if own else None
    got = weighted_zbuffer(uv, depth, image, params, focal_px=100.0, spacing_m=spacing_m)
    want = _brute_weighted(uv, depth, image, params, 100.0, spacing_m)
    assert 0 < len(got) < len(_brute_block(uv, depth, image.shape[:2], 5))  # some erased
    np.testing.assert_array_equal(got, want)


def _surrounded(directions: np.ndarray) -> bool:
    """The largest gap between the directions' angles is ≤ 180°, by sorting angles."""
    a = np.sort(np.arctan2(directions[:, 1], directions[:, 0]))
    return bool(max(a[0] + 2 * np.pi - a[-1], np.diff(a).max(initial=0.0)) <= np.pi + 1e-9)


def test_arc_of_steep_supporters_matches_the_largest_angular_gap_in_any_order():
    # guards _widen_arc, which decides the surround rule with cross-product signs, one
    # direction at a time: it must agree with sorting the angles, whatever the order
    rng = np.random.default_rng(5)
    cases = [np.array([[1.0, 0.0], [-2.0, 0.0]]), np.array([[0.0, 3.0], [0.0, 1.0]])]
    cases += [np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])]  # exactly 180° gap
    cases += [np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, -1e-3]])]  # just under 180°
    for _ in range(300):
        n = int(rng.integers(1, 9))
        spread = rng.uniform(1.0, 2 * np.pi)  # narrow and wide fans
        angles = rng.uniform(0, spread, n) + rng.uniform(0, 2 * np.pi)
        cases.append(np.column_stack([np.cos(angles), np.sin(angles)]) * rng.uniform(1, 9, (n, 1)))
    surrounded = 0
    for directions in cases:
        want = len(directions) >= 2 and _surrounded(directions)
        surrounded += want
        for order in (directions, directions[::-1], rng.permutation(directions)):
            state, arc = 0, np.zeros(4)
            for du, dv in order:
                if state != _ERASED:
                    state = _widen_arc(state, arc, du, dv)
            assert (state == _ERASED) == want, directions
    assert 50 < surrounded < len(cases) - 50  # both outcomes are exercised
