"""Street segments: trajectory order, cuts by length and gaps, stable ids, neighbours."""

import numpy as np
import pytest

from streetcd.config import Config, CorrelateParams, DetectParams, RunParams, SegmentParams
from streetcd.errors import InputError
from streetcd.geometry.camera import look_at
from streetcd.run.segments import (
    Segment,
    cell_id,
    cut_points,
    order_views,
    path_order,
    plan_segments,
)
from streetcd.types import Intrinsics, View

E0, N0 = 372_000.0, 143_000.0  # UTM-sized coordinates, as real poses have
INTR = Intrinsics(640, 360, 400.0, 400.0, 319.5, 179.5)


def street(
    n, step_m=4.0, start=(E0 + 1.0, N0 + 1.0), along=(1.0, 0.0), prefix="a", t0=0.0, times=True
):
    """``n`` cameras driving along ``along``, 1.8 m high, looking sideways at a façade 12 m away."""
    along = np.asarray(along, dtype=float)
    side = np.array([-along[1], along[0]])
    views = []
    for i in range(n):
        xy = np.asarray(start) + i * step_m * along
        c = np.array([xy[0], xy[1], 101.8])
        target = np.array([*(xy + 12.0 * side + 3.0 * along), 103.0])
        views.append(
            View(f"{prefix}_{i:03d}.jpg", INTR, look_at(c, target), None, t0 + i if times else None)
        )
    return views


def test_order_by_time_ignores_input_order():
    views = street(12)
    shuffled = [views[i] for i in np.random.default_rng(3).permutation(12)]
    assert [v.name for v in order_views(shuffled)] == [v.name for v in views]


def test_order_by_path_without_times_follows_the_street():
    views = street(15, times=False)
    shuffled = [views[i] for i in np.random.default_rng(4).permutation(15)]
    names = [v.name for v in order_views(shuffled)]
    expected = [v.name for v in views]
    assert names in (expected, expected[::-1])


def test_path_order_is_a_permutation_and_walks_an_l_shape():
    leg1 = [(x, 0.0, 0.0) for x in range(0, 40, 4)]
    leg2 = [(36.0, y, 0.0) for y in range(4, 40, 4)]
    pts = np.array(leg1 + leg2, dtype=float)
    order = path_order(pts[np.random.default_rng(5).permutation(len(pts))])
    assert sorted(order.tolist()) == list(range(len(pts)))
    walked = pts[np.random.default_rng(5).permutation(len(pts))][order]
    steps = np.linalg.norm(np.diff(walked, axis=0), axis=1)
    np.testing.assert_allclose(steps, 4.0)  # never jumps: a true walk along the L


def test_cut_points_respects_length_and_is_maximal():
    centers = np.column_stack([np.arange(0, 101, 3.0), np.zeros(34), np.zeros(34)])
    pieces = cut_points(centers, length_m=20.0, max_gap_m=10.0)
    covered = np.concatenate([np.arange(len(centers))[p] for p in pieces])
    np.testing.assert_array_equal(covered, np.arange(len(centers)))
    for a, b in zip(pieces, pieces[1:], strict=False):
        c = centers[a]
        assert np.linalg.norm(np.diff(c[:, :2], axis=0), axis=1).sum() <= 20.0
        # one more view would have made the piece too long
        assert (
            np.linalg.norm(np.diff(centers[a.start : b.start + 1, :2], axis=0), axis=1).sum() > 20.0
        )


def test_segments_are_cells_of_a_fixed_grid_in_trajectory_order():
    views = street(40, step_m=4.9, start=(E0 + 1.0, N0 + 1.0))  # 191 m from E0 + 1 m
    segments = plan_segments(views, SegmentParams(length_m=50.0))
    names = [n for s in segments for n in s.views]
    assert names == [v.name for v in views]
    assert [s.id for s in segments] == [f"g50-E{int(E0) + 50 * k}-N{int(N0)}" for k in range(4)]
    by_name = {v.name: v for v in views}
    for s in segments:
        west = float(s.id.split("-E")[1].split("-N")[0])
        xs = [by_name[n].center[0] for n in s.views]
        assert all(west <= x < west + 50.0 for x in xs)


