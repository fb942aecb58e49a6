"""Node energy (eq. 7), smoothness (eq. 8–9), superpixels (eq. 10–11), max-flow, speckle."""

import math
from dataclasses import replace

import numpy as np
import pytest

from streetcd.config import GraphCutParams
from streetcd.detect.graphcut import (
    adjacency,
    cut_changes,
    min_cut,
    node_energy,
    smoothness,
    speckle_filter,
    speckle_min_px,
    superpixel_mean,
    superpixels,
)


def test_node_energy_is_a_monotone_s_curve_from_0_to_1():
    c = np.linspace(0, 1, 1001, dtype=np.float32)
    f = node_energy(c, 45.0, 11.0)
    assert f.dtype == np.float32
    assert f[0] == 0.0 and f[-1] == pytest.approx(1.0, abs=1e-6)
    assert np.all(np.diff(f) >= 0)
    assert node_energy(np.float32(11 / 45), 45, 11) == pytest.approx(0.5, abs=1e-4)  # midpoint b/a
    # an S, not a line: flat near 0 (illumination noise suppressed), steep in the middle
    assert f[100] < 0.02 and f[400] > 0.98
    assert node_energy(np.array([-0.5, 2.0], np.float32)).tolist() == [0.0, 1.0]  # clipped


def test_node_energy_steepness_follows_a():
    c = np.array([0.2], np.float32)
    assert node_energy(c, 30, 6)[0] < node_energy(c, 30, 5)[0]  # larger b shifts right


def pair(color_i, color_j, depth_i=10.0, depth_j=10.0, cls_i=6, cls_j=6, **switches):
    p = replace(GraphCutParams(), **switches)
    return smoothness(
        np.array([color_i], float),
        np.array([color_j], float),
        np.array([depth_i]),
        np.array([depth_j]),
        np.array([cls_i]),
        np.array([cls_j]),
        p,
    )[0]


def test_smoothness_is_zero_across_classes_and_one_for_identical_nodes():
    assert pair([100, 100, 100], [100, 100, 100]) == 1.0
    assert pair([100, 100, 100], [100, 100, 100], cls_i=6, cls_j=2) == 0.0
    assert pair([100, 100, 100], [100, 100, 100], cls_i=6, cls_j=2, use_class=False) == 1.0


def test_smoothness_is_larger_for_similar_colours_and_depths():
    near = pair([100, 100, 100], [103, 100, 96])
    far = pair([100, 100, 100], [160, 40, 100])
    assert near == pytest.approx(math.exp(-5 / 10.0))  # colour distance 5, color_scale 10
    assert near > far > 0
    assert pair([100] * 3, [100] * 3, 10.0, 10.25) == pytest.approx(
        math.exp(-0.25 / GraphCutParams().depth_scale_m)
    )
    assert pair([100] * 3, [100] * 3, 10.0, 13.0) < pair([100] * 3, [100] * 3, 10.0, 10.2)
    # eq. 8 takes the smaller of the two similarities
    depth_scale = GraphCutParams().depth_scale_m
    assert pair([100] * 3, [103, 100, 96], 10.0, 13.0) == pytest.approx(math.exp(-3 / depth_scale))


def test_smoothness_switches_drop_their_term():
    assert pair([0, 0, 0], [255, 255, 255], use_color=False) == 1.0
    assert pair([9] * 3, [9] * 3, 5.0, 50.0, use_depth=False) == 1.0
    nan = float("nan")
    assert pair([9] * 3, [9] * 3, nan, nan) == 1.0  # neither has a surface: alike
    assert pair([9] * 3, [9] * 3, nan, 10.0) == 0.0  # surface against none: unlike


def test_min_cut_on_a_hand_made_graph():
    # a chain 0–1–2–3; D(0) = f is the cost of "unchanged", D(1) = 1 − f of "changed"
    f = np.array([0.9, 0.4, 0.9, 0.1])
    pairs = np.array([[0, 1], [1, 2], [2, 3]])
    assert min_cut(f, 1 - f, pairs, np.zeros(3)).tolist() == [True, False, True, False]
    # cutting 0|1 and 1|2 (0.4) costs more than flipping node 1 (1−2·0.4 = 0.2)
    assert min_cut(f, 1 - f, pairs, np.full(3, 0.2)).tolist() == [True, True, True, False]
    # …and cutting 2|3 (1.0) costs more than flipping node 3 (0.8)
    assert min_cut(f, 1 - f, pairs, np.full(3, 1.0)).tolist() == [True] * 4
    # a weak link keeps two groups apart
    w = np.array([5.0, 5.0, 0.01])
    assert min_cut(f, 1 - f, pairs, w).tolist() == [True, True, True, False]


def test_adjacency_counts_boundary_pixel_pairs():
    labels = np.array([[0, 0, 1], [2, 2, 1], [2, 2, 1]])
    pairs, boundary = adjacency(labels)
    assert pairs.tolist() == [[0, 1], [0, 2], [1, 2]]
    assert boundary.tolist() == [1, 2, 2]


