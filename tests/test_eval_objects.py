"""Scoring an index's change objects against a synthetic scene (`streetcd evaluate --scene DIR
--index INDEX`, issue 17 item 5).

The street of tests/test_objects.py: cameras every 3 m looking at a façade. A real index is
written through the store (masks on disk, regions, change objects rebuilt from them) and a
scene folder beside it holds the truth: a removed pole (change 1), an added box (change 2) and
a removed bin no view flagged (change 3); a parked car that came is a don't-care disturbance.
Every view's regions are rectangles of 30 × 20 pixels, one above the other, so that OpenCV's
labelling numbers them in the order the index lists them.
"""

import dataclasses
import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from test_objects import BOX, PARAMS, POLE, _on_facade, _region, view_record
from test_segments import E0, N0, street

from streetcd import classes as C
from streetcd.errors import CorruptFileError, InputError, MissingInputError
from streetcd.eval.objects import MATCH_FRACTION, score_index
from streetcd.run.segments import plan_segments
from streetcd.store.index import ChangeIndex
from streetcd.store.objects import list_objects, rebuild_objects, sees
from streetcd.store.records import RegionRecord

CAR = np.array([E0 + 10.0, N0 + 1.0 + 6.0, 101.5])  # a car parked since the scan
H, W = 360, 640  # the cameras' image size (test_segments.INTR)
ROWS = 30  # each region is ROWS × 20 pixels: above run.min_region_fraction of the image
COLS = slice(10, 30)
ON = {"pole": 16, "box": 8, "car": 20}  # of each region's 20 columns, those on its truth
PX = ROWS * 20  # pixels per region
BIN_PX = 3 * 10  # the unflagged bin's pixels in the first view's truth


def _rows(label):
    return slice(40 * (label - 1) + 1, 40 * (label - 1) + 1 + ROWS)


def _scene_and_index(tmp_path, unlocated_in_first=True):
    """Write the index (through the store) and the scene's truth; returns (scene, index,
    how many views flagged each thing)."""
    scene, run = tmp_path / "scene", tmp_path / "run"
    (scene / "truth").mkdir(parents=True)
    (run / "masks").mkdir(parents=True)
    rng = np.random.default_rng(0)
    views = street(16, step_m=3.0)
    segments = plan_segments(views, PARAMS)
    seg = {n: s.id for s in segments for n in s.views}
    seen = {"pole": 0, "box": 0, "car": 0, "unlocated": 0, "no_change_views": 0}
    views_by = {(True, True): 0, (True, False): 0, (False, True): 0, (False, False): 0}
    records, manifest_views = [], []
    for i, v in enumerate(views):
        mask = np.zeros((H, W), np.uint8)
        inst = np.zeros((H, W), np.uint16)
        dontcare = np.zeros((H, W), np.uint8)
        regions = []
        for what, point in (("pole", POLE), ("box", BOX), ("car", CAR)):
            if not sees(v, point):
                continue
            label = len(regions) + 1
            if what == "pole":
                g = _region(label, point, np.array([0.15, 0.15, 1.0]), C.POLE, rng)
            else:
                cls = C.CAR if what == "car" else C.BUILDING
                g = _region(
                    label, _on_facade(v.center, point), np.array([0.7, 0.05, 0.7]), cls, rng
                )
            regions.append(dataclasses.replace(g, pixels=PX))
            mask[_rows(label), COLS] = 255
            on = slice(COLS.start, COLS.start + ON[what])
            if what == "car":
                dontcare[_rows(label), on] = 255
            else:
                inst[_rows(label), on] = 1 if what == "pole" else 2
            seen[what] += 1
        if i == 0 and unlocated_in_first:  # a region with no old surface behind it
            label = len(regions) + 1
            regions.append(RegionRecord(label, PX, 0.5, None, None, None, 0))
            mask[_rows(label), COLS] = 255
            seen["unlocated"] += 1
        if regions and not any(g.dominant_class != C.CAR and g.located for g in regions):
            seen["no_change_views"] += 1
        if i == 0:
            inst[300:303, 500:510] = 3  # the bin, never flagged
        ids, counts = np.unique(inst[inst > 0], return_counts=True)
        changed = {str(k): int(n) for k, n in zip(ids, counts, strict=True)}
        views_by[bool(changed), bool(regions)] += 1  # (has a true change, flagged)
        cv2.imwrite(str(scene / "truth" / f"{v.stem}.instances.png"), inst)
        cv2.imwrite(str(scene / "truth" / f"{v.stem}.dontcare.png"), dontcare)
        manifest_views.append(
            {
                "name": v.name,
                "instances": f"truth/{v.stem}.instances.png",
                "dontcare": f"truth/{v.stem}.dontcare.png",
                "changed_pixels": changed,
            }
        )
        mask_path = None
        if regions:
            mask_path = str(run / "masks" / f"{v.stem}.mask.png")
            cv2.imwrite(mask_path, mask)
        records.append(
            view_record(v, "aaa", seg[v.name], regions, mask_path=mask_path, overlay_path=mask_path)
        )
    changes = [
        {"instance_id": 1, "kind": "removed", "type": "pole"},
        {"instance_id": 2, "kind": "added", "type": "box"},
        {"instance_id": 3, "kind": "removed", "type": "bin"},
    ]
    (scene / "manifest.json").write_text(json.dumps({"views": manifest_views, "changes": changes}))
    index = run / "change_index.sqlite"
    with ChangeIndex(index) as idx:
        idx.add_segments(segments)
        idx.publish("r", records)
        rebuild_objects(idx, [s.id for s in segments])
    seen["views"] = views_by
    return scene, index, seen