def test_the_same_street_gets_the_same_ids_whatever_images_arrive():
    night1 = street(30, step_m=4.0, start=(E0 + 1.0, N0 + 1.0))
    # Another night: other names, other times, one image missing, a slightly other path.
    night2 = street(30, step_m=4.0, start=(E0 + 1.7, N0 + 1.3), prefix="b", t0=5000.0)
    del night2[12]
    ids1 = [s.id for s in plan_segments(night1, SegmentParams(length_m=50.0))]
    ids2 = [s.id for s in plan_segments(night2, SegmentParams(length_m=50.0))]
    assert ids1 == ids2 == [f"g50-E{int(E0) + 50 * k}-N{int(N0)}" for k in range(3)]


def test_cell_ids_on_edges_negative_and_fractional_coordinates():
    assert cell_id(100.0, 0.0, 100.0) == "g100-E100-N0"
    assert cell_id(99.999, -0.001, 100.0) == "g100-E0-N-100"
    assert cell_id(3.0, 4.0, 2.5) == "g2.500-E2.500-N2.500"


def test_polyline_and_bbox_are_in_the_crs():
    views = street(10)
    params = SegmentParams(bbox_margin_m=15.0)
    (seg,) = plan_segments(views, params)
    np.testing.assert_allclose(seg.polyline, [v.center[:2] for v in views], atol=1e-6)
    lo = np.min(seg.polyline, axis=0) - 15.0
    hi = np.max(seg.polyline, axis=0) + 15.0
    np.testing.assert_allclose(seg.bbox, [lo[0], lo[1], hi[0], hi[1]])
    assert seg.length_m == pytest.approx(36.0)


def test_neighbours_are_the_overlapping_views_and_cross_segment_ends():
    views = street(12, step_m=4.0)
    segments = plan_segments(views, SegmentParams(length_m=20.0), n_neighbours=2)
    by_name = {v.name: v for v in views}
    for seg in segments:
        assert len(seg.neighbours) == len(seg.views)
        for name, nbrs in zip(seg.views, seg.neighbours, strict=True):
            assert name not in nbrs and len(nbrs) == 2
            i = int(name[2:5])
            # sideways cameras 4 m apart: the overlapping views are the two nearest
            assert {int(n[2:5]) for n in nbrs} <= {i - 2, i - 1, i + 1, i + 2}
            assert all(
                np.linalg.norm(by_name[n].center - by_name[name].center) <= 8.0 + 1e-9 for n in nbrs
            )
    last_of_first = segments[0].neighbours[-1]
    assert any(n not in segments[0].views for n in last_of_first)


def test_duplicate_names_and_bad_parameters_are_refused():
    views = street(3)
    with pytest.raises(InputError, match="a_000.jpg"):
        plan_segments(views + [views[0]])
    with pytest.raises(InputError, match="length_m"):
        SegmentParams(length_m=0.0)
    with pytest.raises(InputError, match="n_neighbours"):
        CorrelateParams(n_neighbours=0)


def test_no_views_no_segments():
    assert plan_segments([]) == []
    assert isinstance(plan_segments(street(1))[0], Segment)


def test_dense_acquisitions_rank_only_the_nearest_candidates():
    views = street(40, step_m=0.5)  # a camera every half metre: 40 within the radius
    (seg,) = plan_segments(views, SegmentParams(max_candidates=4), n_neighbours=3)
    for name, nbrs in zip(seg.views, seg.neighbours, strict=True):
        i = int(name[2:5])
        assert len(nbrs) == 3 and all(abs(int(n[2:5]) - i) <= 4 for n in nbrs)
    three = DetectParams(correlate=CorrelateParams(n_neighbours=3))
    with pytest.raises(InputError, match="max_candidates"):
        Config(three, RunParams(segments=SegmentParams(max_candidates=2)))


# --- segments from a city's road network (run.segments.roads) -------------------------------


def _linestring_wkb(xy):
    import struct

    return struct.pack("<BII", 1, 2, len(xy)) + np.asarray(xy, "<f8").tobytes()


