"""Node energy, class-aware superpixels, graph cut and speckle filter (paper §3.4, eq. 6–11).

Two misprints of the paper are resolved here, not copied:

* **Eq. 7** as printed, ``exp(aC − b) / exp(aC + b)``, is the constant ``exp(−2b)``. The text
  and Fig. 10(a) describe an S-curve of steepness ``a`` and shift ``b``, normalised (``m``,
  ``s``) to [0, 1]. We use the logistic ``σ(aC − b)`` rescaled so that C = 0 → 0 and C = 1 → 1;
  with a = 45, b = 11 its midpoint is at C = b/a ≈ 0.24.
* **Eq. 8** as printed couples neighbours only across *different* classes (``δ`` of eq. 9 is 1
  when the classes differ) and charges the cost when the labels are *equal*. The text means
  the opposite: change spreads to similar neighbours of the *same* class, so the cost is paid
  when the labels *differ* and is zero across a class boundary.

**Superpixels, not pixels.** The paper's pixel graph is too slow and too large at 12 MP
(docs/BENCHMARKS.md). We cut on class-aware SLIC superpixels instead, with an energy that
equals the pixel energy of eq. 6 restricted to labellings constant on each superpixel
(superpixel means stand in for pixel values in eq. 8): a superpixel's node energy is the sum
of its pixels' node energies and an edge's weight is β · S_ij times the number of
4-neighbour pixel pairs on the shared boundary. Both are divided by the cell area S² so that
β means the same at every resolution: β = 1 makes one cell-length of similar boundary cost
as much as one cell of node energy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from streetcd.config import REFERENCE_WIDTH_PX, GraphCutParams, scale_px
from streetcd.detect.boxes import mask_box

_DEFAULTS = GraphCutParams()  # frozen: one shared default instance


def node_energy(change: np.ndarray, a: float = 45.0, b: float = 11.0) -> np.ndarray:
    """Eq. 7 (corrected): ``f(C) = (σ(aC − b) − σ(−b)) / (σ(a − b) − σ(−b))``.

    change : (...) float32 raw change in [0, 1]. Returns (...) float32 in [0, 1], monotone,
    f(0) = 0, f(1) = 1. ``f`` is ``D_p(x_p = 0)``, the cost of calling the pixel unchanged
    (the "probability of change" of Fig. 7(b)); ``D_p(x_p = 1) = 1 − f``.
    """
    lo = 1.0 / (1.0 + math.exp(b))
    hi = 1.0 / (1.0 + math.exp(b - a))
    c = np.ascontiguousarray(change, dtype=np.float32)
    out = np.empty_like(c)
    _s_curve(c.reshape(-1), out.reshape(-1), float(a), float(b), lo, hi)
    return out


@numba.njit(cache=True, nogil=True, fastmath=True)
def _s_curve(c, out, a, b, lo, hi):  # pragma: no cover - compiled
    """out = clip((σ(a·clip(c, 0, 1) − b) − lo) / (hi − lo), 0, 1), one pass, float32 out.

    About half the pixels of a view have no raw change at all (no evidence, or a colour
    inside the neighbours' envelope): they get f(0), computed once, not one exp each."""
    scale = 1.0 / (hi - lo)
    zero = min(max((1.0 / (1.0 + math.exp(b - a * 0.0)) - lo) * scale, 0.0), 1.0)
    for i in range(c.shape[0]):
        if c[i] <= 0.0:
            out[i] = zero
            continue
        x = min(max(c[i], 0.0), 1.0)
        s = 1.0 / (1.0 + math.exp(b - a * x))
        out[i] = min(max((s - lo) * scale, 0.0), 1.0)


def smoothness(
    color_i: np.ndarray,
    color_j: np.ndarray,
    depth_i: np.ndarray,
    depth_j: np.ndarray,
    class_i: np.ndarray,
    class_j: np.ndarray,
    params: GraphCutParams = _DEFAULTS,
) -> np.ndarray:
    """Eq. 8–9 (corrected): similarity ``S_ij`` of two nodes, paid when their labels differ.

    ``S = min(exp(−‖I_i − I_j‖ / color_scale), exp(−|z_i − z_j| / depth_scale_m)) · [G_i = G_j]``

    color_* : (E, 3) float RGB in [0, 255]; depth_* : (E,) metres, NaN = no surface (two
    nodes without surface count as equally deep, one with and one without as unlike);
    class_* : (E,) class codes. ``use_color`` / ``use_depth`` / ``use_class`` switch the terms
    off (a switched-off term does not constrain the minimum). Returns (E,) float64 in [0, 1].
    """
    s = np.ones(len(class_i), dtype=np.float64)
    if params.use_color:
        dc = np.linalg.norm(
            np.asarray(color_i, np.float64) - np.asarray(color_j, np.float64), axis=1
        )
        s = np.minimum(s, np.exp(-dc / params.color_scale))
    if params.use_depth:
        di, dj = np.asarray(depth_i, np.float64), np.asarray(depth_j, np.float64)
        dz = np.where(np.isnan(di) & np.isnan(dj), 0.0, np.abs(di - dj))  # NaN: one has none
        s = np.minimum(s, np.exp(-np.nan_to_num(dz, nan=np.inf) / params.depth_scale_m))
    if params.use_class:
        s = s * (np.asarray(class_i) == np.asarray(class_j))
    return s


def _work_scale(width: int, params: GraphCutParams) -> tuple[float, float]:
    """(cell size in px at full resolution, downscale factor for SLIC ≤ 1)."""
    cell = scale_px(params.superpixel_cell_px, width, minimum=2.0)
    return cell, min(1.0, params.superpixel_work_cell_px / cell)


def superpixels(
    image: np.ndarray, classes: np.ndarray, params: GraphCutParams = _DEFAULTS
) -> np.ndarray:
    """Class-aware SLIC superpixels (eq. 10–11), labels 0..n−1.

    image : (H, W, 3) float32 RGB in [0, 255]; classes : (H, W) uint8 class codes.
    Returns (H, W) int32 labels, each superpixel 4-connected.

    The distance is eq. 11 in SLIC's normalised form,
    ``D = sqrt(‖Lab_k − Lab_i‖² + (m/S)² ‖x_k − x_i‖²) + α·[G_k ≠ G_i]``: we read the paper's
    "M/S = 20" as SLIC's compactness ``m = 20`` (Lab units per cell length S; taken literally,
    20 Lab units per pixel, the cells would be a rigid grid). A centre's class is the
    majority class of its members. SLIC runs on the image downscaled so a cell is about
    ``superpixel_work_cell_px`` wide (INTER_AREA colours, nearest classes) and the labels
    are upsampled (nearest), which keeps every superpixel 4-connected. Our own numba kernel
    (5 iterations) is several times faster than skimage's ``slic`` on the same 4-channel
    stack (docs/BENCHMARKS.md).
    """
    h, w = classes.shape
    cell, scale = _work_scale(w, params)
    hs, ws = max(1, round(h * scale)), max(1, round(w * scale))
    small: np.ndarray = np.ascontiguousarray(image, dtype=np.float32)
    cls = classes
    if (hs, ws) != (h, w):
        small = cv2.resize(small, (ws, hs), interpolation=cv2.INTER_AREA)
        cls = classes[nearest_index(hs, h)][:, nearest_index(ws, w)]
    # scaled to [0, 1] (what cvtColor expects of float RGB) after the downscale: a
    # twentieth of the pixels, and no full-size float copy of the image
    small = small * np.float32(1 / 255)
    lab = cv2.cvtColor(small, cv2.COLOR_RGB2Lab)
    _, rank = np.unique(cls, return_inverse=True)
    rank = rank.reshape(hs, ws).astype(np.int32)
    step = max(2.0, cell * scale)
    labels = _slic(
        lab,
        rank,
        int(rank.max()) + 1,
        float(step),
        float(params.compactness),
        float(params.class_penalty),
        _SLIC_ITERATIONS,
    )
    if (hs, ws) != (h, w):
        # C-contiguous in one pass (``a[rows][:, cols]`` is neither), which spares
        # superpixel_stats and adjacency a full-size copy each
        labels = _upsample_nearest(labels, nearest_index(h, hs), nearest_index(w, ws))
    return labels


@numba.njit(cache=True, nogil=True)
def _upsample_nearest(labels, rows, cols):  # pragma: no cover - compiled
    """(len(rows), len(cols)) int32 ``labels[rows][:, cols]``, C-contiguous."""
    out = np.empty((rows.shape[0], cols.shape[0]), dtype=labels.dtype)
    for r in range(rows.shape[0]):
        src = labels[rows[r]]
        for c in range(cols.shape[0]):
            out[r, c] = src[cols[c]]
    return out


_SLIC_ITERATIONS = 5  # Achanta et al.: most of the convergence happens in the first few


@numba.njit(cache=True, fastmath=True, error_model="numpy")
def _slic(lab, rank, n_classes, step, compactness, alpha, n_iter):  # pragma: no cover - jit
    """SLIC k-means (Achanta et al. 2012) with the class penalty of eq. 11, then connectivity
    enforcement. lab (h, w, 3) float32, rank (h, w) int32 class ranks. Returns (h, w) int32."""
    h, w = rank.shape
    ny = max(1, int(round(h / step)))
    nx = max(1, int(round(w / step)))
    k_n = ny * nx
    cy = np.empty(k_n, np.float32)
    cx = np.empty(k_n, np.float32)
    cf = np.empty((k_n, 3), np.float32)
    cc = np.empty(k_n, np.int32)
    for a in range(ny):
        for b in range(nx):
            k = a * nx + b
            y = min(h - 1, int((a + 0.5) * h / ny))
            x = min(w - 1, int((b + 0.5) * w / nx))
            cy[k] = y
            cx[k] = x
            for i in range(3):
                cf[k, i] = lab[y, x, i]
            cc[k] = rank[y, x]
    spatial = np.float32((compactness / step) ** 2)
    penalty = np.float32(alpha)
    labels = np.full((h, w), -1, np.int32)
    dist = np.empty((h, w), np.float32)
    sums = np.zeros((k_n, 5))
    votes = np.zeros((k_n, n_classes), np.int32)
    for _ in range(n_iter):
        dist[:] = np.inf
        for k in range(k_n):
            y0 = max(0, int(cy[k] - step))
            y1 = min(h, int(cy[k] + step) + 1)
            x0 = max(0, int(cx[k] - step))
            x1 = min(w, int(cx[k] + step) + 1)
            for y in range(y0, y1):
                for x in range(x0, x1):
                    d0 = lab[y, x, 0] - cf[k, 0]
                    d1 = lab[y, x, 1] - cf[k, 1]
                    d2 = lab[y, x, 2] - cf[k, 2]
                    dy = np.float32(y) - cy[k]
                    dx = np.float32(x) - cx[k]
                    d = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2 + spatial * (dy * dy + dx * dx))
                    if rank[y, x] != cc[k]:
                        d += penalty
                    if d < dist[y, x]:
                        dist[y, x] = d
                        labels[y, x] = k
        sums[:] = 0.0
        votes[:] = 0
        for y in range(h):
            for x in range(w):
                k = labels[y, x]
                if k >= 0:
                    sums[k, 0] += y
                    sums[k, 1] += x
                    for i in range(3):
                        sums[k, 2 + i] += lab[y, x, i]
                    votes[k, rank[y, x]] += 1
        for k in range(k_n):
            n = votes[k].sum()
            if n > 0:
                cy[k] = sums[k, 0] / n
                cx[k] = sums[k, 1] / n
                for i in range(3):
                    cf[k, i] = sums[k, 2 + i] / n
                cc[k] = np.argmax(votes[k])
    return _enforce_connectivity(labels, rank, max(1, int(step * step / 4)))