def test_speckle_filter_removes_exactly_the_components_below_the_threshold():
    mask = np.zeros((30, 40), bool)
    mask[1:3, 1:6] = True  # 10 px
    mask[10:13, 1:4] = True  # 9 px
    mask[20, 20] = True  # 1 px
    mask[20:25, 30:36] = True  # 30 px
    mask[5, 20] = mask[6, 21] = mask[7, 22] = True  # 3 px, 8-connected diagonal
    out = speckle_filter(mask, 10)
    expected = np.zeros_like(mask)
    expected[1:3, 1:6] = True
    expected[20:25, 30:36] = True
    assert np.array_equal(out, expected)
    only_single = mask.copy()
    only_single[20, 20] = False
    assert np.array_equal(speckle_filter(mask, 3), only_single)  # the 3 px diagonal stays


@pytest.mark.parametrize("seed", range(4))
def test_speckle_filter_agrees_with_scipys_labelling(seed):
    # the filter labels only the segments' bounding box: the same segments as the whole image
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    mask = np.zeros((60, 80), bool)
    mask[7:50, 11:71] = rng.random((43, 60)) < 0.45
    labels, n = ndimage.label(mask, structure=np.ones((3, 3)))
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    keep = sizes >= 5
    keep[0] = False
    assert np.array_equal(speckle_filter(mask, 5), keep[labels])
    assert not speckle_filter(np.zeros_like(mask), 5).any()


def test_speckle_area_scales_with_the_square_of_the_width():
    p = GraphCutParams(speckle_min_px=200)
    assert speckle_min_px(4000, p) == 200
    assert speckle_min_px(2000, p) == 50


def test_superpixels_respect_class_boundaries():
    rng = np.random.default_rng(3)
    h, w = 90, 120
    image = np.full((h, w, 3), 128, np.float32) + rng.normal(0, 2, (h, w, 3)).astype(np.float32)
    rows, cols = np.mgrid[0:h, 0:w]
    classes = np.where(cols + 0.7 * rows > 70, 6, 2).astype(np.uint8)  # a slanted boundary
    params = GraphCutParams(superpixel_cell_px=400.0)  # 12 px cells at 120 px width
    labels = superpixels(image, classes, params)
    assert labels.dtype == np.int32 and labels.shape == (h, w)
    n = labels.max() + 1
    assert np.array_equal(np.unique(labels), np.arange(n))
    assert 30 <= n <= 130  # about (90·120) / 12² = 75 cells
    mixed = [k for k in range(n) if len(np.unique(classes[labels == k])) > 1]
    assert mixed == []


def test_superpixels_at_reduced_resolution_stay_class_pure_and_cover_the_image():
    rng = np.random.default_rng(4)
    h, w = 240, 480
    image = rng.uniform(0, 255, (h, w, 3)).astype(np.float32)
    classes = np.full((h, w), 6, np.uint8)
    classes[:, 200:] = 2
    params = GraphCutParams(superpixel_cell_px=400.0, superpixel_work_cell_px=16.0)
    labels = superpixels(image, classes, params)  # 48 px cells, SLIC at 1/3 size
    assert labels.shape == (h, w)
    purity = [
        np.bincount(classes[labels == k]).max() / np.sum(labels == k)
        for k in range(labels.max() + 1)
    ]
    assert min(purity) > 0.9  # nearest-neighbour upsampling blurs the boundary by ≤ 1.5 px


def board_scene():
    """A red board on a blue background; the raw change says only its left half changed."""
    rng = np.random.default_rng(5)
    h, w = 120, 160
    image = np.empty((h, w, 3), np.float32)
    image[:] = [40, 60, 200]
    image[30:90, 40:120] = [210, 40, 40]
    image += rng.normal(0, 1.5, image.shape).astype(np.float32)
    energy = np.zeros((h, w), np.float32)
    energy[30:90, 40:80] = 0.95
    energy[30:90, 80:120] = 0.2  # homogeneous: the neighbours' colours matched by chance
    depth = np.full((h, w), 12.0, np.float32)
    classes = np.full((h, w), 6, np.uint8)
    board = np.zeros((h, w), bool)
    board[30:90, 40:120] = True
    return image, energy, depth, classes, board


def test_graph_cut_spreads_change_over_the_similar_board_and_stops_at_its_edge():
    image, energy, depth, classes, board = board_scene()
    params = GraphCutParams(superpixel_cell_px=400.0, beta=3.0)  # 16 px cells
    smooth = cut_changes(energy, image, depth, classes, params).mask
    assert np.mean(smooth[board]) > 0.95 and np.mean(smooth[~board]) < 0.01  # cells vs edges
    alone = cut_changes(energy, image, depth, classes, replace(params, beta=0.0)).mask
    left = np.zeros_like(board)
    left[30:90, 40:80] = True
    assert np.mean(alone == left) > 0.98  # no smoothing: the cut thresholds f at 0.5


