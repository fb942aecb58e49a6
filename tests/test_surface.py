"""View-dependent triangulation and depth / class rasters (paper §3.3) on synthetic scenes."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import binary_erosion
from scipy.spatial import ConvexHull, Delaunay

from streetcd import classes as cls
from streetcd.config import REFERENCE_WIDTH_PX, DetectParams, SurfaceParams, ZBufferParams
from streetcd.detect.surface import surface_for_view, triangulate, view_surface
from streetcd.detect.zbuffer import block_zbuffer, project_cloud
from streetcd.errors import EmptyViewError, InputError
from streetcd.geometry.camera import look_at, pixel_grid, project
from streetcd.types import Intrinsics

W, H, F = 320, 240, 300.0
INTR = Intrinsics(W, H, F, F, (W - 1) / 2, (H - 1) / 2)
# Pixels 5 px (one z-buffer cell) or more from the image border. Points outside the image take
# no part, so the outermost pixels are covered only where a point lies nearer the border than
# their centre.
INTERIOR = np.zeros((H, W), bool)
INTERIOR[5:-5, 5:-5] = True


def surface_params(edge_px: float, jump_m: float = 0.5) -> SurfaceParams:
    """Params whose edge threshold is ``edge_px`` at this test's image width."""
    return SurfaceParams(max_depth_jump_m=jump_m, max_edge_px=edge_px * REFERENCE_WIDTH_PX / W)


def _plane_points(rng, n, corner, e1, e2):
    """n points uniformly on the parallelogram corner + s e1 + t e2, s, t in [0, 1]."""
    s, t = rng.uniform(0, 1, (2, n, 1))
    return np.asarray(corner) + s * np.asarray(e1) + t * np.asarray(e2)


def _inside_hull(uv, offset=0.0):
    """(H, W) bool: pixel centres (+ offset px) inside the convex hull of ``uv``."""
    eq = ConvexHull(uv).equations  # rows (a, b, c): inside where a u + b v + c <= 0
    return ((pixel_grid(H, W) + offset) @ eq[:, :2].T + eq[:, 2] <= 0).all(axis=1).reshape(H, W)


def _analytic_plane_depth(pose, point, normal):
    """(H, W) camera z of the plane through ``point`` with ``normal`` (world) per pixel."""
    n_cam = pose.R @ np.asarray(normal, float)
    d = n_cam @ (pose.R @ np.asarray(point, float) + pose.t)
    grid = pixel_grid(H, W)
    rays = np.column_stack(
        [(grid[:, 0] - INTR.cx) / F, (grid[:, 1] - INTR.cy) / F, np.ones(len(grid))]
    )
    return (d / (rays @ n_cam)).reshape(H, W)


@pytest.mark.parametrize("cell_px", [1, 5])
def test_depth_of_a_tilted_plane_is_exact_inside_the_triangulated_area(cell_px):
    rng = np.random.default_rng(2)
    pose = look_at([1.0, -9.0, 2.5], [0.0, 0.0, 1.0])
    # a façade-sized plane turned 30° about the vertical
    corner, e1, e2 = [-5.0, -2.0, -1.0], [8.66, 5.0, 0.0], [0.0, 0.0, 6.0]
    pts = _plane_points(rng, 40000, corner, e1, e2)
    uv, depth = project(pts, INTR, pose)
    if cell_px > 1:  # as the detector does: z-buffer first, triangulate on the same grid
        keep = block_zbuffer(uv, depth, (H, W), cell_px)
        uv_kept, depth_kept = uv[keep], depth[keep]
    else:
        uv_kept, depth_kept = uv, depth
    surf = view_surface(
        uv_kept,
        depth_kept,
        np.full(len(depth_kept), cls.BUILDING, np.uint8),
        (H, W),
        surface_params(12.0),
        cell_px=cell_px,
    )
    truth = _analytic_plane_depth(pose, corner, np.cross(e1, e2))
    assert surf.valid.sum() > 0.3 * H * W
    assert np.abs(surf.depth[surf.valid] - truth[surf.valid]).max() < 1e-3
    assert np.all(surf.classes[surf.valid] == cls.BUILDING)
    assert np.all(np.isnan(surf.depth[~surf.valid])) and np.all(surf.classes[~surf.valid] == 0)
    # and it covers the plane without holes: every pixel inside the hull of the points that
    # fall in the image, away from its rim and from the image border
    in_image = (uv_kept > -0.5).all(axis=1) & (uv_kept[:, 0] < W - 0.5) & (uv_kept[:, 1] < H - 0.5)
    inside = binary_erosion(_inside_hull(uv_kept[in_image]), iterations=2 * cell_px)
    assert surf.valid[inside & INTERIOR].all()


