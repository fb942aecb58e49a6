"""Metrics of §5 / eq. 12 on hand-made masks with exact expectations."""

import math
from fractions import Fraction

import numpy as np
import pytest

from streetcd import classes
from streetcd.errors import InputError
from streetcd.eval.metrics import (
    PixelCounts,
    TypeRow,
    false_components,
    per_type_table,
    pixel_counts,
    score_view,
    summarize,
    truth_coverage,
)


def textbook_kappa(det: np.ndarray, gt: np.ndarray) -> float:
    """Cohen's kappa from the 2×2 confusion matrix: (p_o − p_e) / (1 − p_e)."""
    a = np.sum(det & gt)
    b = np.sum(det & ~gt)
    c = np.sum(~det & gt)
    d = np.sum(~det & ~gt)
    n = a + b + c + d
    p_o = (a + d) / n
    p_e = ((a + b) * (a + c) + (c + d) * (b + d)) / n**2
    return float((p_o - p_e) / (1 - p_e))


def scene_10x10():
    """Two truth instances and three detected blobs, all apart (no 8-neighbour contact)."""
    inst = np.zeros((10, 10), np.uint16)
    inst[0:4, 0:5] = 1  # 20 px
    inst[6:10, 6:10] = 2  # 16 px
    det = np.zeros((10, 10), bool)
    det[0:4, 0:3] = True  # 12 px on instance 1: 60 % covered, a true component
    det[6:8, 6:8] = True  # 4 px on instance 2: 25 % covered, a true component
    det[8:10, 0:2] = True  # 4 px on no change: a false component
    return det, inst > 0, inst


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kappa_matches_textbook_cohen(seed):
    rng = np.random.default_rng(seed)
    gt = rng.random((37, 53)) < 0.2
    det = gt ^ (rng.random(gt.shape) < 0.1)  # 10 % of the pixels flipped
    assert pixel_counts(det, gt).kappa == pytest.approx(textbook_kappa(det, gt), abs=1e-12)


def test_hand_made_masks_give_exact_rates():
    det, gt, inst = scene_10x10()
    s = score_view(det, gt, inst, min_truth_px=1)
    p = s.pixels
    assert (p.ntp, p.nfp, p.nfn, p.ntn) == (16, 4, 20, 60)
    assert p.tp == pytest.approx(16 / 36)
    assert p.fp == pytest.approx(4 / 20)
    assert s.coverage == {1: pytest.approx(0.6), 2: pytest.approx(0.25)}
    assert (s.segments.n_truth, s.segments.n_good) == (2, 1)
    assert (s.segments.n_detected, s.segments.n_false) == (3, 1)
    assert s.segments.gdr == 0.5
    assert s.segments.fdr == pytest.approx(1 / 3)
    assert p.kappa == pytest.approx(textbook_kappa(det, gt))


def test_dontcare_pixels_leave_every_count():
    det, gt, inst = scene_10x10()
    dontcare = np.zeros_like(det)
    dontcare[8:10, 0:2] = True  # exactly the false blob
    dontcare[0, 4] = True  # one truth pixel of instance 1 (not detected)
    s = score_view(det, gt, inst, dontcare, min_truth_px=1)
    p = s.pixels
    assert p.n == 100 - 5
    assert (p.ntp, p.nfp, p.nfn) == (16, 0, 19)
    assert s.coverage[1] == pytest.approx(12 / 19)
    assert (s.segments.n_detected, s.segments.n_false) == (2, 0)
    assert s.segments.fdr == 0.0
    care = ~dontcare
    assert p.kappa == pytest.approx(textbook_kappa(det[care], gt[care]))


def test_segments_covered_by_several_components_count_as_detected():
    inst = np.zeros((6, 10), np.uint16)
    inst[:, :] = 7
    det = np.zeros(inst.shape, bool)
    det[:, 0:3] = True  # 30 %
    det[:, 5:8] = True  # another 30 %, not touching
    s = score_view(det, inst > 0, inst, min_truth_px=1)
    assert s.coverage == {7: pytest.approx(0.6)}
    assert s.segments.gdr == 1.0
    assert s.segments.n_detected == 2


def test_small_truth_slivers_are_not_counted():
    inst = np.zeros((10, 10), np.uint16)
    inst[0:5, 0:5] = 1  # 25 px
    inst[9, 9] = 2  # 1 px sliver
    assert set(truth_coverage(np.zeros((10, 10), bool), inst, min_truth_px=2)) == {1}
    assert set(truth_coverage(np.zeros((10, 10), bool), inst, min_truth_px=1)) == {1, 2}


def test_component_with_little_overlap_is_a_false_detection():
    gt = np.zeros((10, 10), bool)
    gt[0:5, 0] = True
    det = np.zeros((10, 10), bool)
    det[0:2, 0:10] = True  # 20 px, 2 on truth: 10 % is not below 10 % → true
    assert false_components(det, gt, false_max_overlap=0.1)[1] == []
    det[0, 0] = False  # 19 px, 1 on truth: 5.3 % → false
    n, false = false_components(det, gt, false_max_overlap=0.1)
    assert n == 1 and len(false) == 1 and false[0].pixels == 19


