"""The cloud's own point spacing (streetcd.detect.spacing) and the triangle filters and z-buffer
window it widens on sparse clouds (issue 16)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from streetcd.config import REFERENCE_WIDTH_PX, DetectParams, SurfaceParams, ZBufferParams
from streetcd.detect import spacing as spacing_mod
from streetcd.detect.spacing import MIN_CLASS_SAMPLES, class_spacing, sampled_spacing
from streetcd.detect.surface import surface_for_view, view_surface
from streetcd.detect.zbuffer import weighted_zbuffer
from streetcd.errors import InputError
from streetcd.geometry.camera import look_at
from streetcd.types import Intrinsics

W, H, F = 320, 240, 300.0
INTR = Intrinsics(W, H, F, F, (W - 1) / 2, (H - 1) / 2)


def _grid(step: float, n: int, z: float = 0.0, x0: float = 0.0) -> np.ndarray:
    """(n², 3) points of a square grid ``step`` m apart in the plane at height ``z``."""
    x, y = np.meshgrid(x0 + step * np.arange(n), step * np.arange(n))
    return np.column_stack([x.ravel(), y.ravel(), np.full(n * n, z)])


def test_spacing_of_a_regular_grid_is_its_step():
    index, spacing = sampled_spacing(_grid(0.25, 40))
    assert len(index) == len(spacing) == 1600  # fewer points than a sample: all of them
    assert np.allclose(spacing, 0.25)


def test_each_class_gets_its_own_spacing_and_rare_classes_the_cloud_median():
    dense, sparse = _grid(0.05, 60), _grid(0.4, 30, x0=100.0)  # far apart: no shared neighbours
    rare = _grid(1.0, 3, x0=-500.0)[:5]  # 5 points: too few samples for a class of its own
    xyz = np.vstack([dense, sparse, rare])
    codes = np.r_[np.full(len(dense), 2), np.full(len(sparse), 6), np.full(len(rare), 64)]
    table = class_spacing(xyz, codes.astype(np.uint8))
    assert table.shape == (256,)
    assert table[2] == pytest.approx(0.05) and table[6] == pytest.approx(0.4)
    median = np.median(sampled_spacing(xyz)[1])
    assert len(rare) < MIN_CLASS_SAMPLES and table[64] == median and table[17] == median


def test_a_cloud_larger_than_the_tree_is_scaled_from_a_random_subset(monkeypatch):
    # 40,000 points scattered at random on a 20 m square, the tree limited to a quarter of
    # them: that subset is spaced twice as wide, and the scaled estimate finds the true median
    xyz = np.random.default_rng(1).uniform(0, 20, (40_000, 3)) * [1, 1, 0]
    true = np.median(cKDTree(xyz).query(xyz, k=2)[0][:, 1])  # 0.047 m
    monkeypatch.setattr(spacing_mod, "TREE_POINTS", 10_000)
    _, spacing = sampled_spacing(xyz)
    assert np.median(spacing) == pytest.approx(true, rel=0.05)


def test_small_clouds_and_bad_input():
    assert class_spacing(np.zeros((1, 3)), np.zeros(1, np.uint8)).max() == 0.0
    with pytest.raises(InputError, match="xyz must be"):
        sampled_spacing(np.zeros((5, 2)))
    with pytest.raises(InputError, match="classes must be"):
        class_spacing(np.zeros((5, 3)), np.zeros(4, np.uint8))
    with pytest.raises(InputError, match="spacing_edge_factor"):
        SurfaceParams(spacing_edge_factor=-1.0)
    with pytest.raises(InputError, match="spacing_factor"):
        ZBufferParams(spacing_factor=float("nan"))


def _lattice(step_px: float, depth: float | np.ndarray = 5.0):
    """A 9 × 9 lattice ``step_px`` apart in a 320 × 240 image, at ``depth`` m."""
    u, v = np.meshgrid(40 + step_px * np.arange(9), 20 + step_px * np.arange(9))
    uv = np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)
    return uv, np.broadcast_to(np.asarray(depth, np.float64), (81,)).copy()


def _paper(edge_px: float = 15.0) -> SurfaceParams:
    """The paper's fixed filters: no widening (the defaults widen sparse classes)."""
    return SurfaceParams(
        max_edge_px=edge_px * REFERENCE_WIDTH_PX / W,
        spacing_edge_factor=0.0,
        spacing_edge_min_spacing_m=0.0,
        spacing_edge_same_role=False,
    )