def _box_and_wall(rng):
    """A wall 10 m away, a 2 × 2 m box face 2 m in front of it; visible points only."""
    pose = look_at([0.0, -10.0, 0.0], [0.0, 0.0, 0.0])
    wall = _plane_points(rng, 60000, [-6, 0, -4.5], [12, 0, 0], [0, 0, 9])
    hidden = (np.abs(wall[:, 0] * 8 / 10) < 1.0) & (np.abs(wall[:, 2] * 8 / 10) < 1.0)
    box = _plane_points(rng, 15000, [-1, -2, -1], [2, 0, 0], [0, 0, 2])
    xyz = np.vstack([wall[~hidden], box])
    labels = np.r_[np.full((~hidden).sum(), cls.BUILDING), np.full(len(box), cls.CAR)]
    pts = project_cloud(xyz, labels.astype(np.uint8), INTR, pose, 60.0)
    return pts


def test_box_in_front_of_a_wall_gets_its_own_depth_and_no_bridging_triangles():
    pts = _box_and_wall(np.random.default_rng(4))
    params = surface_params(12.0)
    tris = triangulate(pts.uv, pts.depth, W, params)
    on_box = pts.classes == cls.CAR
    mixed = on_box[tris].any(axis=1) & ~on_box[tris].all(axis=1)
    assert len(tris) > 1000 and not mixed.any()  # the depth-jump filter cut every bridge

    surf = view_surface(pts.uv, pts.depth, pts.classes, (H, W), params)
    u, v = np.meshgrid(np.arange(W) - INTR.cx, np.arange(H) - INTR.cy)
    box_px = F * 1.0 / 8.0  # the box's half size in pixels
    well_inside = (np.abs(u) < box_px - 3) & (np.abs(v) < box_px - 3)
    well_outside = ((np.abs(u) > box_px + 3) | (np.abs(v) > box_px + 3)) & INTERIOR
    assert surf.valid[well_inside].all() and surf.valid[well_outside].mean() > 0.99
    np.testing.assert_allclose(surf.depth[well_inside], 8.0, atol=1e-3)
    np.testing.assert_allclose(surf.depth[well_outside & surf.valid], 10.0, atol=1e-3)
    assert np.all(surf.classes[well_inside] == cls.CAR)
    assert np.all(surf.classes[well_outside & surf.valid] == cls.BUILDING)
    # nothing in between: every surface pixel is on the box or on the wall
    d = surf.depth[surf.valid]
    assert np.all((np.abs(d - 8.0) < 1e-3) | (np.abs(d - 10.0) < 1e-3))
    # the depth step leaves a gap instead of a ramp: some pixels at the rim have no surface
    rim = ~well_inside & ~well_outside
    assert (~surf.valid[rim]).sum() > 0


def test_depth_jump_threshold_decides_whether_a_step_is_bridged():
    pts = _box_and_wall(np.random.default_rng(4))
    on_box = pts.classes == cls.CAR
    bridging = triangulate(pts.uv, pts.depth, W, surface_params(12.0, jump_m=2.5))
    assert (on_box[bridging].any(axis=1) & ~on_box[bridging].all(axis=1)).sum() > 50