@numba.njit(cache=True)
def _enforce_connectivity(labels, rank, min_size):  # pragma: no cover - jit
    """Relabel 4-connected pieces 0..n−1; a piece under ``min_size`` px joins a piece of the
    same class already labelled that touches it (Achanta's post-processing, made class-aware
    so that eq. 11 still holds after it); without one it stays a superpixel of its own."""
    h, w = labels.shape
    out = np.full((h, w), -1, np.int32)
    qy = np.empty(h * w, np.int32)
    qx = np.empty(h * w, np.int32)
    n = 0
    for y0 in range(h):
        for x0 in range(w):
            if out[y0, x0] >= 0:
                continue
            old = labels[y0, x0]
            cls = rank[y0, x0]
            same = -1
            out[y0, x0] = n
            qy[0] = y0
            qx[0] = x0
            head = 0
            tail = 1
            while head < tail:
                y = qy[head]
                x = qx[head]
                head += 1
                for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                    yy = y + dy
                    xx = x + dx
                    if yy < 0 or yy >= h or xx < 0 or xx >= w:
                        continue
                    o = out[yy, xx]
                    if o < 0 and labels[yy, xx] == old:
                        out[yy, xx] = n
                        qy[tail] = yy
                        qx[tail] = xx
                        tail += 1
                    elif o >= 0 and o != n and rank[yy, xx] == cls:
                        same = o
            if tail < min_size and same >= 0:
                for i in range(tail):
                    out[qy[i], qx[i]] = same
            else:
                n += 1
    return out


