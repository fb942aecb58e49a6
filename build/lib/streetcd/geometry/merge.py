"""Merging per-view change regions in 3D: which regions are one physical change, and where
that change stands.

Pure numpy kernels (no I/O); :mod:`streetcd.store.objects` feeds them the regions of a
segment's flagged views, each located through its view's old-surface depth
(:mod:`streetcd.detect.regions`). Coordinates are metres in one frame (the CRS).
"""

from __future__ import annotations

import numpy as np

MAX_SIZE_RATIO = 5.0  # two views of one object: apparent sizes within this factor


def link_regions(
    centroids: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    margin_m: float = 0.5,
    max_link_m: float = 4.0,
    cameras: np.ndarray | None = None,
    view_ids: np.ndarray | None = None,
    max_ray_gap_m: float = 0.5,
    object_ids: np.ndarray | None = None,
    pixels: np.ndarray | None = None,
) -> np.ndarray:
    """Connected components of regions that are one change in 3D.

    centroids, lo, hi : (N, 3) float64, metres: each region's centroid and box corners,
    located on the old surface behind its pixels. Two regions are linked when

    * their boxes, each grown by ``margin_m``, overlap on all three axes and their
      centroids are at most ``max_link_m`` apart (a large box, a region seen against a far
      wall, must not swallow every small one near it): the same spot of the old surface;
    * or, for regions of two different views (``cameras`` (N, 3) their camera centres,
      ``view_ids`` (N,) which view each is), their lines of sight (camera → centroid) pass
      within ``max_ray_gap_m`` of each other at a point in front of both old surfaces that
      each region covers when seen from its camera (:func:`covers`): a new object standing
      before the surface, which each view sees against another part of it.

    Links are taken closest first (centroid distance, or the gap between the lines of
    sight), and never join two groups that both hold a region of the same view: the
    detector already told a view's regions apart (a car beside a new board are two
    regions in every view that sees both, and stay two objects however close they stand).
    The exception: two regions of one view are one object split in two when their boxes
    overlap on every axis by at least half the smaller one's extent, or when they touch and
    lie on the same kind of object of the old cloud (``object_ids`` (N,): the old object's
    class under each region, -1 for none; a board cut by a post). The latter are joined
    first; the former are a link like the others, at their centroid distance, that may join
    two groups sharing that view only.

    ``pixels`` (N,): with it, regions of two views link (either way) only when they are of
    about the same apparent size (within a factor :data:`MAX_SIZE_RATIO`): one object seen
    from two nearby views; a speck of noise whose line of sight crosses a large region's, or
    whose box touches it, is no evidence.

    Returns (N,) int64 component labels 0, 1, … numbered in order of each component's
    first region, so the result depends only on the order of the input.
    """
    n = len(centroids)
    parent = np.arange(n)
    if view_ids is None:
        view_ids = np.arange(n)
    members: dict[int, set[int]] = {i: {int(view_ids[i])} for i in range(n)}

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = int(parent[i])
        return i

    if n:
        touch = np.all(
            (lo[:, None, :] - margin_m <= hi[None, :, :] + margin_m)
            & (lo[None, :, :] - margin_m <= hi[:, None, :] + margin_m),
            axis=2,
        )
        dist = np.linalg.norm(centroids[:, None, :] - centroids[None, :, :], axis=2)
        same_view = view_ids[:, None] == view_ids[None, :]
        cost = np.where(touch & (dist <= max_link_m), dist, np.inf)
        alike = np.ones((n, n), bool)
        if pixels is not None:
            # Two views of one thing from nearby cameras see it at about the same size, on
            # the old surface as before it: a speck touching a large region of another view
            # is no evidence (seed 0: a parked car's region chained to two specks).
            px = np.maximum(np.asarray(pixels, dtype=np.float64), 1.0)
            ratio = np.maximum(px[:, None] / px[None, :], px[None, :] / px[:, None])
            alike = ratio <= MAX_SIZE_RATIO
            cost = np.where(alike | same_view, cost, np.inf)
        if cameras is not None:
            gap = _rays_meet(centroids, lo, hi, cameras, view_ids, margin_m, max_ray_gap_m)
            cost = np.minimum(cost, np.where(alike, gap, np.inf))
        on_one = np.zeros((n, n), bool)
        if object_ids is not None:
            on_one = (object_ids[:, None] == object_ids[None, :]) & (object_ids[:, None] >= 0)
            on_one &= touch & same_view
        for i, j in zip(*np.nonzero(np.triu(on_one, k=1)), strict=True):
            a, b = find(int(i)), find(int(j))
            if a != b:
                keep, gone = min(a, b), max(a, b)
                parent[gone] = keep
                members[keep] |= members.pop(gone)
        # Boxes that overlap by half take their turn among the links, at their centroid
        # distance: taken first, a car's lower half lying flat inside the box of a region
        # holding the car's roof and a board behind it tied the board to the car before the
        # board's other views could link to it (seed 0's added board, issue 17). Two parts
        # of one old object (above) are surer and are joined first.
        same = same_view & _overlap_half(lo, hi)
        cost = np.where(same, dist, np.where(same_view, np.inf, cost))
        i_s, j_s = np.nonzero(np.triu(np.isfinite(cost), k=1))
        for k in np.lexsort((j_s, i_s, cost[i_s, j_s])):  # closest first, ties by index
            a, b = find(int(i_s[k])), find(int(j_s[k]))
            # Groups that share a view are not joined, save through the two parts of that
            # view's one object.
            shared = members[a] & members[b]
            if same[i_s[k], j_s[k]]:
                shared = shared - {int(view_ids[i_s[k]])}
            if a == b or shared:
                continue
            keep, gone = min(a, b), max(a, b)
            parent[gone] = keep
            members[keep] |= members.pop(gone)
    roots = np.array([find(i) for i in range(n)], dtype=np.int64)
    _, first, labels = np.unique(roots, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))  # renumber by first appearance
    return order[labels].astype(np.int64)


