"""Change objects: per-view regions merged in 3D across views and nights, kinds, transients,
reviews that later nights respect, and the read-only listing (docs/DECISIONS.md contract).

The street: cameras every 3 m along x, looking sideways (+y) at a façade 12 m away. The
regions are made as the detector locates them, on the old surface behind their pixels: a
removed pole's regions lie on the pole; an added box's regions lie on the façade, where each
view's line of sight through the box meets it.
"""

import json
import os
import sqlite3
import stat

import numpy as np
import pytest
from click.testing import CliRunner
from test_segments import E0, N0, street

from streetcd import classes as C
from streetcd.cli.main import query as query_cmd
from streetcd.cli.review import review as review_cmd
from streetcd.errors import InputError, MissingInputError
from streetcd.geometry.merge import link_regions, nearest_to_rays
from streetcd.run.segments import SegmentParams, plan_segments
from streetcd.store.index import ChangeIndex
from streetcd.store.objects import list_objects, rebuild_objects, record_review, sees
from streetcd.store.records import RegionRecord, ViewRecord, camera_json

FACADE_Y = N0 + 1.0 + 12.0
POLE = np.array([E0 + 16.0, N0 + 1.0 + 8.0, 102.0])  # an old pole, gone
BOX = np.array([E0 + 25.0, N0 + 1.0 + 5.0, 102.3])  # a new box, 5 m from the cameras
BIN = np.array([E0 + 34.0, N0 + 1.0 + 6.0, 102.0])  # another new object, on night 2 only
PARAMS = SegmentParams(length_m=100.0)


def _on_facade(camera, point):
    """Where the line of sight from ``camera`` through ``point`` meets the façade."""
    t = (FACADE_Y - camera[1]) / (point[1] - camera[1])
    return camera + t * (point - camera)


def view_record(
    v, key, segment, regions, day="2026-11-01", mask_path=None, overlay_path=None
) -> ViewRecord:
    """A done view's record as a night publishes it: key ``<name>#<key>``, flagged (score
    0.8) when it has ``regions``, captured at 02:00 on ``day``."""
    return ViewRecord(
        f"{v.name}#{key}",
        "h",
        "p",
        segment,
        "done",
        flagged=bool(regions),
        score=0.8 if regions else 0.0,
        regions=tuple(regions),
        mask_path=mask_path,
        overlay_path=overlay_path,
        center=tuple(float(x) for x in v.center),
        captured_at=f"{day}T02:00:00Z",
        image=v.name,
        camera=camera_json(v),
    )


def _region(label, centroid, half, cls, rng):
    c = np.asarray(centroid) + rng.normal(0, 0.03, 3)
    return RegionRecord(label, 4000, 0.8, tuple(c), tuple(c - half), tuple(c + half), cls)


def night(index, suffix, changes, day, skip=(), run="r", ground=None):
    """Publish one night of the street: each view that sees a change gets a region for it
    (except the views in ``skip``); view keys carry ``suffix`` as their content hash."""
    rng = np.random.default_rng(len(suffix) + len(changes))
    views = street(16, step_m=3.0)
    segments = plan_segments(views, PARAMS)
    seg = {n: s.id for s in segments for n in s.views}
    records = []
    for v in views:
        regions = []
        for kind, point in changes:
            if v.name in skip or not sees(v, point):
                continue
            if kind == "removed":
                g = _region(len(regions) + 1, point, np.array([0.15, 0.15, 1.0]), C.POLE, rng)
            else:
                hit = _on_facade(v.center, point)
                g = _region(len(regions) + 1, hit, np.array([0.7, 0.05, 0.7]), C.BUILDING, rng)
            regions.append(g)
        records.append(
            view_record(
                v,
                suffix,
                seg[v.name],
                regions,
                day,
                mask_path=f"/out/masks/{v.stem}-{suffix}.png" if regions else None,
                overlay_path=f"/out/overlays/{v.stem}-{suffix}.jpg" if regions else None,
            )
        )
    with ChangeIndex(index) as idx:
        idx.add_segments(segments)
        idx.publish(run, records)
        rebuild_objects(idx, [s.id for s in segments], ground)
    return [s.id for s in segments]


def seers(point):
    return [v.name for v in street(16, step_m=3.0) if sees(v, point)]


@pytest.fixture
def one_night(tmp_path):
    index = tmp_path / "change_index.sqlite"
    night(index, "aaa", [("removed", POLE), ("added", BOX)], "2026-11-01")
    return index