def _write_roads(path, lines, ids=None, driver=None):
    """A road network file of (K, 2) lines, written with pyogrio as a city's GIS would."""
    import pyogrio.raw

    fields = [np.array(ids, dtype=object)] if ids is not None else []
    pyogrio.raw.write(
        str(path),
        geometry=np.array([_linestring_wkb(xy) for xy in lines], dtype=object),
        field_data=fields,
        fields=["street"] if ids is not None else [],
        geometry_type="LineString",
        crs="EPSG:32631",
        driver=driver,
    )


def test_project_on_polyline_gives_chainage_and_distance():
    from streetcd.geometry.chainage import project_on_polyline

    line = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 100.0]])
    chainage, dist = project_on_polyline(np.array([[50, 3], [103, 40], [-5, 0]]), line)
    np.testing.assert_allclose(chainage, [50.0, 140.0, 0.0])
    np.testing.assert_allclose(dist, [3.0, 3.0, 5.0])


@pytest.mark.parametrize("suffix", [".gpkg", ".geojson"])
def test_road_pieces_keep_their_ids_whatever_images_arrive(tmp_path, suffix):
    roads = tmp_path / f"roads{suffix}"
    # the street's centre line runs 3 m beside the cameras, from 20 m before the first one
    _write_roads(roads, [[(E0 - 20.0, N0 - 2.0), (E0 + 400.0, N0 - 2.0)]], ids=["Main St"])
    params = SegmentParams(length_m=50.0, roads=str(roads), roads_id_field="street")
    night1 = street(30)  # cameras every 4 m from E0 + 1
    segs1 = plan_segments(night1, params)
    ids1 = {v: s.id for s in segs1 for v in s.views}
    # chainage of camera i: 21 + 4 i m; pieces of 50 m from the line's first vertex
    assert ids1["a_000.jpg"] == "r50-Main_St-C0"
    assert ids1["a_008.jpg"] == "r50-Main_St-C50"  # chainage 53 m
    # another night: other names, one image missing, the cameras 1 m to the side
    night2 = [v for i, v in enumerate(street(30, start=(E0 + 1.0, N0), prefix="b")) if i != 10]
    ids2 = {v: s.id for s in plan_segments(night2, params) for v in s.views}
    for name, seg in ids2.items():
        assert seg == ids1[name.replace("b_", "a_")]


def test_views_far_from_every_road_fall_back_to_the_grid(tmp_path):
    roads = tmp_path / "roads.geojson"
    _write_roads(roads, [[(E0, N0 + 500.0), (E0 + 400.0, N0 + 500.0)]])
    params = SegmentParams(roads=str(roads))
    segs = plan_segments(street(5), params)
    assert [s.id for s in segs] == [plan_segments(street(5), SegmentParams())[0].id]
    assert segs[0].id.startswith("g100-")


def test_a_bad_road_network_names_the_file(tmp_path):
    from streetcd.errors import MissingInputError

    with pytest.raises(MissingInputError, match="roads.gpkg: road network not found"):
        plan_segments(street(3), SegmentParams(roads=str(tmp_path / "roads.gpkg")))
    junk = tmp_path / "junk.geojson"
    junk.write_text('{"type": "FeatureCollection", "features": [')
    with pytest.raises(InputError, match="junk.geojson: cannot read the road network"):
        plan_segments(street(3), SegmentParams(roads=str(junk)))
    roads = tmp_path / "roads.geojson"
    _write_roads(roads, [[(E0, N0), (E0 + 9.0, N0)]], ids=["a"])
    with pytest.raises(InputError, match="no field 'name'"):
        plan_segments(street(3), SegmentParams(roads=str(roads), roads_id_field="name"))
    poly = tmp_path / "poly.geojson"
    poly.write_text(
        '{"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {}, '
        '"geometry": {"type": "Point", "coordinates": [0, 0]}}]}'
    )
    with pytest.raises(InputError, match="poly.geojson: feature 0: geometry type 1"):
        plan_segments(street(3), SegmentParams(roads=str(poly)))


def test_a_road_network_changes_the_results_hash():
    base = Config()
    roads = Config(run=RunParams(segments=SegmentParams(roads="roads.gpkg")))
    assert roads.results_hash() != base.results_hash()