def _overlap_half(lo: np.ndarray, hi: np.ndarray, floor_m: float = 0.1) -> np.ndarray:
    """(N, N) bool: boxes whose overlap on every axis is at least half the smaller extent
    there (extents below ``floor_m`` count as ``floor_m``: a flat region still overlaps)."""
    ext = np.maximum(hi - lo, floor_m)
    inter = np.minimum(hi[:, None, :], hi[None, :, :]) - np.maximum(lo[:, None, :], lo[None, :, :])
    need = 0.5 * np.minimum(ext[:, None, :], ext[None, :, :])
    return np.all(inter >= need, axis=2)


def covers(
    point: np.ndarray,
    camera: np.ndarray,
    centroid: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    margin_m: float = 0.5,
) -> bool:
    """Whether a region (located on the old surface: ``centroid``, box ``lo``–``hi``) covers
    ``point`` as its camera sees it: the line of sight through ``point``, carried to the
    region's depth, lands in the box grown by ``margin_m``. All (3,) metres."""
    d = point - camera
    dist = float(np.linalg.norm(d))
    if dist < 1e-6:
        return False
    on_surface = camera + d * (float(np.linalg.norm(centroid - camera)) / dist)
    return bool(np.all(on_surface >= lo - margin_m) and np.all(on_surface <= hi + margin_m))