def test_false_detection_names_the_class_under_it():
    gt = np.zeros((8, 8), bool)
    det = np.zeros((8, 8), bool)
    det[2:5, 2:5] = True
    cls = np.full((8, 8), classes.BUILDING, np.uint8)
    cls[2, 2:5] = classes.VEGETATION  # 3 of 9 pixels
    _, false = false_components(det, gt, class_raster=cls)
    assert [(f.pixels, f.dominant_class) for f in false] == [(9, classes.BUILDING)]


def test_empty_truth_and_empty_detection_is_perfect_agreement():
    empty = np.zeros((5, 5), bool)
    s = score_view(empty, empty, empty.astype(np.uint16))
    assert s.pixels.kappa == 1.0
    assert math.isnan(s.pixels.tp) and math.isnan(s.pixels.fp)
    assert math.isnan(s.segments.gdr) and math.isnan(s.segments.fdr)
    assert summarize([s]).as_dict() == {
        "gdr": None,
        "fdr": None,
        "tp": None,
        "fp": None,
        "kappa": 1.0,
        "flagged": 0.0,
    }


def test_all_changed_on_both_sides_is_perfect_agreement():
    full = np.ones((4, 4), bool)
    assert pixel_counts(full, full).kappa == 1.0


def test_detection_on_an_unchanged_view_has_zero_kappa():
    gt = np.zeros((5, 5), bool)
    det = gt.copy()
    det[0, 0] = True
    p = pixel_counts(det, gt)
    assert p.kappa == 0.0
    assert p.fp == 1.0
    assert p.flagged == pytest.approx(1 / 25)


def test_everything_dontcare_gives_nan_kappa():
    m = np.ones((3, 3), bool)
    assert math.isnan(pixel_counts(m, m, dontcare=m).kappa)


def test_totals_pool_pixel_counts_over_views():
    rng = np.random.default_rng(5)
    views = []
    for _ in range(3):
        gt = rng.random((20, 30)) < 0.3
        views.append((gt ^ (rng.random(gt.shape) < 0.2), gt))
    total = summarize(score_view(d, g, g.astype(np.uint16)) for d, g in views)
    det_all = np.concatenate([d for d, _ in views])
    gt_all = np.concatenate([g for _, g in views])
    assert total.pixels == pixel_counts(det_all, gt_all)
    assert total.pixels.kappa == pytest.approx(textbook_kappa(det_all, gt_all))
    out = total.as_dict()
    assert out["tp"] == pytest.approx(100 * total.pixels.tp)
    assert -1 <= out["kappa"] <= 1


def test_kappa_is_exact_for_huge_pooled_counts():
    p = PixelCounts(ntp=3 * 10**9 + 1, nfp=7 * 10**8 + 3, nfn=5 * 10**8 + 7, ntn=4 * 10**10 + 11)
    n = p.n
    chance = Fraction(p.pd * p.pg + (n - p.pd) * (n - p.pg), n * n)
    exact = (Fraction(p.ntp + p.ntn, n) - chance) / (1 - chance)
    assert p.kappa == float(exact)


def test_shape_mismatch_names_the_mask():
    with pytest.raises(InputError, match="truth has shape"):
        pixel_counts(np.zeros((3, 3), bool), np.zeros((3, 4), bool))


def test_per_type_table_counts_objects_changes_and_false_detections():
    objects = [
        {"id": 1, "type": "pole", "class": classes.POLE},
        {"id": 2, "type": "pole", "class": classes.POLE},
        {"id": 3, "type": "board", "class": classes.SIGN},
        {"id": 4, "type": "building", "class": classes.BUILDING},
        {"id": 5, "type": "house", "class": classes.BUILDING},
    ]
    changes = [
        {"instance_id": 1, "type": "pole"},
        {"instance_id": 3, "type": "board"},
        {"instance_id": 9, "type": "pole"},
    ]  # 9 is never seen
    inst = np.zeros((10, 10), np.uint16)
    inst[0:4, 0:4] = 1
    inst[6:10, 6:10] = 3
    cls = np.full((10, 10), classes.BUILDING, np.uint8)
    cls[8:10, 0:2] = classes.POLE
    det_a = np.zeros((10, 10), bool)
    det_a[0:4, 0:4] = True  # pole detected in view a, board not
    det_a[8:10, 0:2] = True  # false, on a pole surface
    det_b = np.zeros((10, 10), bool)
    det_b[0:2, 7:10] = True  # false, on building (two types share that class)
    scores = [
        score_view(d, inst > 0, inst, class_raster=cls, min_truth_px=1) for d in (det_a, det_b)
    ]
    table = per_type_table(objects, changes, scores)
    # pole: seen in 2 views, detected in 1 (half) → correctly detected
    assert table["pole"] == TypeRow(ns=2, ngt=1, ncdc=1, nfdc=1)
    assert (table["board"].ngt, table["board"].ncdc) == (1, 0)
    assert table["building"].nfdc == 1  # the class name, as two types share the class
    assert table["house"].ns == 1 and table["house"].nfdc == 0