def test_one_object_per_physical_change_with_its_views(one_night):
    objects = list_objects(one_night, sort="id")
    assert len(objects) == 2
    by_kind = {o["kind"]: o for o in objects}
    assert set(by_kind) == {"removed", "added"}
    pole, box = by_kind["removed"], by_kind["added"]
    assert len(seers(POLE)) >= 3 and len(seers(BOX)) >= 3
    for o, point in ((pole, POLE), (box, BOX)):
        assert sorted(v["image"] for v in o["views"]) == sorted(seers(point))
        assert all(v["sees_change"] and v["overlay"].endswith("-aaa.jpg") for v in o["views"])
        assert o["first_seen"] == o["last_seen"] == "2026-11-01"
        assert o["review"] is None and o["transient"] is None
        lo, hi = np.array(o["bbox"][:3]), np.array(o["bbox"][3:])
        assert np.all(lo <= o["centroid"]) and np.all(np.array(o["centroid"]) <= hi)
    assert pole["class"] == C.POLE
    np.testing.assert_allclose(pole["centroid"], POLE, atol=0.1)
    # The added box is where the lines of sight meet, not on the façade behind it.
    np.testing.assert_allclose(box["centroid"], BOX, atol=0.3)
    assert box["confidence"] == pytest.approx(1 - 0.5 ** len(seers(BOX)), abs=1e-6)


def test_views_that_see_the_spot_without_a_change_lower_the_confidence(tmp_path):
    index = tmp_path / "i.sqlite"
    missing = seers(POLE)[1:3]
    night(index, "aaa", [("removed", POLE)], "2026-11-01", skip=missing)
    (pole,) = list_objects(index)
    without = sorted(v["image"] for v in pole["views"] if not v["sees_change"])
    assert without == sorted(missing)
    n = len(seers(POLE)) - 2
    assert pole["confidence"] == pytest.approx(n / (n + 2) * (1 - 0.5**n), abs=1e-6)


def test_a_change_seen_by_one_view_only_is_a_transient_with_its_reason(tmp_path):
    index = tmp_path / "i.sqlite"
    night(index, "aaa", [("added", BOX)], "2026-11-01", skip=seers(BOX)[1:])
    (o,) = list_objects(index)
    assert "seen by one view only" in o["transient"]
    assert list_objects(index, status="awaiting") == []
    assert [x["id"] for x in list_objects(index, status="transient")] == [o["id"]]


def test_two_nights_with_reused_names_are_both_kept_and_merge_into_the_same_objects(one_night):
    first = {o["kind"]: o["id"] for o in list_objects(one_night)}
    night(one_night, "bbb", [("removed", POLE), ("added", BOX)], "2026-11-02", run="r2")
    with ChangeIndex(one_night, readonly=True) as idx:
        keys = [r[0] for r in idx.conn.execute("SELECT view FROM views")]
    assert len(keys) == 32 and len({k.split("#")[0] for k in keys}) == 16
    objects = list_objects(one_night)
    assert {o["kind"]: o["id"] for o in objects} == first  # ids last from night to night
    for o in objects:
        assert (o["first_seen"], o["last_seen"]) == ("2026-11-01", "2026-11-02")
        suffixes = {v["view"].split("#")[1] for v in o["views"]}
        assert suffixes == {"aaa", "bbb"}


def test_a_change_gone_on_a_later_night_came_and_went(one_night):
    night(one_night, "bbb", [("removed", POLE)], "2026-11-02", run="r2")
    box = next(o for o in list_objects(one_night) if o["kind"] == "added")
    assert box["transient"].startswith("gone on a later night (2026-11-02)")


def test_a_dismissed_change_is_not_flagged_again_but_a_new_one_is(one_night):
    box = next(o for o in list_objects(one_night) if o["kind"] == "added")
    out = CliRunner().invoke(
        review_cmd,
        [box["id"], "--index", str(one_night), "--status", "false-alarm", "--note", "a skip"],
    )
    assert out.exit_code == 0, out.output
    awaiting = [o["id"] for o in list_objects(one_night, status="awaiting")]
    assert box["id"] not in awaiting and len(awaiting) == 1
    # Next night: the street is unchanged at the box (the detector flags it again against
    # the old cloud), and a new object has appeared further along.
    night(one_night, "bbb", [("removed", POLE), ("added", BOX), ("added", BIN)], "2026-11-02")
    objects = {o["id"]: o for o in list_objects(one_night)}
    kept = objects[box["id"]]
    assert kept["review"]["status"] == "false_alarm" and kept["review"]["note"] == "a skip"
    assert kept["last_seen"] == "2026-11-02"
    awaiting = list_objects(one_night, status="awaiting")
    assert box["id"] not in [o["id"] for o in awaiting]
    (bin_,) = [o for o in awaiting if o["first_seen"] == "2026-11-02"]
    np.testing.assert_allclose(bin_["centroid"], BIN, atol=0.3)