@pytest.fixture
def scored(tmp_path):
    scene, index, seen = _scene_and_index(tmp_path)
    return score_index(scene, index), seen, index


def test_flagged_pixels_are_split_by_where_they_fall(scored):
    score, seen, _ = scored
    assert seen["pole"] >= 3 and seen["box"] >= 3 and seen["car"] >= 3
    on_change = seen["pole"] * ROWS * ON["pole"] + seen["box"] * ROWS * ON["box"]
    dontcare = seen["car"] * PX
    total = (seen["pole"] + seen["box"] + seen["car"] + seen["unlocated"]) * PX
    assert (score.flagged.change, score.flagged.dontcare) == (on_change, dontcare)
    assert score.flagged.total == total
    # The car is a transient (the old cloud has a car there): its pixels are kept out; the
    # unlocated region is in no object, so neither reported nor kept out.
    assert score.reported.dontcare == 0
    assert score.reported.total == (seen["pole"] + seen["box"]) * PX
    assert score.reported.change == on_change
    assert score.kept_out.total == score.kept_out.dontcare == dontcare
    d = score.as_dict()
    assert d["pixels"]["true_change_kept_pct"] == 100.0
    assert d["pixels"]["flagged"]["on_dontcare_pct"] == round(100 * dontcare / total, 2)
    assert d["pixels"]["reported"]["on_dontcare_pct"] == 0.0


def test_objects_are_matched_to_the_manifests_changes(scored):
    score, seen, index = scored
    d = score.as_dict()
    by_id = {c["instance_id"]: c for c in d["changes"]}
    objects = {o["id"]: o for o in list_objects(index)}
    (pole,) = by_id[1]["objects"]
    (box,) = by_id[2]["objects"]
    assert objects[pole]["kind"] == "removed" and objects[box]["kind"] == "added"
    assert by_id[3]["objects"] == [] and by_id[3]["flagged_px"] == 0
    assert by_id[3]["truth_px"] == BIN_PX
    assert by_id[1]["truth_px"] == by_id[1]["flagged_px"] == seen["pole"] * ROWS * ON["pole"]
    # the box: 8 of its region's 20 columns on it, 40 % >= MATCH_FRACTION: still a match
    assert ON["box"] / 20 >= MATCH_FRACTION
    assert (d["changes_found"], d["changes_total"], d["changes_one_object"]) == (2, 3, 2)
    assert d["objects_reported"] == 2 and d["object_precision_pct"] == 100.0
    assert d["object_recall_pct"] == round(100 * 2 / 3, 2)
    car_ids = [o["id"] for o in d["objects"] if o["transient"] is not None]
    assert car_ids and all(objects[i]["class"] == C.CAR for i in car_ids)
    reasons = d["transient_reasons"]
    assert sum(r["objects"] for r in reasons.values()) == len(car_ids)
    assert sum(r["pixels"] for r in reasons.values()) == seen["car"] * PX
    assert all(r["on_change"] == 0 for r in reasons.values())
    assert d["flagged_views_without_change"] == seen["no_change_views"] > 0


def test_a_mask_that_disagrees_with_the_index_is_named(tmp_path):
    scene, index, _ = _scene_and_index(tmp_path)
    with ChangeIndex(index, readonly=True) as idx:
        path = idx.conn.execute("SELECT mask_path FROM flagged ORDER BY view").fetchone()[0]
    mask = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    mask[H - 2 :, W - 2 :] = 255  # one more region than the index lists
    cv2.imwrite(path, mask)
    with pytest.raises(CorruptFileError, match="mask has .* regions, the index lists"):
        score_index(scene, index)