def test_edge_filter_drops_long_triangles():
    # a 10 px lattice with one far point: short-edge triangles stay, ones to the far point go
    u, v = np.meshgrid(np.arange(20, 101, 10.0), np.arange(20, 101, 10.0))
    uv = np.vstack([np.column_stack([u.ravel(), v.ravel()]), [[150.0, 60.0]]])
    depth = np.full(len(uv), 5.0)
    far = len(uv) - 1
    short = triangulate(uv, depth, W, surface_params(15.0))
    assert len(short) == 2 * 8 * 8 and not (short == far).any()
    edges = np.linalg.norm(uv[short] - uv[np.roll(short, 1, axis=1)], axis=2)
    assert edges.max() <= 15.0
    loose = triangulate(uv, depth, W, surface_params(60.0))
    assert (loose == far).any(axis=1).sum() >= 3
    assert len(triangulate(uv, depth, W, surface_params(9.0))) == 0


def test_triangulation_matches_delaunay_on_scattered_points():
    rng = np.random.default_rng(9)
    uv = rng.uniform(10, [W - 10, H - 10], (3000, 2))
    depth = np.full(len(uv), 7.0)
    ours = triangulate(uv, depth, W, surface_params(1e4))
    ref = np.sort(Delaunay(uv).simplices, axis=1)
    common = len({tuple(t) for t in ours} & {tuple(t) for t in ref})
    # The Voronoi dual on a 1 px grid misses Voronoi edges shorter than a pixel, so some
    # near-cocircular quads get the other diagonal; the area shows it is still a triangulation.
    assert common >= 0.85 * len(ref)

    # no holes inside the hull (away from its rim, where Voronoi vertices fall outside the
    # grid), and overlaps (the other diagonal next to a kept one) on under 0.5 % of it
    count = _coverage_count(uv, ours, (H, W))
    inside = _inside_hull(uv, offset=0.25)
    interior = binary_erosion(inside, iterations=15, border_value=0)
    assert (count[interior] >= 1).all()
    assert (count[interior] > 1).mean() < 0.005


def _coverage_count(uv, tris, shape):
    """(H, W) number of triangles containing each sample point (pixel centre + 0.25 px)."""
    count = np.zeros(shape, int)
    for a, b, c in uv[tris]:
        lo = np.floor(np.minimum(np.minimum(a, b), c)).astype(int)
        hi = np.ceil(np.maximum(np.maximum(a, b), c)).astype(int)
        gu, gv = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
        pu, pv = gu + 0.25, gv + 0.25
        s1 = (b[0] - a[0]) * (pv - a[1]) - (b[1] - a[1]) * (pu - a[0])
        s2 = (c[0] - b[0]) * (pv - b[1]) - (c[1] - b[1]) * (pu - b[0])
        s3 = (a[0] - c[0]) * (pv - c[1]) - (a[1] - c[1]) * (pu - c[0])
        hit = ((s1 > 0) & (s2 > 0) & (s3 > 0)) | ((s1 < 0) & (s2 < 0) & (s3 < 0))
        ok = hit & (gu >= 0) & (gv >= 0) & (gu < shape[1]) & (gv < shape[0])
        count[gv[ok], gu[ok]] += 1
    return count


def test_grid_cells_of_the_zbuffer_window_lose_no_zbuffered_point():
    rng = np.random.default_rng(6)
    uv = rng.uniform(-0.5, [W - 0.5, H - 0.5], (50000, 2))
    depth = rng.uniform(5, 5.2, len(uv))
    kept = block_zbuffer(uv, depth, (H, W), 5)
    tris = triangulate(uv[kept], depth[kept], W, surface_params(20.0), cell_px=5)
    assert len(np.unique(tris)) == len(kept)