def test_a_fixed_change_seen_again_is_a_new_change(one_night):
    pole = next(o for o in list_objects(one_night) if o["kind"] == "removed")
    record_review(one_night, pole["id"], "fixed", who="ana")
    assert list_objects(one_night, status="fixed")[0]["review"]["who"] == "ana"
    night(one_night, "bbb", [("removed", POLE)], "2099-01-01", run="r2")
    again = [o for o in list_objects(one_night, status="awaiting") if o["kind"] == "removed"]
    assert len(again) == 1 and again[0]["id"] != pole["id"]
    assert again[0]["first_seen"] == "2099-01-01"


def test_reviews_refuse_bad_statuses_and_unknown_objects(one_night):
    oid = list_objects(one_night)[0]["id"]
    with pytest.raises(InputError, match="status 'maybe'"):
        record_review(one_night, oid, "maybe", who="x")
    with pytest.raises(MissingInputError, match="o-nothere"):
        record_review(one_night, "o-nothere", "confirmed", who="x")
    out = CliRunner().invoke(
        review_cmd, ["o-nothere", "--index", str(one_night), "--status", "fixed"]
    )
    assert out.exit_code == 1 and "o-nothere" in out.output


def test_listing_filters_and_opens_read_only(one_night):
    before = one_night.read_bytes()
    all_ = list_objects(one_night)
    assert [o["confidence"] for o in all_] == sorted((o["confidence"] for o in all_), reverse=True)
    assert [o["kind"] for o in list_objects(one_night, kind="added")] == ["added"]
    x, y = POLE[:2]
    assert [o["kind"] for o in list_objects(one_night, bbox=(x - 1, y - 1, x + 1, y + 1))] == [
        "removed"
    ]
    assert len(list_objects(one_night, limit=1)) == 1
    assert list_objects(one_night, segment="nope") == []
    bare = list_objects(one_night, with_views=False)  # what the table reads: counts, no list
    assert [o["views"] for o in bare] == [[], []]
    assert [{**o, "views": []} for o in all_] == bare
    with pytest.raises(InputError, match="kind"):
        list_objects(one_night, kind="moved")
    with pytest.raises(InputError, match="limit"):
        list_objects(one_night, limit=-1)
    os.chmod(one_night, stat.S_IRUSR)
    try:
        assert len(list_objects(one_night)) == 2
    finally:
        os.chmod(one_night, stat.S_IRUSR | stat.S_IWUSR)
    assert one_night.read_bytes() == before


def test_rebuilding_is_deterministic(one_night):
    def dump():
        con = sqlite3.connect(one_night)
        rows = con.execute("SELECT * FROM objects ORDER BY object_id").fetchall()
        views = con.execute("SELECT * FROM object_views ORDER BY object_id, view").fetchall()
        con.close()
        return [r[1:] for r in rows], views

    before = dump()
    with ChangeIndex(one_night) as idx:
        rebuild_objects(idx, [s.segment_id for s in idx.segments()])
    assert dump() == before


def test_the_configs_region_rule_decides_which_objects_are_too_small(one_night):
    # every region covers 4000 of 640 x 360 px (1.7 %): changes under the default 0.2 %
    # rule, too small under a 2 % rule (run.min_region_fraction, passed by the night)
    assert len(list_objects(one_night, transients=False)) == 2
    with ChangeIndex(one_night) as idx:
        rebuild_objects(idx, [s.segment_id for s in idx.segments()], min_region_fraction=0.02)
    assert list_objects(one_night, transients=False) == []
    kept_out = list_objects(one_night)
    assert len(kept_out) == 2
    assert all(
        o["transient"].startswith("small: no view's region of it covers 2.0%") for o in kept_out
    )


def test_the_kernels_link_what_meets_and_only_that():
    # Two boxes that touch, one far away.
    c = np.array([[0, 0, 0], [0.9, 0, 0], [10, 0, 0]], dtype=float)
    labels = link_regions(c, c - 0.3, c + 0.3, margin_m=0.2)
    assert labels.tolist() == [0, 0, 1]
    # Rays from two cameras through a common point meet there.
    origins = np.array([[0, 0, 0], [4, 0, 0], [8, 0, 0]], dtype=float)
    p = np.array([3.0, 5.0, 1.0])
    x, miss = nearest_to_rays(origins, origins + 2.5 * (p - origins))
    np.testing.assert_allclose(x, p, atol=1e-9)
    assert miss < 1e-9
    _, miss = nearest_to_rays(origins[:2], origins[:2] + np.array([0, 1.0, 0]))
    assert miss == float("inf")  # parallel lines of sight say nothing of depth