def test_an_index_of_another_scene_or_no_scene_is_refused(tmp_path):
    scene, index, _ = _scene_and_index(tmp_path)
    manifest = json.loads((scene / "manifest.json").read_text())
    for v in manifest["views"]:
        v["name"] = "other_" + v["name"]
    other = tmp_path / "other"
    other.mkdir()
    (other / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="none of its .* flagged views is an image of"):
        score_index(other, index)
    with pytest.raises(MissingInputError, match="no manifest.json"):
        score_index(tmp_path, index)
    (other / "manifest.json").write_text("{not json")
    with pytest.raises(CorruptFileError, match="manifest.json: not valid JSON"):
        score_index(other, index)


def test_cli_scores_an_index_and_writes_json(tmp_path):
    from streetcd.cli.evaluate import evaluate

    scene, index, _ = _scene_and_index(tmp_path)
    out = tmp_path / "eval-index.json"
    res = CliRunner().invoke(
        evaluate, ["--scene", str(scene), "--index", str(index), "--json", str(out)]
    )
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    assert data == score_index(scene, index).as_dict()
    assert "Changes of the manifest" in res.output and "Transients kept out" in res.output
    assert "the old cloud has a car there" in res.output
    res = CliRunner().invoke(evaluate, ["--index", str(index)])
    assert res.exit_code == 2 and "give --scene DIR" in res.output


def _case_of(scene, tmp_path, labels=True):
    """The scene's truth laid out as an annotated case (`streetcd evaluate --case`): gt/ with
    each view's mask, don't-care and labels, images/ with a file per view, case.json naming
    the labels."""
    manifest = json.loads((scene / "manifest.json").read_text())
    case = tmp_path / "case"
    (case / "gt").mkdir(parents=True)
    (case / "images").mkdir()
    for v in manifest["views"]:
        stem = v["name"].rsplit(".", 1)[0]
        inst = cv2.imread(str(scene / v["instances"]), cv2.IMREAD_UNCHANGED)
        dontcare = cv2.imread(str(scene / v["dontcare"]), cv2.IMREAD_UNCHANGED)
        (case / "images" / v["name"]).write_bytes(b"")  # only the names are read
        cv2.imwrite(
            str(case / "gt" / f"{stem}.mask.png"), np.where(inst > 0, 255, 0).astype(np.uint8)
        )
        cv2.imwrite(str(case / "gt" / f"{stem}.dontcare.png"), dontcare)
        if labels:
            cv2.imwrite(str(case / "gt" / f"{stem}.labels.png"), inst)
    objects = [
        {"id": c["instance_id"], "type": c["type"], "kind": c["kind"]} for c in manifest["changes"]
    ]
    (case / "case.json").write_text(json.dumps({"objects": objects}))
    return case


def test_an_index_is_scored_against_a_cases_labelled_objects_as_against_a_scene(tmp_path):
    from streetcd.eval.objects import score_case_index

    scene, index, _ = _scene_and_index(tmp_path)
    case = _case_of(scene, tmp_path)
    by_scene = score_index(scene, index).as_dict()
    by_case = score_case_index(case, index).as_dict()
    assert by_case.pop("scene") == str(case) and by_scene.pop("scene") == str(scene)
    assert by_case == by_scene
    assert (by_case["changes_found"], by_case["changes_total"]) == (2, 3)


def test_a_label_under_dont_care_is_a_disturbance_in_a_case(tmp_path):
    from streetcd.eval.objects import score_case_index

    scene, index, seen = _scene_and_index(tmp_path)
    case = _case_of(scene, tmp_path)
    before = score_case_index(case, index)
    # the pole's pixels in every view marked don't-care as well: they count as don't-care
    for path in (case / "gt").glob("*.labels.png"):
        labels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        dc_path = path.with_name(path.name.replace(".labels.", ".dontcare."))
        dontcare = cv2.imread(str(dc_path), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(dc_path), np.where(labels == 1, 255, dontcare).astype(np.uint8))
    after = score_case_index(case, index)
    pole_px = seen["pole"] * ROWS * ON["pole"]
    assert after.flagged.change == before.flagged.change - pole_px
    assert after.flagged.dontcare == before.flagged.dontcare + pole_px
    pole = {c.instance_id: c for c in after.changes}[1]
    assert (pole.truth_px, pole.flagged_px, pole.objects) == (0, 0, ())