def _rays_meet(
    centroids: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    cameras: np.ndarray,
    view_ids: np.ndarray,
    margin_m: float,
    max_gap_m: float,
    chunk: int = 1 << 16,
) -> np.ndarray:
    """(N, N) float: for pairs of regions of different views whose lines of sight meet
    (see :func:`link_regions`), the gap between the lines there (metres); inf otherwise.

    All pairs at once, ``chunk`` pairs per numpy call (a pair at a time in Python was a
    quarter of a city night's change-object building, docs/BENCHMARKS.md)."""
    n = len(centroids)
    out = np.full((n, n), np.inf)
    has = np.all(np.isfinite(cameras), axis=1)
    d = centroids - cameras
    length = np.linalg.norm(d, axis=1)
    u = d / np.where(length > 0, length, 1.0)[:, None]
    first, second = np.triu_indices(n, k=1)
    keep = has[first] & has[second] & (view_ids[first] != view_ids[second])
    first, second = first[keep], second[keep]
    for start in range(0, len(first), chunk):
        i, j = first[start : start + chunk], second[start : start + chunk]
        gap = _pair_gaps(i, j, centroids, lo, hi, cameras, u, length, margin_m, max_gap_m)
        out[i, j] = out[j, i] = gap
    return out


def _pair_gaps(
    i: np.ndarray,
    j: np.ndarray,
    centroids: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    cameras: np.ndarray,
    u: np.ndarray,
    length: np.ndarray,
    margin_m: float,
    max_gap_m: float,
) -> np.ndarray:
    """(P,) the gap of each pair (i[k], j[k]) of :func:`_rays_meet`, inf where they do not
    meet: closest points of the lines c_i + s u_i and c_j + t u_j, in front of both cameras
    (0.5 m) and not beyond either region's surface, within ``max_gap_m``, at a point both
    regions cover."""
    w = cameras[i] - cameras[j]
    b = np.einsum("pk,pk->p", u[i], u[j])
    uw_i = np.einsum("pk,pk->p", u[i], w)
    uw_j = np.einsum("pk,pk->p", u[j], w)
    den = 1.0 - b * b
    ok = den >= 1e-4  # (nearly) parallel: no depth from this pair
    den = np.where(ok, den, 1.0)
    s = (b * uw_j - uw_i) / den
    t = (uw_j - b * uw_i) / den
    ok &= (0.5 < s) & (s <= length[i] + margin_m) & (0.5 < t) & (t <= length[j] + margin_m)
    p_i = cameras[i] + s[:, None] * u[i]
    p_j = cameras[j] + t[:, None] * u[j]
    gap = np.linalg.norm(p_i - p_j, axis=1)
    ok &= gap <= max_gap_m
    x = (p_i + p_j) / 2
    ok &= _covers_all(x, cameras[i], centroids[i], lo[i], hi[i], margin_m)
    ok &= _covers_all(x, cameras[j], centroids[j], lo[j], hi[j], margin_m)
    return np.where(ok, gap, np.inf)


def _covers_all(
    points: np.ndarray,
    cameras: np.ndarray,
    centroids: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    margin_m: float,
) -> np.ndarray:
    """(P,) bool: :func:`covers` of each row ((P, 3) metres each)."""
    d = points - cameras
    dist = np.linalg.norm(d, axis=1)
    near = dist < 1e-6
    scale = np.linalg.norm(centroids - cameras, axis=1) / np.where(near, 1.0, dist)
    on_surface = cameras + d * scale[:, None]
    inside = np.all((on_surface >= lo - margin_m) & (on_surface <= hi + margin_m), axis=1)
    return inside & ~near


def nearest_to_rays(origins: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, float]:
    """The point nearest (least squares) to the rays from ``origins`` through ``targets``
    ((K, 3) metres each, K ≥ 2), and its RMS distance to them (metres).

    The rays are the views' lines of sight through a change's region centroids; where they
    meet is the change itself (for an added object, in front of the old surface the regions
    were located on). Rays that are almost parallel (all within ~1°) give no depth: the
    mean target is returned with an infinite distance.
    """
    d = targets - origins
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # (K, 3, 3): off-ray component
    a = proj.sum(axis=0)
    b = np.einsum("kij,kj->i", proj, origins)
    if np.linalg.cond(a) > 1e4 or len(origins) < 2:
        return targets.mean(axis=0), float("inf")
    x = np.linalg.solve(a, b)
    off = np.einsum("kij,kj->ki", proj, x[None] - origins)
    return x, float(np.sqrt(np.mean(np.sum(off**2, axis=1))))