def test_query_lists_objects_views_and_geojson(one_night):
    run = CliRunner().invoke
    args = ["--index", str(one_night), "--format"]
    data = json.loads(run(query_cmd, [*args, "json"]).output)
    assert sorted(o["kind"] for o in data["objects"]) == ["added", "removed"]
    for key in ("id", "kind", "confidence", "centroid", "bbox", "views", "first_seen", "review"):
        assert all(key in o for o in data["objects"])
    views = json.loads(run(query_cmd, [*args, "json", "--views"]).output)["views"]
    flagged = {v for o in data["objects"] for v in (w["view"] for w in o["views"])}
    assert {v["id"] for v in views} == flagged
    assert all(v["id"] == f"{v['image']}#aaa" and v["segment"] and v["score"] for v in views)
    gj = json.loads(run(query_cmd, [*args, "geojson", "--native-crs"]).output)
    assert len(gj["features"]) == 2
    for f in gj["features"]:
        assert f["geometry"]["type"] == "Polygon"
        assert f["properties"]["overlays"] and all(
            p.endswith("-aaa.jpg") for p in f["properties"]["overlays"]
        )
    table = run(query_cmd, [*args, "table"]).output.splitlines()
    for o in data["objects"]:  # the table's view counts, read without the views' list
        (line,) = [t for t in table if t.startswith(o["id"])]
        assert f"{o['n_views']:>3}/{o['n_views'] + o['n_without']:<3}" in line
    oid = data["objects"][0]["id"]
    assert run(review_cmd, [oid, "--index", str(one_night), "--status", "confirmed"]).exit_code == 0
    left = json.loads(run(query_cmd, [*args, "json", "--awaiting-review"]).output)
    assert [o["id"] for o in left["objects"]] == [data["objects"][1]["id"]]


def test_an_added_object_standing_on_the_road_is_a_transient(tmp_path):
    index = tmp_path / "i.sqlite"
    asked = []

    def road_under_the_box(x, y):
        asked.append((x, y))
        return C.ROAD if abs(x - BOX[0]) < 1 and abs(y - BOX[1]) < 1 else C.GROUND

    night(
        index, "aaa", [("removed", POLE), ("added", BOX)], "2026-11-01", ground=road_under_the_box
    )
    by_kind = {o["kind"]: o for o in list_objects(index)}
    assert by_kind["added"]["transient"].startswith("stands on the road")
    assert by_kind["removed"]["transient"] is None
    assert len(asked) == 1  # only an added object is looked under, where it stands
    np.testing.assert_allclose(asked[0], BOX[:2], atol=0.3)


def test_a_regions_foot_is_the_old_class_just_below_it():
    from streetcd.detect.regions import changed_regions
    from streetcd.types import Intrinsics, Pose

    h, w = 100, 80
    mask = np.zeros((h, w), bool)
    mask[20:60, 30:50] = True  # a car's cabin, flagged against the wall behind
    classes = np.full((h, w), C.BUILDING, np.uint8)
    classes[60:, :] = C.ROAD  # its body hides the road: the rows just below are road
    depth = np.full((h, w), 10.0, np.float32)
    intr = Intrinsics(w, h, 80.0, 80.0, w / 2, h / 2)
    _, (g,) = changed_regions(
        mask, mask.astype(np.float32), depth, classes, intr, Pose(np.eye(3), np.zeros(3))
    )
    assert g.dominant_class == C.BUILDING and g.foot_class == C.ROAD
    classes[60:, :] = 0  # no old surface below it: unknown
    _, (g,) = changed_regions(
        mask, mask.astype(np.float32), depth, classes, intr, Pose(np.eye(3), np.zeros(3))
    )
    assert g.foot_class == 0


