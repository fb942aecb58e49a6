"""Roles from the geometry of an unclassified cloud (streetcd.detect.infer_roles) and where the
detector applies them (streetcd.detect.roles.cloud_roles, the class map's ``infer``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from streetcd import classes
from streetcd.config import ClassMap, Config, DetectParams, config_from_dict
from streetcd.detect.cache import SurfaceCache
from streetcd.detect.infer_roles import height_above_ground, infer_roles
from streetcd.detect.roles import (
    _INFERRED,
    _code_counts,
    _table,
    cloud_roles,
    in_roles,
    infers,
    road_told,
    road_told_codes,
    role_codes,
)
from streetcd.errors import InputError
from streetcd.types import Intrinsics, PointCloud, Pose, View

STEP = 0.05  # metres between sampled points: a dense mobile-mapping cloud


def grid(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    uu, vv = np.meshgrid(u, v, indexing="ij")
    return uu.ravel(), vv.ravel()


def box(x0: float, x1: float, y0: float, y1: float, z0: float, z1: float) -> np.ndarray:
    """(N, 3) points on the four sides and the top of an axis-aligned box."""
    xs, ys, zs = (np.arange(a, b + 1e-9, STEP) for a, b in ((x0, x1), (y0, y1), (z0, z1)))
    sides = []
    for y in (y0, y1):
        x, z = grid(xs, zs)
        sides.append(np.stack([x, np.full_like(x, y), z], axis=1))
    for x in (x0, x1):
        y, z = grid(ys, zs)
        sides.append(np.stack([np.full_like(y, x), y, z], axis=1))
    x, y = grid(xs, ys)
    sides.append(np.stack([x, y, np.full_like(x, z1)], axis=1))
    return np.concatenate(sides)


def ball(cx: float, cy: float, cz: float, r: float) -> np.ndarray:
    """(N, 3) points on a sphere (a tree's canopy)."""
    n = int(4 * np.pi * r * r / STEP**2)
    k = np.arange(n) + 0.5
    phi, theta = np.arccos(1 - 2 * k / n), np.pi * (1 + 5**0.5) * k
    return np.stack(
        [
            cx + r * np.cos(theta) * np.sin(phi),
            cy + r * np.sin(theta) * np.sin(phi),
            cz + r * np.cos(phi),
        ],
        axis=1,
    )


def street() -> tuple[np.ndarray, np.ndarray]:
    """A 40 × 20 m street rising 2 % along x, with a 0.12 m kerb at y = 4 and one object of
    each kind on it; (N, 3) points and (N,) the role each point should get."""
    x, y = grid(np.arange(0, 40, 0.1), np.arange(-6, 14, 0.1))
    parts = [(np.stack([x, y, np.where(y > 4, 0.12, 0.0)], axis=1), classes.GROUND)]
    parts += [
        (box(2, 30, 12, 12.3, 0, 8), classes.BUILDING),  # a façade
        (box(5, 5.2, 5, 5.2, 0.12, 6), classes.POLE),  # a street light's pole
        (box(10, 10.6, 6, 6.6, 0.12, 1.0), classes.FURNITURE),  # a bin
        (box(14, 18.5, 1, 2.8, 0.3, 1.5), classes.CAR),  # a parked car
        (box(20, 26, 7, 7.05, 0.12, 1.0), classes.RAILING),
        (np.concatenate([box(33, 33.3, 7, 7.3, 0.12, 3.5), ball(33.15, 7.15, 5.5, 2.0)]), 5),
    ]
    xyz = np.concatenate([p for p, _ in parts])
    want = np.concatenate([np.full(len(p), role, np.uint8) for p, role in parts])
    xyz[:, 2] += 0.02 * xyz[:, 0]  # the street climbs: the ground follows it
    return xyz, want


@pytest.fixture(scope="module")
def scene() -> tuple[np.ndarray, np.ndarray]:
    return street()


@pytest.fixture(scope="module")
def inferred(scene) -> np.ndarray:
    return infer_roles(scene[0])


@pytest.mark.parametrize(
    "role",
    [
        classes.GROUND,
        classes.BUILDING,
        classes.POLE,
        classes.FURNITURE,
        classes.CAR,
        classes.RAILING,
        classes.VEGETATION,
    ],
)
def test_each_kind_of_object_gets_its_role(scene, inferred, role):
    xyz, want = scene
    got = inferred
    # an object's lowest 0.3 m are within the ground's tolerance: judged above that
    base = np.where(xyz[:, 1] > 4, 0.12, 0.0) + 0.02 * xyz[:, 0]
    mine = (want == role) & ((xyz[:, 2] - base > 0.35) | (role == classes.GROUND))
    share = float(np.mean(got[mine] == role))
    assert share > 0.95, f"{classes.NAMES[role]}: {share:.2f}, got {np.unique(got[mine])}"


def test_the_ground_follows_a_slope_and_a_kerb_and_ignores_a_stray_low_point(scene):
    xyz, want = scene
    stray = np.array([[12.0, 0.0, -3.0]])  # a scanner's ghost point under the road
    height = height_above_ground(np.concatenate([xyz, stray]))
    ground = height[:-1][want == classes.GROUND]
    assert np.abs(ground).max() < 0.2  # kerb and slope included
    assert np.abs(height[:-1][want == classes.POLE]).max() == pytest.approx(6 + 0.02 * 5, 0.05)


def test_the_roles_do_not_depend_on_the_order_of_the_points_or_much_on_the_frame(scene):
    xyz, _ = scene
    order = np.random.default_rng(0).permutation(len(xyz))
    base = infer_roles(xyz)
    assert np.array_equal(infer_roles(xyz[order]), base[order])
    # another frame moves a few points across a cell's edge (rounding), no more
    assert np.mean(infer_roles(xyz + [500.0, -300.0, 40.0]) == base) > 0.999


def test_non_finite_points_stay_unclassified_and_an_empty_cloud_gives_nothing(scene):
    xyz, _ = scene
    bad = xyz.copy()
    bad[::1000, 2] = np.nan
    got = infer_roles(bad)
    assert np.all(got[::1000] == classes.UNCLASSIFIED)
    assert np.array_equal(
        np.delete(got, np.s_[::1000]), infer_roles(np.delete(xyz, np.s_[::1000], 0))
    )
    assert infer_roles(np.empty((0, 3))).shape == (0,)


def test_auto_infers_only_for_a_cloud_without_useful_classes(scene):
    xyz, want = scene
    flat = np.ones(len(xyz), np.uint8)
    auto = ClassMap()
    assert infers(flat, auto) and not infers(want, auto)
    assert np.array_equal(cloud_roles(xyz, want, auto), role_codes(want, auto))  # classified
    inferred = cloud_roles(xyz, flat, auto)
    assert np.array_equal(inferred, infer_roles(xyz))
    assert id(xyz) in _INFERRED.items  # kept with the cloud: its views share one inference
    off = ClassMap(infer="off")
    assert not infers(flat, off)
    assert np.all(cloud_roles(xyz, flat, off) == classes.UNCLASSIFIED)


def test_role_codes_are_the_class_maps_table_for_every_code_and_shape():
    codes = np.arange(256, dtype=np.uint8)
    for class_map in (ClassMap(), ClassMap(road=(1,), building=(200, 201))):
        table = _table(class_map)
        assert np.array_equal(role_codes(codes, class_map), table[codes])
        assert np.array_equal(
            role_codes(codes.reshape(16, 16), class_map), table[codes].reshape(16, 16)
        )
        assert role_codes(np.zeros(0, np.uint8), class_map).shape == (0,)


def test_code_counts_are_taken_once_per_array():
    codes = np.array([1, 2, 2, 6, 64, 64, 64], np.uint8)
    counts, total = _code_counts(codes)
    assert total == 7 and counts[64] == 3 and counts[2] == 2 and counts.sum() == 7
    assert _code_counts(codes)[0] is counts  # the class checks of one cloud share them
    assert not counts.flags.writeable
    other = codes.copy()  # another array: counted on its own
    assert _code_counts(other)[0] is not counts
    assert np.array_equal(_code_counts([1, 1, 300 - 256])[0][[1, 44]], [2, 1])  # a plain list


def test_roles_are_made_once_per_cloud_and_class_map(scene):
    xyz, want = scene
    flat = np.ones(len(xyz), np.uint8)
    first = cloud_roles(xyz, flat, ClassMap())
    assert cloud_roles(xyz, flat, ClassMap()) is first  # every surface of the cloud shares it
    assert not first.flags.writeable  # shared: nobody may change it in place
    off = cloud_roles(xyz, flat, ClassMap(infer="off"))  # another class map: its own roles
    assert np.all(off == classes.UNCLASSIFIED) and np.any(first != classes.UNCLASSIFIED)
    moved = xyz + 100.0  # the same classes over other points: inferred again, not reused
    again = cloud_roles(moved, flat, ClassMap())
    assert again is not first and np.array_equal(again, infer_roles(moved))


def test_always_fills_in_only_the_unclassified_points(scene):
    xyz, want = scene
    # the car alone has a role (3 % of the points), as the real case's inserted objects
    car = want == classes.CAR
    mixed = np.where(car, classes.POLE, 1).astype(np.uint8)
    got = cloud_roles(xyz, mixed, ClassMap(infer="always"))
    assert np.all(got[car] == classes.POLE)
    assert np.array_equal(got[~car], infer_roles(xyz)[~car])


def test_auto_infers_for_a_mostly_unclassified_cloud_and_leaves_a_mostly_classified_one(scene):
    xyz, want = scene
    car = want == classes.CAR
    # 97 % class 1 around a few classified objects (the real case: 68 % class 1 around the
    # inserted ones): read like an unclassified cloud, the objects keep their class
    mostly_plain = np.where(car, classes.POLE, 1).astype(np.uint8)
    assert infers(mostly_plain, ClassMap())
    got = cloud_roles(xyz, mostly_plain, ClassMap())
    assert np.all(got[car] == classes.POLE)
    assert np.array_equal(got[~car], infer_roles(xyz)[~car])
    # a classified cloud with some class 1 left (a third here: under half) is left as it is
    some_plain = want.copy()
    some_plain[::3] = 1
    assert not infers(some_plain, ClassMap())
    assert np.sum(cloud_roles(xyz, some_plain, ClassMap()) == classes.UNCLASSIFIED) == len(
        want[::3]
    )


def test_a_railing_gets_its_foot_back_from_the_ground_and_nothing_else_does(scene, inferred):
    xyz, want = scene
    base = np.where(xyz[:, 1] > 4, 0.12, 0.0) + 0.02 * xyz[:, 0]
    height = xyz[:, 2] - base
    foot = (height > 0.07) & (height < 0.28)  # within the ground's 0.3 m, clear of FOOT_M
    assert np.all(inferred[(want == classes.RAILING) & foot] == classes.RAILING)
    # the sidewalk under and beside it stays ground, and so do the pole's and the bin's feet
    rail_columns = (xyz[:, 0] >= 19.9) & (xyz[:, 0] <= 26.1) & (np.abs(xyz[:, 1] - 7.0) < 0.3)
    assert np.all(inferred[(want == classes.GROUND) & rail_columns] == classes.GROUND)
    for role in (classes.POLE, classes.FURNITURE):
        assert np.all(inferred[(want == role) & foot] == classes.GROUND)


def test_a_small_part_that_does_not_stand_on_the_ground_is_foliage_not_a_pole(scene):
    xyz, want = scene
    # a piece of a crown the LiDAR reached apart from its tree, 4.7-5.3 m up, and a pole
    # of the same footprint standing on the ground
    piece = ball(36.0, -3.0, 5.0 + 0.02 * 36.0, 0.3)
    pole = box(38, 38.2, -3, -2.8, 0.0, 5.4) + [0.0, 0.0, 0.02 * 38.0]
    got = infer_roles(np.concatenate([xyz, piece, pole]))
    n = len(xyz)
    assert np.all(got[n : n + len(piece)] == classes.VEGETATION)
    high = pole[:, 2] - 0.02 * 38.0 > 0.35  # above the ground's tolerance
    assert np.all(got[n + len(piece) :][high] == classes.POLE)


def test_the_surface_cache_keys_on_the_inference_switch(scene):
    xyz, want = scene
    cloud = PointCloud(xyz, np.zeros(3), np.ones(len(xyz), np.uint8))
    view = View("v", Intrinsics(64, 48, 50.0, 50.0, 32.0, 24.0), Pose(np.eye(3), np.zeros(3)))
    image = np.zeros((48, 64, 3), np.uint8)
    cache = SurfaceCache()
    off = DetectParams(classes=ClassMap(infer="off"))
    assert cache.key(image, view, cloud, DetectParams()) != cache.key(image, view, cloud, off)


@pytest.mark.parametrize(
    "value, want",
    [("always", "always"), (False, "off"), ("off", "off")],  # YAML 1.1: unquoted off is false
)
def test_the_switch_is_read_from_the_config(value, want):
    config = config_from_dict({"detect": {"classes": {"infer": value}}})
    assert config.detect.classes.infer == want


def test_a_bad_switch_is_named():
    with pytest.raises(InputError, match=r"classes.infer = 'sometimes' must be one of"):
        config_from_dict({"detect": {"classes": {"infer": "sometimes"}}})
    with pytest.raises(InputError, match="classes.infer"):
        dataclasses.replace(ClassMap(), infer="yes")


def test_the_results_hash_changes_with_the_switch_and_off_keeps_the_old_one():
    """Results of unclassified clouds change with the inference: views are detected again;
    ``off`` is the detector before it, and hashes as it did."""
    off = Config(DetectParams(classes=ClassMap(infer="off")))
    always = Config(DetectParams(classes=ClassMap(infer="always")))
    assert len({Config().results_hash(), off.results_hash(), always.results_hash()}) == 3
    assert off.detect.classes.table() == ClassMap().table()


@pytest.mark.parametrize("codes", [(), (2,), (6, 64, 65, 66, 67), tuple(range(256))])
def test_in_roles_is_numpys_isin(codes):
    raster = np.random.default_rng(7).integers(0, 256, (37, 53), dtype=np.uint8)
    got = in_roles(raster, codes)
    assert got.dtype == bool and got.shape == raster.shape
    assert np.array_equal(got, np.isin(raster, codes))
    assert in_roles(raster[:0], codes).shape == (0, 53)


def test_the_road_is_told_from_the_ground_only_by_the_clouds_own_classes(scene):
    """The reference-colour check looks at the ground only where the cloud tells its road
    from it (streetcd.detect.roles.road_told): inferred roles give both one role."""
    xyz, want = scene
    auto = ClassMap()
    with_road = want.copy()
    ground = np.flatnonzero(want == classes.GROUND)
    assert len(ground) > 0.02 * len(want)
    with_road[ground[: len(ground) // 2]] = classes.ROAD
    assert road_told(with_road, auto)
    assert not road_told(want, auto)  # no point is road
    mostly_flat = with_road.copy()
    mostly_flat[mostly_flat != classes.ROAD] = classes.UNCLASSIFIED  # the rest inferred
    assert infers(mostly_flat, auto) and not road_told(mostly_flat, auto)
    assert road_told(mostly_flat, ClassMap(infer="off"))  # nothing inferred: the road is told
    few = want.copy()
    few[ground[: int(0.005 * len(want))]] = classes.ROAD  # 0.5 % road: under the 1 % share
    assert not road_told(few, auto)
    why = road_told_codes(np.bincount(few, minlength=256), auto)
    assert (
        why is not None
        and why.startswith("only 0.")
        and why.endswith(" % of the points are road (detect.classes road)")
    )
    assert road_told_codes(np.bincount(with_road, minlength=256), auto) is None
    assert not road_told(np.empty(0, np.uint8), auto)