def test_graph_cut_does_not_spread_across_a_class_boundary():
    image, energy, depth, classes, board = board_scene()
    classes[:, 80:] = 2  # the right half of the board is another class
    params = GraphCutParams(superpixel_cell_px=400.0, beta=3.0)
    mask = cut_changes(energy, image, depth, classes, params).mask
    assert np.mean(mask[30:90, 40:80]) > 0.95 and np.mean(mask[30:90, 82:120]) < 0.03
    no_class = cut_changes(energy, image, depth, classes, replace(params, use_class=False)).mask
    assert np.mean(no_class[board]) > 0.95


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_speckle_on_superpixels_equals_the_pixel_speckle_filter(seed):
    """Guards the superpixel-level speckle filter of cut_changes: on random superpixels
    (4-connected, as superpixels() makes them) and a random set of changed ones, touching
    at corners too, it gives exactly speckle_filter(changed[labels])."""
    from streetcd.detect.graphcut import _speckle_superpixels

    rng = np.random.default_rng(seed)
    h, w = 90, 130
    image = rng.uniform(0, 255, (h // 6, w // 6, 3)).astype(np.float32)
    image = np.repeat(np.repeat(image, 6, axis=0), 6, axis=1)
    image = np.pad(image, ((0, h - image.shape[0]), (0, w - image.shape[1]), (0, 0)), "edge")
    classes = rng.integers(1, 4, (h // 10 + 1, w // 10 + 1)).astype(np.uint8)
    classes = np.repeat(np.repeat(classes, 10, axis=0), 10, axis=1)[:h, :w]
    labels = superpixels(image, classes, GraphCutParams(superpixel_cell_px=250.0))
    n = int(labels.max()) + 1
    changed = rng.random(n) < 0.3
    count = np.bincount(labels.ravel(), minlength=n).astype(np.float64)
    for min_px in (2.0, 40.0, 150.0, 600.0):
        want = speckle_filter(changed[labels], min_px)
        got = _speckle_superpixels(labels, changed, count, min_px)
        assert np.array_equal(got, want), min_px
    # a corner contact joins two superpixels into one segment, as 8-connectivity does
    corner = np.array([[0, 1], [1, 2]], np.int32)
    both = np.array([True, False, True])
    assert _speckle_superpixels(corner, both, np.array([1.0, 2.0, 1.0]), 2.0)[[0, 1], [0, 1]].all()


def test_node_energy_of_no_change_is_the_curve_at_zero():
    """Guards the shortcut for pixels without raw change (they get f(0) computed once)."""
    c = np.array([0.0, -0.5, 1e-9, 0.3, 1.0, 2.0], np.float32)
    f = node_energy(c, 45.0, 11.0)
    lo = 1 / (1 + math.exp(11.0))
    hi = 1 / (1 + math.exp(11.0 - 45.0))
    x = np.clip(c.astype(np.float64), 0, 1)
    want = np.clip((1 / (1 + np.exp(11.0 - 45.0 * x)) - lo) / (hi - lo), 0, 1)
    assert f[0] == f[1] == 0.0
    np.testing.assert_allclose(f, want, atol=1e-6)


def test_superpixel_mean_gives_each_pixel_its_superpixels_mean():
    labels = np.array([[0, 0, 1], [2, 1, 1]])
    values = np.array([[0.2, 0.4, 1.0], [0.5, 0.0, 0.5]], np.float32)
    got = superpixel_mean(values, labels)
    np.testing.assert_allclose(got, [[0.3, 0.3, 0.5], [0.5, 0.5, 0.5]], rtol=1e-6)
    assert got.dtype == np.float32 and got.shape == values.shape


def test_a_weak_change_over_a_whole_superpixel_outweighs_a_few_strong_pixels():
    """Eq. 7 of the superpixel's mean raw change (energy_of_mean) against the mean of eq. 7:
    a change of 0.3 over all of one superpixel (above the S-curve's middle, b/a = 0.244)
    against 0.9 on a tenth of another's pixels (mean 0.09)."""
    labels = np.repeat(np.arange(2), 50).reshape(10, 10)
    change = np.zeros((10, 10), np.float32)
    change[labels == 0] = 0.3
    change[labels == 1] = np.where(np.arange(50) % 10 == 0, 0.9, 0.0)
    mean_of_f = superpixel_mean(node_energy(change), labels)
    f_of_mean = node_energy(superpixel_mean(change, labels))
    weak, specks = labels == 0, labels == 1
    assert f_of_mean[weak].min() == mean_of_f[weak].max()  # uniform: the same either way
    assert f_of_mean[weak].min() > 0.5  # ... and changed
    assert mean_of_f[specks].max() > 0.09 > f_of_mean[specks].max()  # specks weigh less