def test_an_old_cars_changed_pixels_are_a_region_apart_from_a_new_poles_beside_it():
    from streetcd.detect.regions import changed_regions, cut_apart
    from streetcd.types import Intrinsics, Pose

    h, w = 60, 80
    classes = np.full((h, w), C.BUILDING, np.uint8)
    classes[20:50, 40:70] = C.CAR  # a car of the old cloud, gone
    classes[25:30, 50:60] = 0  # its windows: no old surface
    mask = np.zeros((h, w), bool)
    mask[10:50, 30:40] = True  # a new pole before the wall, touching...
    mask[20:50, 40:70] = True  # ...the car's pixels, gone from the image
    mask[5:10, 30:40] = True  # the sky above the pole (no old surface): the pole's side
    classes[5:10, 30:40] = 0
    cut = cut_apart(mask, classes, (C.CAR, C.PEDESTRIAN))
    # one pixel-wide line of the car's pixels along the pole is left out, nothing else
    assert (mask & ~cut).sum() == 30 and not (cut & ~mask).any()
    assert not cut[20:50, 40].any() and cut[20:50, 41:70].all()
    intr = Intrinsics(w, h, 80.0, 80.0, w / 2, h / 2)
    depth = np.full((h, w), 10.0, np.float32)
    labels, regions = changed_regions(
        cut, cut.astype(np.float32), depth, classes, intr, Pose(np.eye(3), np.zeros(3))
    )
    assert sorted((g.pixels, g.dominant_class) for g in regions) == [
        (450, C.BUILDING),  # the pole and the sky above it
        (30 * 29, C.CAR),  # the car, its windows with it
    ]
    assert labels[7, 35] == labels[30, 35] != labels[27, 55] == labels[45, 65]
    # off, or no old vehicle under the mask: the mask as it is (the same array)
    assert cut_apart(mask, classes, ()) is mask
    assert cut_apart(mask, np.full((h, w), C.BUILDING, np.uint8), (C.CAR,)) is mask


def test_a_component_without_any_old_surface_is_not_cut():
    from streetcd.detect.regions import cut_apart

    classes = np.zeros((30, 30), np.uint8)
    classes[:, 20:] = C.CAR
    mask = np.zeros((30, 30), bool)
    mask[5:15, 2:10] = True  # no old surface at all: a region of its own, as it is
    mask[5:15, 22:28] = True  # on the car alone: nothing else to cut it from
    assert (cut_apart(mask, classes, (C.CAR,)) == mask).all()


def publish(index, regions_of, ground=None, params=PARAMS):
    """Publish one night of the street (2026-11-01) in which ``regions_of(view)`` gives each
    view's regions (labels 1, 2, …), and rebuild the objects with ``ground``. Returns the
    segments (``params``: how the street is cut)."""
    views = street(16, step_m=3.0)
    segments = plan_segments(views, params)
    seg = {n: s.id for s in segments for n in s.views}
    records = []
    for v in views:
        regions = tuple(regions_of(v))
        records.append(
            view_record(
                v,
                "aaa",
                seg[v.name],
                regions,
                mask_path=f"/out/masks/{v.stem}.png" if regions else None,
            )
        )
    with ChangeIndex(index) as idx:
        idx.add_segments(segments)
        idx.publish("r", records)
        rebuild_objects(idx, [s.id for s in segments], ground)
    return segments


CAR = np.array([E0 + 20.0, N0 + 1.0 + 6.0, 101.5])  # a car parked on the road since the scan


def _car_regions(v):
    """The car's region on the façade behind it; the first view that sees it has it cut
    short by the image border, its centroid 3 m off, so not every region covers the point
    where the lines of sight meet (the object's kind is unknown, not added)."""
    if not sees(v, CAR):
        return []
    hit = _on_facade(v.center, CAR)
    if v.name == seers(CAR)[0]:
        hit = hit + np.array([3.0, 0.0, 0.0])
    half = np.array([0.2, 0.05, 0.2])
    return [
        RegionRecord(1, 4000, 0.8, tuple(hit), tuple(hit - half), tuple(hit + half), C.BUILDING)
    ]


def test_an_object_whose_lines_of_sight_meet_over_the_road_is_a_transient(tmp_path):
    def road_near_the_car(x, y):
        return C.ROAD if abs(y - CAR[1]) < 2.5 else C.GROUND

    publish(tmp_path / "a.sqlite", _car_regions, road_near_the_car)
    (car,) = list_objects(tmp_path / "a.sqlite")
    assert car["kind"] == "unknown"
    assert sorted(v["image"] for v in car["views"] if v["sees_change"]) == seers(CAR)
    assert car["transient"].startswith("stands on the road (its views' lines of sight meet")
    # The same regions where the old cloud has ground (a sidewalk): a change of the street.
    publish(tmp_path / "b.sqlite", _car_regions, lambda x, y: C.GROUND)
    (thing,) = list_objects(tmp_path / "b.sqlite")
    assert thing["kind"] == "unknown" and thing["transient"] is None