def test_class_raster_takes_the_nearest_point_and_stops_at_the_surface():
    # a left half of class POLE and a right half of class SIGN, with a gap without points
    u, v = np.meshgrid(np.arange(20, 301, 4.0), np.arange(20, 221, 4.0))
    uv = np.column_stack([u.ravel(), v.ravel()])
    keep = (uv[:, 0] < 140) | (uv[:, 0] > 180)
    uv = uv[keep]
    labels = np.where(uv[:, 0] < 100, cls.POLE, cls.SIGN).astype(np.uint8)
    surf = view_surface(uv, np.full(len(uv), 6.0), labels, (H, W), surface_params(8.0))
    assert np.all(surf.classes[30:200, 30:97] == cls.POLE)
    assert np.all(surf.classes[30:200, 103:137] == cls.SIGN)
    assert not surf.valid[:, 141:180].any() and np.all(surf.classes[:, 141:180] == 0)
    assert not surf.valid[:19].any() and not surf.valid[:, 301:].any()


def test_surface_for_view_end_to_end_on_a_wall():
    rng = np.random.default_rng(8)
    pose = look_at([0.0, -10.0, 0.0], [0.0, 0.0, 0.0])
    wall = _plane_points(rng, 80000, [-7, 0, -5], [14, 0, 0], [0, 0, 10])
    image = np.full((H, W, 3), 120, np.uint8)
    params = DetectParams(zbuffer=ZBufferParams(), surface=surface_params(12.0))
    surf, kept = surface_for_view(
        wall, np.full(len(wall), cls.BUILDING, np.uint8), image, INTR, pose, params
    )
    assert surf.valid[INTERIOR].mean() > 0.999
    np.testing.assert_allclose(surf.depth[surf.valid], 10.0, atol=1e-3)
    np.testing.assert_allclose(kept.depth, wall[kept.index, 1] + 10.0)
    # windows scaled to the width: w = round(5 · 320 / 4000) = 1 keeps one point per pixel
    scaled = DetectParams(
        zbuffer=ZBufferParams(scale_with_resolution=True), surface=surface_params(12.0)
    )
    _, kept_scaled = surface_for_view(
        wall, np.full(len(wall), cls.BUILDING, np.uint8), image, INTR, pose, scaled
    )
    pts = project_cloud(wall, np.zeros(len(wall), np.uint8), INTR, pose, 60.0)
    assert len(kept_scaled) == len(block_zbuffer(pts.uv, pts.depth, (H, W), 1)) > len(kept)
    with pytest.raises(EmptyViewError, match="60.0 m"):
        surface_for_view(
            wall + [0, -30, 0], np.zeros(len(wall), np.uint8), image, INTR, pose, params
        )
    with pytest.raises(InputError, match="does not match"):
        surface_for_view(wall, np.zeros(len(wall), np.uint8), image[:100], INTR, pose, params)


def test_edge_floor_keeps_a_small_image_surface_whole_with_the_paper_defaults():
    # Regression: at 320 px the paper's 30 px (for 4000 px) scales to 2.4 px, below the 5 px
    # block z-buffer grid, and every triangle was dropped. The floor of three grid cells keeps it.
    rng = np.random.default_rng(9)
    pose = look_at([0.0, -10.0, 0.0], [0.0, 0.0, 0.0])
    wall = _plane_points(rng, 80000, [-7, 0, -5], [14, 0, 0], [0, 0, 10])
    image = np.full((H, W, 3), 120, np.uint8)
    surf, _ = surface_for_view(
        wall, np.full(len(wall), cls.BUILDING, np.uint8), image, INTR, pose, DetectParams()
    )
    assert surf.valid[INTERIOR].mean() > 0.99


def _wall_surface(h: int = 200, w: int = 200):
    """A wall 15 m away over the whole view, grey, class building."""
    from streetcd.detect.surface import ViewSurface

    return ViewSurface(
        np.full((h, w), 15.0, np.float32),
        np.full((h, w), cls.BUILDING, np.uint8),
        np.ones((h, w), bool),
        np.full((h, w, 3), 128, np.uint8),
    )