def test_a_case_without_labels_cannot_score_objects(tmp_path):
    from streetcd.eval.objects import score_case_index

    scene, index, _ = _scene_and_index(tmp_path)
    case = _case_of(scene, tmp_path, labels=False)
    with pytest.raises(InputError, match="no <stem>.labels.png"):
        score_case_index(case, index)
    first = sorted((case / "gt").glob("*.mask.png"))[0]
    stem = first.name.split(".")[0]
    cv2.imwrite(str(case / "gt" / f"{stem}.labels.png"), np.zeros((H, W), np.uint8))
    # one view has labels now; another view's mask has changed pixels and no labels
    with pytest.raises(MissingInputError, match=r"labels.png: labels not found, and .* changed"):
        score_case_index(case, index)


def test_cli_scores_an_index_against_a_case(tmp_path):
    from streetcd.cli.evaluate import evaluate
    from streetcd.eval.objects import score_case_index

    scene, index, _ = _scene_and_index(tmp_path)
    case = _case_of(scene, tmp_path)
    out = tmp_path / "eval-case-index.json"
    res = CliRunner().invoke(
        evaluate, ["--case", str(case), "--index", str(index), "--json", str(out)]
    )
    assert res.exit_code == 0, res.output
    assert json.loads(out.read_text()) == score_case_index(case, index).as_dict()
    assert "Labelled objects of the case" in res.output and "recall" in res.output


def test_the_views_the_run_flagged_are_counted_by_their_truth(tmp_path):
    from streetcd.eval.objects import score_case_index

    scene, index, seen = _scene_and_index(tmp_path)
    by = dict(seen["views"])
    # one view the run did not flag gets a change in its truth (the bin, 5 pixels): a view
    # with a true change that was not flagged
    with ChangeIndex(index, readonly=True) as idx:
        flagged = {r[0] for r in idx.conn.execute("SELECT image FROM views WHERE flagged = 1")}
    manifest = json.loads((scene / "manifest.json").read_text())
    quiet = next(v for v in manifest["views"] if v["name"] not in flagged)
    inst = cv2.imread(str(scene / quiet["instances"]), cv2.IMREAD_UNCHANGED)
    inst[10, 10:15] = 3
    cv2.imwrite(str(scene / quiet["instances"]), inst)
    quiet["changed_pixels"] = {"3": 5}
    (scene / "manifest.json").write_text(json.dumps(manifest))
    by[False, False] -= 1
    by[True, False] += 1
    assert all(n > 0 for n in by.values()), by  # every kind of view is there
    expected = {
        "with_change": by[True, True] + by[True, False],
        "with_change_flagged": by[True, True],
        "without_change": by[False, True] + by[False, False],
        "without_change_flagged": by[False, True],
    }
    views = score_index(scene, index).as_dict()["views"]
    assert {k: views[k] for k in expected} == expected
    pct = round(100 * by[True, True] / expected["with_change"], 2)
    assert views["with_change_flagged_pct"] == pct
    assert score_case_index(_case_of(scene, tmp_path), index).as_dict()["views"] == views


def test_a_found_change_is_placed_off_its_box_by_the_horizontal_distance(tmp_path):
    scene, index, _ = _scene_and_index(tmp_path)
    manifest = json.loads((scene / "manifest.json").read_text())
    origin = np.array([E0, N0, 100.0])  # the local frame's origin in the index's CRS
    manifest["origin"] = origin.tolist()
    by_id = {c["instance_id"]: c for c in manifest["changes"]}
    by_id[1]["bbox_local"] = [*(POLE - 1.0 - origin), *(POLE + 1.0 - origin)]  # around it
    far = BOX + np.array([30.0, 40.0, 0.0])  # a box 50 m from the box that was added
    by_id[2]["bbox_local"] = [*(far - 0.5 - origin), *(far + 0.5 - origin)]
    (scene / "manifest.json").write_text(json.dumps(manifest))
    d = score_index(scene, index).as_dict()
    errors = {c["instance_id"]: c["position_error_m"] for c in d["changes"]}
    objects = {o["id"]: o for o in list_objects(index)}
    (box_object,) = [c["objects"][0] for c in d["changes"] if c["instance_id"] == 2]
    x, y, _ = objects[box_object]["centroid"]
    lo, hi = far - 0.5, far + 0.5
    expected = np.hypot(max(lo[0] - x, 0, x - hi[0]), max(lo[1] - y, 0, y - hi[1]))
    assert errors[1] == 0.0 and errors[2] == pytest.approx(expected, abs=1e-3)
    assert 45.0 < errors[2] < 55.0
    assert errors[3] is None  # no box, and no object found it
    summary = d["position_error_m"]
    assert summary["measured"] == 2 and summary["max"] == errors[2]
