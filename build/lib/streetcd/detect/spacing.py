"""The reference cloud's own point spacing, per class (not in the paper; issue 16).

The paper's triangle filters (30 px edges at 16 MP, 0.5 m depth jumps) and the z-buffer's
adaptive window (:mod:`streetcd.detect.zbuffer`, 0.12 m) are set for dense mobile mapping.
A tenth of the points, or an automotive LiDAR (one point per 50–100 px of a photograph),
leaves most triangles longer than that, and the view surface falls apart. The spacing
measured here lets :mod:`streetcd.detect.surface` widen those limits where, and only where,
the cloud is sparser; the limits never go below the configured ones.

The measure: the median distance (metres) from a point to its nearest neighbour in 3D, per
class code, on a random sample. Why per class: a cloud may hold surfaces scanned at very
different densities (the real case's dense street furniture in sparse LiDAR), and the class
is the one label every point carries. The nearest neighbours are found in a random subset of
at most ``TREE_POINTS`` points and the distances scaled by ``sqrt(subset / all)``: a random
subset of fraction p of points on surfaces is spaced ``1 / sqrt(p)`` times wider (exact for an
even 2D density; a few per cent off on the synthetic streets, docs/DECISIONS.md). That keeps
the cost to one small k-d tree per cloud (a third of a second at 3 M points, this VM),
computed once and kept while the cloud's array lives.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from streetcd.detect.memo import ArrayMemo
from streetcd.errors import InputError

TREE_POINTS = 250_000  # the k-d tree holds at most this many points of the cloud
SAMPLE_POINTS = 8192  # points whose nearest neighbour is looked up
MIN_CLASS_SAMPLES = 32  # a class with fewer sampled points takes the whole cloud's median
_SAMPLES = ArrayMemo()  # a cloud's xyz → (sample indices, their spacing)


def sampled_spacing(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-neighbour spacing of a random sample of a cloud's points (see module doc).

    xyz : (N, 3) float64, metres (any frame). Returns ``(index, spacing)``: (S,) int64 rows of
    ``xyz`` and (S,) float64 metres, S = min(N, ``SAMPLE_POINTS``); both empty for fewer
    than two points. The sample is fixed (seed 0), so the result is deterministic; kept
    while ``xyz`` lives (it must not be changed in place).
    """
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"xyz must be (N, 3), got shape {xyz.shape}")
    return _SAMPLES.get(xyz, _sample)


def _sample(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = xyz.shape[0]
    if n < 2:
        return np.empty(0, np.int64), np.empty(0, np.float64)
    rng = np.random.default_rng(0)
    subset = np.sort(rng.choice(n, TREE_POINTS, replace=False)) if n > TREE_POINTS else None
    rows = subset if subset is not None else np.arange(n)
    pts = np.ascontiguousarray(xyz[rows], dtype=np.float64)
    picks = np.sort(rng.choice(len(rows), min(SAMPLE_POINTS, len(rows)), replace=False))
    dist, _ = cKDTree(pts).query(pts[picks], k=2)
    # the second hit is the nearest other point (the first is the point itself, or a
    # duplicate at distance 0, which is a spacing of 0: kept, duplicates are real)
    spacing = dist[:, 1] * np.sqrt(len(rows) / n)
    return rows[picks].astype(np.int64), spacing


def class_spacing(xyz: np.ndarray, classes: np.ndarray) -> np.ndarray:
    """Point spacing per class code: (256,) float64 metres, indexed by code.

    xyz : (N, 3) float64 metres; classes : (N,) integer codes 0–255. Each code's value is the
    median nearest-neighbour spacing of its sampled points (:func:`sampled_spacing`); codes
    with fewer than ``MIN_CLASS_SAMPLES`` of them (and codes not in the cloud) take the
    median of the whole sample; 0 everywhere for a cloud of fewer than two points.
    """
    classes = np.asarray(classes)
    if classes.shape != (np.asarray(xyz).shape[0],):
        raise InputError(f"classes must be ({np.asarray(xyz).shape[0]},), got {classes.shape}")
    index, spacing = sampled_spacing(xyz)
    out = np.zeros(256, np.float64)
    if spacing.size == 0:
        return out
    out[:] = np.median(spacing)
    codes = classes[index].astype(np.int64)
    if codes.size and (codes.min() < 0 or codes.max() > 255):
        raise InputError(f"class codes must be 0–255, got {codes.min()}–{codes.max()}")
    for code in np.unique(codes):
        mine = spacing[codes == code]
        if mine.size >= MIN_CLASS_SAMPLES:
            out[code] = np.median(mine)
    return out