SPOT = np.array([E0 + 57.0, FACADE_Y, 102.0])  # where the street's last two views see a car


def _cabin_regions(fractions):
    """The regions of the two views that see SPOT, on that one spot of the façade (as where
    each sees a different part of a parked car: no parallax between them, so the meeting of
    their lines of sight tells nothing), with the depth fractions ``fractions`` (None: not
    measured) at which each view and its neighbours agree."""

    def regions_of(v):
        names = seers(SPOT)
        if v.name not in names:
            return []
        i = names.index(v.name)
        half = np.array([0.3, 0.05, 0.3])
        c = SPOT + np.array([0.05 * i, 0.0, 0.0])
        return [
            RegionRecord(
                1,
                4000,
                0.8,
                tuple(c),
                tuple(c - half),
                tuple(c + half),
                C.BUILDING,
                0,
                fractions[i],
            )
        ]

    return regions_of


def test_an_object_whose_regions_stand_on_the_road_is_a_transient(tmp_path):
    """Cameras 3 m apart, 12 m from the façade: at a depth fraction of 0.45 the two regions
    stand 1.65 m apart (they agree), 5.4 m from the cameras, over the road (y within 2.5 m
    of the car's); on the façade they would be on the sidewalk. Within a metre of the kerb
    they could be a railing as well."""
    assert len(seers(SPOT)) == 2

    def road_near_the_car(x, y):
        return C.ROAD if abs(y - CAR[1]) < 2.5 else C.GROUND

    def road_up_to(kerb_y):  # the regions stand at y = N0 + 6.4
        return lambda x, y: C.ROAD if y < kerb_y else C.GROUND

    cases = {
        "both on the road": ((0.45, 0.45), road_near_the_car, "stands on the road (where"),
        "one measured": ((0.45, None), road_near_the_car, "stands on the road (where"),
        "none measured": ((None, None), road_near_the_car, None),
        "on the sidewalk": ((0.45, 0.45), lambda x, y: C.GROUND, None),
        "half a metre from the kerb": ((0.45, 0.45), road_up_to(N0 + 6.9), None),
        "a metre and a half from it": ((0.45, 0.45), road_up_to(N0 + 7.9), "stands on the road"),
        "in front of the façade": ((0.95, 0.95), road_near_the_car, None),
        "6 m apart: they disagree": ((0.45, 0.95), road_near_the_car, None),
    }
    for k, (fractions, ground, want) in enumerate(cases.values()):
        publish(tmp_path / f"{k}.sqlite", _cabin_regions(fractions), ground)
        (thing,) = list_objects(tmp_path / f"{k}.sqlite")
        got = thing["transient"]
        assert (got is None) if want is None else got.startswith(want), (fractions, got)
        assert thing["kind"] == "unknown"


def test_a_region_chained_to_a_change_whose_line_of_sight_disagrees_is_split_off(tmp_path):
    """The views that see the new box each have its region on the façade; a view further
    on has a region of something else (a car parked along the street) on the façade just
    beside the first view's. The regions touch, so the links chain them, but that view's
    line of sight passes metres from where the others meet: it is split off, and the box
    stays one object of its own views."""
    seeing = seers(BOX)
    views = {v.name: v for v in street(16, step_m=3.0)}
    beside = _on_facade(views[seeing[0]].center, BOX) + np.array([1.2, 0.0, 0.0])
    stray_view = "a_011.jpg"
    assert stray_view not in seeing and sees(views[stray_view], beside)
    half = np.array([0.7, 0.05, 0.7])

    def regions(v):
        if v.name in seeing:
            hit = _on_facade(v.center, BOX)
        elif v.name == stray_view:
            hit = beside
        else:
            return []
        return [
            RegionRecord(1, 4000, 0.8, tuple(hit), tuple(hit - half), tuple(hit + half), C.BUILDING)
        ]

    publish(tmp_path / "a.sqlite", regions)
    objects = list_objects(tmp_path / "a.sqlite", sort="id")
    assert len(objects) == 2
    box = next(o for o in objects if o["kind"] == "added")
    other = next(o for o in objects if o is not box)
    assert sorted(v["image"] for v in box["views"] if v["sees_change"]) == seeing
    assert box["transient"] is None
    np.testing.assert_allclose(box["centroid"], BOX, atol=0.3)
    assert [v["image"] for v in other["views"] if v["sees_change"]] == [stray_view]
    assert other["transient"] is not None
    # Without the stray view the box is the same object: the split left it whole.
    publish(tmp_path / "b.sqlite", lambda v: regions(v) if v.name != stray_view else [])
    (alone,) = list_objects(tmp_path / "b.sqlite")
    assert alone["id"] == box["id"] and alone["centroid"] == box["centroid"]