def nearest_index(n_out: int, n_in: int) -> np.ndarray:
    """Indices into an axis of length ``n_in`` for nearest resampling to ``n_out`` samples."""
    return np.minimum(((np.arange(n_out) + 0.5) * (n_in / n_out)).astype(np.int64), n_in - 1)


def adjacency(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Superpixel adjacency from a label image (4-neighbourhood).

    labels : (H, W) int labels 0..n−1. Returns ``pairs`` (E, 2) int64 with ``i < j`` and
    ``boundary`` (E,) int64, the number of 4-neighbour pixel pairs between ``i`` and ``j``.
    """
    labels = np.ascontiguousarray(labels, dtype=np.int32)
    n = int(labels.max()) + 1
    uniq, counts = np.unique(_boundary_keys(labels, n), return_counts=True)
    return np.column_stack([uniq // n, uniq % n]), counts


@numba.njit(cache=True, nogil=True)
def _boundary_keys(labels, n):  # pragma: no cover - compiled
    """``min·n + max`` of the two labels of every 4-neighbour pixel pair that differ."""
    h, w = labels.shape
    keys = np.empty(2 * h * w, np.int64)
    k = 0
    for r in range(h):
        for c in range(w):
            a = labels[r, c]
            if c + 1 < w and labels[r, c + 1] != a:
                b = labels[r, c + 1]
                keys[k] = min(a, b) * np.int64(n) + max(a, b)
                k += 1
            if r + 1 < h and labels[r + 1, c] != a:
                b = labels[r + 1, c]
                keys[k] = min(a, b) * np.int64(n) + max(a, b)
                k += 1
    return keys[:k]


@dataclass(frozen=True)
class SuperpixelStats:
    """Per-superpixel means, (n,) arrays: pixel count, RGB (n, 3), depth (NaN = none), class
    (majority, 0 = none), mean node energy."""

    count: np.ndarray
    color: np.ndarray
    depth: np.ndarray
    classes: np.ndarray
    energy: np.ndarray


def superpixel_mean(values: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Each pixel's superpixel mean of ``values`` (H, W) float: (H, W) float32, for the node
    energy of a superpixel from its mean raw change (``GraphCutParams.energy_of_mean``: the
    paper assigns each superpixel "the average value over all the pixels", §3.4).
    labels : (H, W) int superpixels 0..n−1 (:func:`superpixels`)."""
    flat = np.ascontiguousarray(labels, dtype=np.int64).ravel()
    n = int(flat.max()) + 1 if flat.size else 0
    count = np.maximum(np.bincount(flat, minlength=n), 1)
    sums = np.bincount(flat, np.asarray(values, np.float64).ravel(), minlength=n)
    return (sums / count).astype(np.float32)[flat].reshape(np.shape(labels))


def superpixel_stats(
    labels: np.ndarray,
    image: np.ndarray,
    depth: np.ndarray,
    classes: np.ndarray,
    energy: np.ndarray,
) -> SuperpixelStats:
    """Mean colour, depth (over pixels with a surface), majority class and mean node energy
    of each superpixel; inputs (H, W[, 3]) as in :func:`cut_changes`."""
    labels = np.ascontiguousarray(labels, dtype=np.int32)
    n = int(labels.max()) + 1
    count, color, depth_sum, n_depth, votes, energy_sum = _sums(
        labels,
        n,
        np.ascontiguousarray(image, dtype=np.float32),
        np.ascontiguousarray(depth, dtype=np.float32),
        np.ascontiguousarray(classes, np.uint8),
        np.ascontiguousarray(energy, dtype=np.float32),
    )
    safe = np.maximum(count, 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_depth = np.where(n_depth > 0, depth_sum / np.maximum(n_depth, 1), np.nan)
    majority = votes.argmax(axis=1).astype(np.uint8)
    return SuperpixelStats(count, color / safe[:, None], mean_depth, majority, energy_sum / safe)


@numba.njit(cache=True, nogil=True)
def _sums(labels, n, image, depth, classes, energy):  # pragma: no cover - compiled
    """One pass: per label pixel count, RGB sums, depth sum and count (finite only), class
    votes (n, 256) and energy sum."""
    count = np.zeros(n)
    color = np.zeros((n, 3))
    depth_sum = np.zeros(n)
    n_depth = np.zeros(n)
    votes = np.zeros((n, 256), np.int32)
    energy_sum = np.zeros(n)
    h, w = labels.shape
    for r in range(h):
        for c in range(w):
            k = labels[r, c]
            count[k] += 1.0
            for ch in range(3):
                color[k, ch] += image[r, c, ch]
            z = depth[r, c]
            if np.isfinite(z):
                depth_sum[k] += z
                n_depth[k] += 1.0
            votes[k, classes[r, c]] += 1
            energy_sum[k] += energy[r, c]
    return count, color, depth_sum, n_depth, votes, energy_sum


def min_cut(
    cost_unchanged: np.ndarray, cost_changed: np.ndarray, pairs: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """Minimise eq. 6 on a graph with PyMaxflow: ``Σ D_i(x_i) + Σ w_ij [x_i ≠ x_j]``.

    cost_unchanged, cost_changed : (n,) ``D_i(0)``, ``D_i(1)`` ≥ 0. pairs : (E, 2) node
    indices; weights : (E,) ≥ 0 (β already applied). Returns (n,) bool, True = changed.
    """
    import maxflow

    n = len(cost_unchanged)
    graph = maxflow.Graph[float](n, len(pairs))
    nodes = graph.add_nodes(n)
    # A node on the sink side (segment 1, "changed") cuts its source edge: that capacity is
    # the cost of being changed; the sink edge is cut for the source side ("unchanged").
    graph.add_grid_tedges(
        nodes, np.asarray(cost_changed, np.float64), np.asarray(cost_unchanged, np.float64)
    )
    if len(pairs):
        w = np.asarray(weights, np.float64)
        graph.add_edges(nodes[pairs[:, 0]], nodes[pairs[:, 1]], w, w)
    graph.maxflow()
    return np.asarray(graph.get_grid_segments(nodes), dtype=bool)


def speckle_filter(mask: np.ndarray, min_px: float) -> np.ndarray:
    """Remove 8-connected changed segments with fewer than ``min_px`` pixels.

    mask : (H, W) bool. Returns a new (H, W) bool; segments of exactly ``min_px`` stay.
    """
    if min_px <= 1:
        return mask.copy()
    box = mask_box(mask)
    if box is None:
        return mask.copy()
    # labelled within the segments' bounding box: a view's changes cover a few per cent of
    # it, and labelling the whole image (int32 labels, 11 ms at 2 MP) was most of the cost
    n, labels, stats, _ = cv2.connectedComponentsWithStats(
        np.ascontiguousarray(mask[box], np.uint8), connectivity=8
    )
    keep = stats[:, cv2.CC_STAT_AREA] >= min_px
    keep[0] = False  # background
    out = np.zeros_like(mask, dtype=bool)
    out[box] = keep[labels]
    return out


def speckle_min_px(width: int, params: GraphCutParams) -> float:
    """Speckle area threshold at an image ``width`` px wide: an area, so it scales with the
    square of the width relative to ``REFERENCE_WIDTH_PX``."""
    return params.speckle_min_px * (width / REFERENCE_WIDTH_PX) ** 2


@dataclass(frozen=True)
class CutResult:
    """Result of :func:`cut_changes`: ``mask`` (H, W) bool after the speckle filter,
    ``superpixels`` (H, W) int32 labels, ``changed`` (n,) bool per superpixel (before the
    speckle filter), ``stats`` the per-superpixel means the cut used."""

    mask: np.ndarray
    superpixels: np.ndarray
    changed: np.ndarray
    stats: SuperpixelStats


def cut_changes(
    energy: np.ndarray,
    image: np.ndarray,
    depth: np.ndarray,
    classes: np.ndarray,
    params: GraphCutParams = _DEFAULTS,
    labels: np.ndarray | None = None,
) -> CutResult:
    """Graph cut of eq. 6 on class-aware superpixels, then the speckle filter.

    energy : (H, W) float32 node energy ``f`` in [0, 1] (:func:`node_energy`).
    image : (H, W, 3) float32 stretched RGB in [0, 255] (colour term of eq. 8).
    depth : (H, W) float32 metres, NaN = no surface. classes : (H, W) uint8 (0 = none).
    labels : precomputed superpixels (H, W) int32, else :func:`superpixels` is run.
    """
    h, w = classes.shape
    if labels is None:
        labels = superpixels(image, classes, params)
    stats = superpixel_stats(labels, image, depth, classes, energy)
    cell = scale_px(params.superpixel_cell_px, w, minimum=2.0)
    area = stats.count / (cell * cell)
    pairs, boundary = adjacency(labels)
    i, j = pairs[:, 0], pairs[:, 1]
    sim = smoothness(
        stats.color[i],
        stats.color[j],
        stats.depth[i],
        stats.depth[j],
        stats.classes[i],
        stats.classes[j],
        params,
    )
    weights = params.beta * sim * boundary / cell
    changed = min_cut(area * stats.energy, area * (1.0 - stats.energy), pairs, weights)
    min_px = speckle_min_px(w, params)
    if min_px <= 1 or not changed.any():
        return CutResult(changed[labels], labels, changed, stats)
    mask = _speckle_superpixels(labels, changed, stats.count, float(min_px))
    return CutResult(mask, labels, changed, stats)


@numba.njit(cache=True, nogil=True)
def _speckle_superpixels(labels, changed, count, min_px):  # pragma: no cover - compiled
    """:func:`speckle_filter` of ``changed[labels]`` (H, W) bool, on superpixels.

    labels (H, W) int32 superpixels, each 4-connected (as :func:`superpixels` makes them);
    changed (n,) bool; count (n,) float64 pixels per superpixel. The mask is a union of
    whole superpixels, so its 8-connected segments are unions of changed superpixels that
    touch (side or corner): one pass over the pixels joins those (union-find), a segment's
    area is the sum of its superpixels' counts, and the mask is drawn from the superpixels
    kept. The same mask as labelling the pixels with OpenCV's connected components, in a
    fraction of their time (docs/BENCHMARKS.md).
    """
    n = changed.shape[0]
    parent = np.arange(n)
    h, w = labels.shape
    for r in range(h):
        for c in range(w):
            a = labels[r, c]
            if not changed[a]:
                continue
            # right, down-left, down, down-right: every 8-neighbour pair once
            for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):
                rr, cc = r + dr, c + dc
                if rr >= h or cc < 0 or cc >= w:
                    continue
                b = labels[rr, cc]
                if b == a or not changed[b]:
                    continue
                ra, rb = _root(parent, a), _root(parent, b)
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
    area = np.zeros(n)
    for k in range(n):
        if changed[k]:
            area[_root(parent, k)] += count[k]
    keep = np.zeros(n, np.bool_)
    for k in range(n):
        keep[k] = changed[k] and area[_root(parent, k)] >= min_px
    out = np.empty((h, w), np.bool_)
    for r in range(h):
        for c in range(w):
            out[r, c] = keep[labels[r, c]]
    return out


@numba.njit(cache=True, inline="always")
def _root(parent, k):  # pragma: no cover - compiled
    """Root of ``k`` in the union-find forest ``parent``, halving the path on the way."""
    while parent[k] != k:
        parent[k] = parent[parent[k]]
        k = parent[k]
    return k