def _profiles(columns, code, depth=2.0, rows=range(40, 161, 8)):
    """ProjectedPoints in vertical scan profiles at ``columns``, every 8 px down each."""
    from streetcd.detect.zbuffer import ProjectedPoints

    uv = np.array([(c, r) for c in columns for r in rows], np.float64)
    n = len(uv)
    return ProjectedPoints(
        uv, np.full(n, depth), np.full(n, code, np.uint8), np.arange(n, dtype=np.int64)
    )


def test_a_near_poles_points_fill_its_surface_between_its_profiles_and_not_past_them():
    """Three profiles 20 px apart, each point a 24 px disc (0.6 of a 40 px reach): the
    gaps between them take the pole's depth, class and colour; the union's edge, 24 px past
    the outer profiles, does not (only what lies 0.9 of a radius inside it); a nearer
    surface, a railing's points and points whose disc is too small fill nothing."""
    from streetcd.detect.surface import fill_from_points

    params = SurfaceParams()
    assert params.point_fill_classes == (cls.POLE, cls.SIGN, cls.FURNITURE)
    surf = _wall_surface()
    surf.depth[100, 90] = np.nan  # a hole between the profiles
    surf.depth[60, 100] = 1.0  # something nearer than the pole stays
    pole = _profiles((80, 100, 120), cls.POLE)
    red = np.tile(np.array([[200, 30, 30]], np.uint8), (len(pole), 1))
    out = fill_from_points(surf, pole, np.full(len(pole), 40.0), params, red)
    assert out is surf  # in place
    for col in (80, 85, 90, 100, 110, 120):
        assert surf.classes[100, col] == cls.POLE and surf.depth[100, col] == 2.0, col
        assert tuple(surf.colour[100, col]) == (200, 30, 30)
    assert surf.valid[100, 90]
    assert surf.depth[60, 100] == 1.0 and surf.classes[60, 100] == cls.BUILDING
    # 24 px past the outer profiles the discs' union ends; 0.9 · 24 px inside it, at 78
    assert (surf.classes[100, :78] == cls.BUILDING).all() and surf.classes[100, 79] == cls.POLE
    assert (surf.classes[100, 123:] == cls.BUILDING).all() and surf.classes[100, 121] == cls.POLE
    # a railing's gaps show what is behind it; points with a disc under the floor are left
    for points, reach in ((_profiles((80, 100, 120), cls.RAILING), 40.0), (pole, 3.0)):
        wall = _wall_surface()
        fill_from_points(wall, points, np.full(len(points), reach), params)
        assert (wall.classes == cls.BUILDING).all() and (wall.depth == 15.0).all()
    # switched off
    wall = _wall_surface()
    fill_from_points(wall, pole, np.full(len(pole), 40.0), SurfaceParams(point_fill_classes=()))
    assert (wall.classes == cls.BUILDING).all()


def test_a_lone_near_point_fills_no_more_than_its_core():
    """A single point's disc keeps only the pixels 0.9 of its radius inside it: a stray
    point does not paint a 24 px disc over the wall."""
    from streetcd.detect.surface import fill_from_points

    wall = _wall_surface()
    lone = _profiles((100,), cls.SIGN, rows=(100,))
    fill_from_points(wall, lone, np.array([40.0]), SurfaceParams())
    filled = wall.classes == cls.SIGN
    assert 0 < filled.sum() <= 40 and filled[100, 100]


@pytest.mark.parametrize(
    ("field", "value"),
    [("point_fill_reach", 0.0), ("point_fill_core", 1.5), ("point_fill_min_px", -1.0)],
)
def test_point_fill_settings_are_checked(field, value):
    with pytest.raises(InputError, match=field):
        SurfaceParams(**{field: value})