def test_the_road_test_answers_what_a_scan_of_the_whole_tiles_answers(tmp_path, monkeypatch):
    """ground_classes reads each tile once (its stored x, y and classes only) and tests the
    points of a small square of it: its answers are those of the old scan of every point
    of the tiles, at points near tile edges and corners too, with the LRU evicting tiles
    between calls."""
    from streetcd.io.las import write_las
    from streetcd.store import objects
    from streetcd.store.ingest import ingest
    from streetcd.store.tiles import TileStore

    origin = np.array([500_000.0, 5_200_000.0, 0.0])
    rng = np.random.default_rng(3)
    xyz = np.round(rng.uniform([0, 0, 0], [30.0, 20.0, 3.0], (20_000, 3)), 3)
    cls = np.where(xyz[:, 1] < 8.0, 11, rng.integers(1, 7, len(xyz)))  # 11: road (LAS code)
    write_las(tmp_path / "a" / "s.laz", xyz, cls, origin=origin, crs="EPSG:32633")
    assert ingest(tmp_path / "a", tmp_path / "s.zarr", tile_size_m=10.0, workers=1).ok
    store = TileStore.open(tmp_path / "s.zarr")
    roles = np.asarray(objects.ClassMap().table(), np.uint8)

    def scan(x, y, r=0.75):  # the former answer: every point of every tile in the box
        codes = []
        for t in store.tiles_in_bbox(x - r, y - r, x + r, y + r):
            cloud = store.read_tile(t.id, cache=False)
            near = np.sum((cloud.xyz[:, :2] + cloud.origin[:2] - (x, y)) ** 2, axis=1) <= r**2
            codes.append(roles[cloud.classification[near]])
        allc = np.concatenate(codes) if codes else np.zeros(0, np.uint8)
        return int(np.bincount(allc).argmax()) if allc.size else None

    monkeypatch.setattr(objects, "GROUND_CACHE_BYTES", 40_000)  # a tile or two at a time
    monkeypatch.setattr(objects, "GROUND_CHUNK_BYTES", 0)
    at = objects.ground_classes(tmp_path / "s.zarr")
    points = [*rng.uniform([-1, -1], [31, 21], (150, 2)), (10.0, 10.0), (20.2, 9.9), (-5, 5)]
    answers = [at(origin[0] + px, origin[1] + py) for px, py in points]
    assert answers == [scan(origin[0] + px, origin[1] + py) for px, py in points]
    assert C.ROAD in answers and None in answers and len(set(answers)) > 2
    assert objects.ground_classes(tmp_path / "nothing.zarr")(origin[0], origin[1]) is None


def _box_regions(v):
    """The new box's region on the façade behind it, in each view that sees it."""
    if not sees(v, BOX):
        return []
    hit = _on_facade(v.center, BOX)
    half = np.array([0.3, 0.05, 0.3])
    return [
        RegionRecord(1, 4000, 0.8, tuple(hit), tuple(hit - half), tuple(hit + half), C.BUILDING)
    ]


def test_a_change_seen_from_two_segments_is_one_object_of_one_segment(tmp_path):
    """Segments of 20 m: the box is seen by one view of the first cell and two of the next.
    Each segment's regions are linked with its neighbour's, and the object belongs to the
    segment of its first region; rebuilding either segment alone gives the same object."""
    index = tmp_path / "a.sqlite"
    segments = publish(index, _box_regions, params=SegmentParams(length_m=20.0))
    seg_of = {n: s.id for s in segments for n in s.views}
    assert len({seg_of[n] for n in seers(BOX)}) == 2
    (box,) = list_objects(index)
    assert box["kind"] == "added" and box["transient"] is None
    assert sorted(v["image"] for v in box["views"] if v["sees_change"]) == seers(BOX)
    assert box["segment"] == seg_of[seers(BOX)[0]]
    np.testing.assert_allclose(box["centroid"], BOX, atol=0.3)
    for seg in {seg_of[n] for n in seers(BOX)}:
        with ChangeIndex(index) as idx:
            rebuild_objects(idx, [seg])
        assert list_objects(index) == [box]