def test_edge_limit_reaches_the_projected_spacing_times_the_factor():
    # 25 px lattice at 5 m, a cloud spaced 0.5 m, f = 300 px: f·s/z = 30 px per spacing; the
    # lattice's triangles have 25 px sides and 35.4 px diagonals
    uv, depth = _lattice(25.0)
    cls = np.zeros(81, np.uint8)
    s = (np.full(81, 0.5), F)
    off = view_surface(uv, depth, cls, (H, W), _paper(), spacing=s)
    assert not off.valid.any()  # the paper's 15 px: no triangle
    short = view_surface(
        uv, depth, cls, (H, W), replace(_paper(), spacing_edge_factor=1.0), spacing=s
    )
    assert not short.valid.any()  # 30 px: the diagonals are still too long
    wide = view_surface(
        uv, depth, cls, (H, W), replace(_paper(), spacing_edge_factor=1.2), spacing=s
    )
    # 36 px: the whole lattice, 2 × 8 × 8 triangles, exactly the 200 × 200 px square
    assert wide.valid.sum() == 201 * 201
    assert wide.valid[20:221, 40:241].all()


def test_edge_limit_never_goes_below_the_configured_one():
    uv, depth = _lattice(10.0)  # 14.1 px diagonals: the paper's 15 px keeps all
    cls = np.zeros(81, np.uint8)
    tiny = (np.full(81, 0.001), F)  # f·s/z = 0.06 px
    paper = view_surface(uv, depth, cls, (H, W), _paper())
    widened = view_surface(
        uv, depth, cls, (H, W), replace(_paper(), spacing_edge_factor=4.0), spacing=tiny
    )
    assert paper.valid.sum() == 81 * 81
    np.testing.assert_array_equal(widened.depth, paper.depth)


def test_depth_jump_limit_follows_the_densest_vertex():
    # a ramp: each lattice row 0.4 m deeper than the one above, so a triangle spans 0.4 m
    uv, _ = _lattice(10.0)
    depth = 5.0 + 0.4 * np.repeat(np.arange(9), 9)
    cls = np.zeros(81, np.uint8)
    params = SurfaceParams(max_depth_jump_m=0.3, max_edge_px=_paper().max_edge_px)
    assert not view_surface(uv, depth, cls, (H, W), params).valid.any()
    sparse = (np.full(81, 0.1), F)
    ramp = view_surface(
        uv, depth, cls, (H, W), replace(params, spacing_jump_factor=5.0), spacing=sparse
    )
    assert ramp.valid.sum() == 81 * 81  # 0.5 m allowed
    # one vertex of a dense class (s = 0.01: 0.05 m) in the middle keeps its six triangles out
    mixed = (np.where(np.arange(81) == 40, 0.01, 0.1), F)
    holed = view_surface(
        uv, depth, cls, (H, W), replace(params, spacing_jump_factor=5.0), spacing=mixed
    )
    assert ramp.valid.sum() - holed.valid.sum() > 0
    assert not holed.valid[uv[40, 1].astype(int), uv[40, 0].astype(int)]


def test_zbuffer_spacing_below_the_configured_one_changes_nothing_and_must_fit():
    rng = np.random.default_rng(0)
    uv = rng.uniform(0, [W - 1, H - 1], (2000, 2))
    depth = rng.uniform(1.0, 10.0, 2000)
    image = rng.integers(0, 3, (H, W, 3)).astype(np.uint8)  # nearly plain: eq. 2 supports
    params = ZBufferParams()
    paper = weighted_zbuffer(uv, depth, image, params, focal_px=F)
    same = weighted_zbuffer(uv, depth, image, params, focal_px=F, spacing_m=np.zeros(2000))
    np.testing.assert_array_equal(paper, same)
    wider = weighted_zbuffer(uv, depth, image, params, focal_px=F, spacing_m=np.full(2000, 0.5))
    assert set(wider) <= set(paper) and len(wider) < len(paper)  # a wider reach erases more
    with pytest.raises(InputError, match="spacing_m must be"):
        weighted_zbuffer(uv, depth, image, params, focal_px=F, spacing_m=np.zeros(3))


