"""Cropping the cloud a view can see (streetcd.store.crop)."""

from __future__ import annotations

import numpy as np
import pytest

from streetcd.errors import CRSMismatchError, InputError
from streetcd.geometry.camera import look_at
from streetcd.geometry.frustum import convex_hull_2d, in_frustum, view_footprint
from streetcd.io.las import read_las, write_las
from streetcd.store.crop import crop_for_view, crop_for_views
from streetcd.store.ingest import ingest
from streetcd.store.tiles import TileStore, tile_cache
from streetcd.types import Intrinsics, View

ORIGIN = np.array([421_000.0, 5_632_000.0, 0.0])  # CRS metres
INTR = Intrinsics(width=64, height=48, fx=40.0, fy=40.0, cx=31.5, cy=23.5)
DISTORTED = Intrinsics(
    width=64, height=48, fx=40.0, fy=40.0, cx=30.0, cy=25.0, dist=(-0.2, 0.05, 0.001, -0.001, 0.0)
)


def view_at(center, target, intrinsics=INTR, name="v") -> View:
    """A view in CRS coordinates; ``center``/``target`` are given local to ORIGIN."""
    return View(name, intrinsics, look_at(np.asarray(center) + ORIGIN, np.asarray(target) + ORIGIN))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Three overlapping LAZ strips over 90 × 60 m, ingested into 10 m tiles. gps_time is a
    unique id per point; ``truth`` holds the exact written coordinates (CRS, float64)."""
    root = tmp_path_factory.mktemp("scene")
    rng = np.random.default_rng(42)
    truth, files = [], []
    for k in range(3):
        n = 4000
        xyz = rng.uniform([k * 25.0, 0.0, 0.0], [k * 25.0 + 40.0, 60.0, 15.0], (n, 3))
        xyz = np.round(xyz, 3)  # on the 1 mm grid, so write → read is exact
        ids = np.arange(k * n, (k + 1) * n, dtype=np.float64)
        files.append(
            write_las(
                root / "archive" / f"s{k}.laz",
                xyz,
                rng.integers(1, 12, n),
                origin=ORIGIN,
                rgb=rng.integers(0, 65535, (n, 3)),
                gps_time=ids,
                crs="EPSG:32633",
            )
        )
        truth.append(xyz + ORIGIN)
    ingest(root / "archive", root / "store.zarr", tile_size_m=10.0)
    return {
        "store": TileStore.open(root / "store.zarr"),
        "files": files,
        "truth": np.concatenate(truth),
    }


def brute_force(scene, view, max_range_m, buffer_m):
    """The full cloud, every point tested: ids of the points the view keeps."""
    origin = scene["store"].origin
    clouds = [read_las(f, origin=origin) for f in scene["files"]]
    xyz = np.concatenate([c.xyz for c in clouds])
    ids = np.concatenate([c.gps_time for c in clouds])
    keep = in_frustum(xyz, view.local(origin), max_range_m, buffer_m)
    return np.sort(ids[keep])


VIEWS = [
    (view_at([5.0, 30.0, 2.0], [40.0, 30.0, 2.0]), 25.0, 1.0),  # along the street
    (view_at([45.0, 10.0, 2.5], [45.0, 60.0, 0.0], DISTORTED), 30.0, 0.5),  # distorted
    (view_at([60.0, 30.0, 40.0], [60.0, 30.001, 0.0]), 60.0, 1.0),  # looking down
    (view_at([80.0, 50.0, 2.0], [20.0, 5.0, 8.0]), 20.0, 2.0),  # diagonal, upwards
    (view_at([-30.0, 30.0, 2.0], [-60.0, 30.0, 2.0]), 60.0, 1.0),  # away from the data
]


def test_in_frustum_keeps_the_frustum_plus_buffer_exactly():
    view = View("v", INTR, look_at([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]))  # along +x, z up
    # Border rays: x/z ∈ [−0.8, 0.8] (left/right), y/z ∈ [−0.6, 0.6] (up/down).
    side, top = np.hypot(1.0, 0.8), np.hypot(1.0, 0.6)
    pts = np.array(
        [
            [10.0, 0.0, 0.0],  # on the axis
            [10.0, -(8.0 + 0.9 * side), 0.0],  # 0.9 m right of the right plane
            [10.0, -(8.0 + 1.1 * side), 0.0],  # 1.1 m right of it
            [10.0, 0.0, 6.0 + 0.9 * top],  # 0.9 m above the top plane
            [10.0, 0.0, 6.0 + 1.1 * top],
            [60.9, 0.0, 0.0],  # range 60.9 ≤ 60 + 1
            [61.1, 0.0, 0.0],
            [-5.0, 0.0, 0.0],  # behind the camera
        ]
    )
    np.testing.assert_array_equal(
        in_frustum(pts, view, 60.0, 1.0), [True, True, False, True, False, True, False, False]
    )
    np.testing.assert_array_equal(
        in_frustum(pts, view, 60.0, 0.0), [True, False, False, False, False, False, False, False]
    )


def _inside_convex(poly: np.ndarray, pts: np.ndarray) -> np.ndarray:
    inside = np.ones(len(pts), bool)
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        cross = (b[0] - a[0]) * (pts[:, 1] - a[1]) - (b[1] - a[1]) * (pts[:, 0] - a[0])
        inside &= cross >= -1e-9
    return inside


@pytest.mark.parametrize("intr", [INTR, DISTORTED])
def test_ground_footprint_contains_every_kept_point(intr):
    rng = np.random.default_rng(9)
    pts = rng.uniform(-80, 80, (40_000, 3))
    for _ in range(10):
        c, t = rng.uniform(-5, 5, 3), rng.uniform(-30, 30, 3)
        view = View("v", intr, look_at(c, t))
        keep = in_frustum(pts, view, 50.0, 1.5)
        assert keep.any()
        poly = view_footprint(view, 50.0, 1.5)
        assert np.all(_inside_convex(poly, pts[keep, :2]))


def test_convex_hull_is_counter_clockwise():
    hull = convex_hull_2d(np.array([[0, 0], [2, 0], [1, 1], [2, 2], [0, 2], [1, 0.5]]))
    np.testing.assert_array_equal(hull, [[0, 0], [2, 0], [2, 2], [0, 2]])


@pytest.mark.parametrize("case", range(len(VIEWS)))
def test_crop_equals_brute_force_crop_of_the_full_cloud(scene, case):
    view, max_range, buffer = VIEWS[case]
    store = scene["store"]
    tile_cache().clear()
    misses = tile_cache().misses
    cloud = crop_for_view(store, view, max_range_m=max_range, buffer_m=buffer)
    want = brute_force(scene, view, max_range, buffer)
    got = np.sort(cloud.gps_time) if len(cloud) else np.empty(0)  # empty: no optional fields
    np.testing.assert_array_equal(got, want)
    assert tile_cache().misses - misses < len(store)  # only the tiles the frustum meets
    assert np.array_equal(cloud.origin, store.origin) and cloud.crs == "EPSG:32633"
    if case == 4:
        assert len(cloud) == 0 and cloud.xyz.shape == (0, 3)
    else:
        assert len(cloud) > 100


def test_ingest_then_crop_keeps_georeferenced_coordinates_within_1mm(scene):
    view, _, _ = VIEWS[0]
    cloud = crop_for_view(scene["store"], view, max_range_m=500.0, buffer_m=100.0)
    assert len(cloud) == len(scene["truth"])  # this view takes everything
    ids = cloud.gps_time.astype(np.int64)
    err = np.abs(cloud.xyz + cloud.origin - scene["truth"][ids])
    assert err.max() <= 0.001


def test_crop_from_files_equals_crop_from_store(scene):
    for view, max_range, buffer in VIEWS[:4]:
        a = crop_for_view(scene["store"], view, max_range_m=max_range, buffer_m=buffer)
        b = crop_for_view(scene["files"], view, max_range_m=max_range, buffer_m=buffer)
        oa, ob = np.argsort(a.gps_time), np.argsort(b.gps_time)
        np.testing.assert_array_equal(a.gps_time[oa], b.gps_time[ob])
        np.testing.assert_allclose(a.xyz[oa] + a.origin, b.xyz[ob] + b.origin, atol=1e-6)
        np.testing.assert_array_equal(a.classification[oa], b.classification[ob])
        np.testing.assert_array_equal(a.rgb[oa], b.rgb[ob])


def test_crop_by_store_path_returns_classes_and_rgb(scene):
    view, max_range, buffer = VIEWS[0]
    cloud = crop_for_view(scene["store"].path, view, max_range_m=max_range, buffer_m=buffer)
    assert cloud.classification.dtype == np.uint8 and cloud.rgb.shape == (len(cloud), 3)
    ref = read_las(scene["files"][0], origin=cloud.origin)
    by_id = dict(zip(ref.gps_time.tolist(), ref.classification.tolist(), strict=True))
    for gid, cls in zip(
        cloud.gps_time[:200].tolist(), cloud.classification[:200].tolist(), strict=True
    ):
        if gid in by_id:
            assert by_id[gid] == cls


def test_neighbouring_views_reuse_cached_tiles(scene):
    tile_cache().clear()
    crop_for_view(scene["store"], view_at([5.0, 30.0, 2.0], [40.0, 30.0, 2.0]), max_range_m=25.0)
    hits, misses = tile_cache().hits, tile_cache().misses
    crop_for_view(scene["store"], view_at([7.0, 30.0, 2.0], [42.0, 30.0, 2.0]), max_range_m=25.0)
    assert tile_cache().hits - hits >= 5
    assert tile_cache().misses - misses <= 3  # only the tiles newly in view are read


def test_crop_files_with_different_crs_names_the_file(tmp_path):
    a = write_las(tmp_path / "a.laz", np.zeros((5, 3)), np.ones(5), origin=ORIGIN, crs="EPSG:32633")
    b = write_las(tmp_path / "b.laz", np.zeros((5, 3)), np.ones(5), origin=ORIGIN, crs="EPSG:32632")
    with pytest.raises(CRSMismatchError, match="b.laz"):
        crop_for_view([a, b], VIEWS[0][0])


def test_bad_range_is_refused(scene):
    with pytest.raises(InputError, match="max_range_m"):
        crop_for_view(scene["store"], VIEWS[0][0], max_range_m=-1.0)


@pytest.mark.parametrize("from_files", [False, True])
def test_crop_for_several_views_is_the_union_of_their_crops(scene, from_files):
    source = scene["files"] if from_files else scene["store"]
    views = [v for v, _, _ in VIEWS]
    union = crop_for_views(source, views, max_range_m=30.0, buffer_m=1.0)
    each = [crop_for_view(source, v, max_range_m=30.0, buffer_m=1.0) for v in views]
    # The last view looks away from the data: its crop is empty and adds nothing.
    assert len(each[-1]) == 0
    expected = np.unique(np.concatenate([c.gps_time for c in each[:-1]]))
    assert len(union) == len(expected) > max(len(c) for c in each)  # no point twice
    np.testing.assert_array_equal(np.sort(union.gps_time), expected)


@pytest.mark.parametrize("from_files", [False, True])
def test_a_crop_of_some_fields_is_the_whole_crop_without_the_others(scene, from_files):
    source = scene["files"] if from_files else scene["store"]
    view = VIEWS[0][0]
    tile_cache().clear()
    whole = crop_for_view(source, view, max_range_m=30.0)
    some = crop_for_view(source, view, max_range_m=30.0, fields=("intensity",))
    again = crop_for_view(source, view, max_range_m=30.0)  # the cache kept the two apart
    assert len(whole) > 0 and whole.gps_time is not None and whole.intensity is not None
    assert some.gps_time is None and some.rgb is None
    for a, b in ((whole, some), (whole, again)):
        np.testing.assert_array_equal(a.xyz, b.xyz)
        np.testing.assert_array_equal(a.classification, b.classification)
        np.testing.assert_array_equal(a.intensity, b.intensity)
    np.testing.assert_array_equal(whole.gps_time, again.gps_time)
    with pytest.raises(InputError, match="crop fields"):
        crop_for_view(source, view, fields=("colour",))