def test_a_speck_touching_another_views_large_region_is_not_linked_to_it():
    c = np.array([[0, 0, 0], [0.5, 0, 0]], dtype=float)
    lo, hi = c - 0.3, c + 0.3
    views = np.array([0, 1])
    assert link_regions(c, lo, hi, view_ids=views).tolist() == [0, 0]
    like = np.array([4000, 801])  # within 5 times: one thing seen from two views
    assert link_regions(c, lo, hi, view_ids=views, pixels=like).tolist() == [0, 0]
    speck = np.array([4000, 799])
    assert link_regions(c, lo, hi, view_ids=views, pixels=speck).tolist() == [0, 1]
    # Two parts of one view's object (boxes overlapping by half) are not compared by size.
    c[1, 0] = 0.1
    lo, hi = c - 0.3, c + 0.3
    assert link_regions(c, lo, hi, view_ids=np.array([0, 0]), pixels=speck).tolist() == [0, 0]


def test_two_parts_of_one_view_wait_their_turn_among_the_links():
    """View 0 has a large region (a board and a car's roof) and a flat one inside its box
    (the car's lower half); view 1 has the board and the car's lower half apart. The links
    between views are closer than the two parts of view 0, so they come first: the board's
    regions are one object and the car's another. Joined first, the two parts of view 0
    took the board's region of view 1 and left the car's alone."""
    c = np.array([[0, 0, 1.0], [0, 0, 0.1], [0.3, 0, 1.0], [0, 0.5, 0.1]])
    lo = np.array([[-1, -1, 0], [-0.8, -0.8, 0], [0, -0.3, 0.7], [-0.3, 0.2, 0]])
    hi = np.array([[1, 1, 2], [0.8, 0.8, 0.2], [0.6, 0.3, 1.3], [0.3, 0.8, 0.2]])
    labels = link_regions(c, lo, hi, view_ids=np.array([0, 0, 1, 1]))
    assert labels.tolist() == [0, 1, 0, 1]
    # Without the other view's regions the two parts are one object.
    assert link_regions(c[:2], lo[:2], hi[:2], view_ids=np.array([0, 0])).tolist() == [0, 0]


def test_lines_of_sight_meet_pair_by_pair_as_in_all_pairs_at_once():
    """merge._rays_meet (all pairs in numpy, in chunks) against the pair-at-a-time reading
    of link_regions' rule: closest points of the two lines, in front of both cameras and not
    past either surface, within the gap, at a point both regions cover."""
    from streetcd.geometry.merge import _rays_meet, covers

    rng = np.random.default_rng(7)
    n = 60
    cameras = np.column_stack([rng.uniform(0, 20, n), np.zeros(n), np.full(n, 1.6)])
    cameras[5] = np.nan  # a region without a camera meets nothing
    centroids = np.column_stack(
        [rng.uniform(0, 20, n), rng.uniform(6, 12, n), rng.uniform(0, 4, n)]
    )
    half = rng.uniform(0.2, 3.0, (n, 3))
    lo, hi = centroids - half, centroids + half
    views = rng.integers(0, 8, n)
    margin, max_gap = 0.5, 0.8
    expected = np.full((n, n), np.inf)
    for i in range(n):
        for j in range(i + 1, n):
            if views[i] == views[j] or not np.isfinite(cameras[[i, j]]).all():
                continue
            u = [
                (centroids[k] - cameras[k]) / np.linalg.norm(centroids[k] - cameras[k])
                for k in (i, j)
            ]
            w = cameras[i] - cameras[j]
            b = u[0] @ u[1]
            if 1 - b * b < 1e-4:
                continue
            s = (b * (u[1] @ w) - u[0] @ w) / (1 - b * b)
            t = (u[1] @ w - b * (u[0] @ w)) / (1 - b * b)
            length = [np.linalg.norm(centroids[k] - cameras[k]) for k in (i, j)]
            if not (0.5 < s <= length[0] + margin and 0.5 < t <= length[1] + margin):
                continue
            p, q = cameras[i] + s * u[0], cameras[j] + t * u[1]
            x = (p + q) / 2
            if np.linalg.norm(p - q) <= max_gap and all(
                covers(x, cameras[k], centroids[k], lo[k], hi[k], margin) for k in (i, j)
            ):
                expected[i, j] = expected[j, i] = np.linalg.norm(p - q)
    for chunk in (7, 1 << 16):
        got = _rays_meet(centroids, lo, hi, cameras, views, margin, max_gap, chunk=chunk)
        assert np.array_equal(np.isfinite(got), np.isfinite(expected))
        assert np.allclose(got[np.isfinite(got)], expected[np.isfinite(expected)], rtol=1e-12)
    assert np.isfinite(expected).sum() >= 10  # the rule is exercised, not only inf