def test_a_sparse_wall_keeps_its_surface_with_the_spacing_filters():
    # a wall 6 m away scanned 0.4 m apart: 20 px in the image, over the paper's 15 px (at 320
    # px wide, the floor of 3 z-buffer cells), so the paper keeps no surface; the cloud's own
    # spacing restores it
    x, z = np.meshgrid(np.arange(-3.0, 3.01, 0.4), np.arange(-2.0, 2.01, 0.4))
    wall = np.column_stack([x.ravel(), np.full(x.size, 6.0), z.ravel()])
    codes = np.full(len(wall), 6, np.uint8)
    image = np.full((H, W, 3), 120, np.uint8)
    pose = look_at([0, 0, 0], [0, 6, 0])
    base = DetectParams()
    fixed = replace(base, surface=replace(base.surface, spacing_edge_factor=0.0))
    paper, _ = surface_for_view(wall, codes, image, INTR, pose, fixed)
    params = replace(base, surface=replace(base.surface, spacing_edge_factor=3.0))
    sparse, _ = surface_for_view(wall, codes, image, INTR, pose, params)
    assert paper.valid.mean() < 0.01
    assert sparse.valid.mean() > 0.7  # the wall fills 300 × 200 px of the 320 × 240 image
    defaults, _ = surface_for_view(wall, codes, image, INTR, pose, base)  # 8 · f · s / z
    assert defaults.valid.mean() > 0.7


def test_edge_widening_leaves_near_vertices_and_other_roles_alone():
    # the 25 px lattice of the test above widened to 36 px (the whole square), with its top
    # three rows 2 m from the camera: with a 3 m floor no triangle touching them widens
    uv, depth = _lattice(25.0)
    depth[:27] = 2.0
    cls = np.full(81, 2, np.uint8)
    s = (np.full(81, 0.5) * depth / 5.0, F)  # the same 30 px projected spacing everywhere
    widened = replace(_paper(), spacing_edge_factor=1.2, max_depth_jump_m=10.0)
    whole = view_surface(uv, depth, cls, (H, W), widened, spacing=s)
    assert whole.valid.sum() == 201 * 201
    floor = replace(widened, spacing_edge_min_depth_m=3.0)
    near = view_surface(uv, depth, cls, (H, W), floor, spacing=s)
    rows = np.flatnonzero(near.valid.any(axis=1))
    assert rows.min() == 20 + 3 * 25 and rows.max() == 220  # rows 3-8 of the lattice only
    assert near.valid.sum() == 201 * (5 * 25 + 1)
    # roles: the lattice's left four columns are vegetation (5), the rest ground (2)
    cls[np.tile(np.arange(9) < 4, 9)] = 5
    ground = view_surface(
        uv, depth, cls, (H, W), replace(widened, spacing_edge_classes=(2, 11)), spacing=s
    )
    cols = np.flatnonzero(ground.valid.any(axis=0))
    assert cols.min() == 40 + 4 * 25 and cols.max() == 240
    # one role per widened triangle: both pieces whole, the 25 px step between them open
    flat, half = np.full(81, 5.0), (np.full(81, 0.5), F)
    same = view_surface(
        uv, flat, cls, (H, W), replace(widened, spacing_edge_same_role=True), spacing=half
    )
    cols = np.flatnonzero(same.valid.any(axis=0))
    assert set(cols) == set(range(40, 40 + 3 * 25 + 1)) | set(range(40 + 4 * 25, 241))
    assert same.valid.sum() == 201 * cols.size
    assert view_surface(uv, flat, cls, (H, W), widened, spacing=half).valid.sum() == 201 * 201
    # a cloud measured as sparse as the floor (0.5 m ≥ 0.4 m) widens, a denser one does not
    at_floor = replace(widened, spacing_edge_min_spacing_m=0.4)
    assert view_surface(uv, flat, cls, (H, W), at_floor, spacing=half).valid.sum() == 201 * 201
    dense = replace(widened, spacing_edge_min_spacing_m=0.6)
    assert not view_surface(uv, flat, cls, (H, W), dense, spacing=half).valid.any()
    # the other way round: a cut above the measured spacing widens, one below it does not
    upto = replace(widened, spacing_edge_max_spacing_m=0.5)
    assert view_surface(uv, flat, cls, (H, W), upto, spacing=half).valid.sum() == 201 * 201
    sparse = replace(widened, spacing_edge_max_spacing_m=0.4)
    assert not view_surface(uv, flat, cls, (H, W), sparse, spacing=half).valid.any()
    with pytest.raises(InputError, match="spacing_edge_min_depth_m"):
        SurfaceParams(spacing_edge_min_depth_m=-1.0)
    with pytest.raises(InputError, match="spacing_edge_max_spacing_m"):
        SurfaceParams(spacing_edge_max_spacing_m=float("nan"))
    with pytest.raises(InputError, match="spacing_edge_classes"):
        SurfaceParams(spacing_edge_classes=(2, 300))
