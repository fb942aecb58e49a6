"""Roles of a cloud's points from its geometry alone, for clouds whose classes say nothing
(not in the paper, whose scanner delivered classes): an unclassified cloud (all class 1)
otherwise loses the low weight of the ground and trees in eq. 5 and the reference-colour and
texture cues, which run on the street inventory only (docs/TUNING.md: kappa 0.17 against 0.53
classified on the same street).

Cheap and deterministic, a few array passes over the points:

1. the ground: the lowest point of each 1 m cell, its pits closed and its bumps narrower than
   ``GROUND_WINDOW_M`` opened away (a grey opening keeps slopes and steps wider than the
   window, removes cars, poles and hedges); a point within ``GROUND_TOLERANCE_M`` of it is
   ground;
2. the rest, binned in ``VOXEL_M`` voxels of (x, y, height above the ground), split into 3D
   connected parts; each part is given a role by its size: tall and long with a thin
   footprint (a façade seen from the street) a building, thin and small across a pole (tall)
   or furniture (low), long and thin and low a railing, car-sized a vehicle, and the rest
   (canopies, hedges: a filled footprint) vegetation;
3. a railing's foot: the points of step 1 more than ``FOOT_M`` above the ground in a railing's
   voxel columns are railing too.

The road and the sidewalk are not told apart (both have the ground's low weight in eq. 5).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from streetcd import classes

GROUND_CELL_M = 1.0  # the ground grid's cells
GROUND_WINDOW_M = 5.0  # wider than a car, narrower than most streets' flat stretches
GROUND_TOLERANCE_M = 0.3  # above a kerb's step (0.10-0.15 m): the sidewalk is ground too
VOXEL_M = 0.25  # parts closer than this may merge (a bin by a parked car stays apart)
MAX_HEIGHT_M = 60.0  # heights above the ground are clipped to this (the voxel grid's depth)
# a ground point this far above the ground surface in a railing's column is the railing's
# foot (the ground tolerance cuts the lowest 0.3 m off every object; 0: no feet)
FOOT_M = 0.05

# The part rules, metres: L and W are a part's footprint length and width (from the spread of
# its voxels), top its highest voxel above the ground.
LOW_PART_M = 0.5  # parts below this (kerbs, bumps, litter) are ground
SMALL_LENGTH_M = 3.0  # a pole (a street light's arm included), a sign, a bench or a bin ...
SMALL_WIDTH_M = 1.0  # ... is at most this long and this wide
POLE_TOP_M = 2.2  # a small part taller than this is a pole (or a sign on one), else furniture
FLOATING_BOTTOM_M = 1.0  # ... when it stands on the ground: a small part starting higher is foliage
RAILING_TOP_M = 1.6  # a long thin part lower than this is a railing ...
RAILING_WIDTH_M = 0.75  # ... when at most this wide (a hedge is wider)
BUILDING_TOP_M = 3.0  # a façade is taller than this ...
BUILDING_LENGTH_M = 4.0  # ... longer than this ...
BUILDING_FILL = 0.4  # ... and its footprint an outline (a canopy's fills its box) ...
BUILDING_WIDTH_M = 1.5  # ... or a wall (a tree's canopy is wider)
VEHICLE_TOP_M = (1.0, 2.6)  # a car or a van: its height, length and width within these
VEHICLE_LENGTH_M = (3.0, 6.5)
VEHICLE_WIDTH_M = (1.4, 2.8)


def infer_roles(xyz: np.ndarray) -> np.ndarray:
    """Roles of the points ``xyz`` (N, 3) float metres, z up, as (N,) uint8 streetcd codes
    (:data:`streetcd.classes.ROLES`): ground, building, vegetation, pole, furniture, railing or
    vehicle; :data:`~streetcd.classes.UNCLASSIFIED` for non-finite points."""
    xyz = np.asarray(xyz, np.float64)
    roles = np.full(len(xyz), classes.UNCLASSIFIED, np.uint8)
    finite = np.isfinite(xyz[:, 0]) & np.isfinite(xyz[:, 1]) & np.isfinite(xyz[:, 2])
    if not finite.any():
        return roles
    pts = xyz if finite.all() else xyz[finite]
    height = height_above_ground(pts)
    out = np.full(len(pts), classes.GROUND, np.uint8)
    above = np.flatnonzero(height >= GROUND_TOLERANCE_M)
    if len(above):
        out[above] = part_roles(pts[above, :2], height[above])
        if FOOT_M > 0:
            out = with_feet(pts[:, :2], height, out)
    roles[finite] = out
    return roles


def with_feet(xy: np.ndarray, height: np.ndarray, roles: np.ndarray) -> np.ndarray:
    """``roles`` (N,) uint8 with the ground points that lie more than ``FOOT_M`` above the
    ground surface (``height`` (N,) metres) in a ``VOXEL_M`` column (``xy`` (N, 2) metres)
    of a railing made railing: the ground tolerance cuts the lowest 0.3 m off every object,
    a third of a railing, whose colours are then not checked there (docs/TUNING.md,
    seventeenth round). Only railings: on the real LiDAR the feet of poles, made pole,
    flagged views of the unchanged twin."""
    railing = roles == classes.RAILING
    low = np.flatnonzero((roles == classes.GROUND) & (height > FOOT_M))
    if not railing.any() or not len(low):
        return roles
    col, row = _cell_index(xy[:, 0], VOXEL_M), _cell_index(xy[:, 1], VOXEL_M)
    key = col * (int(row.max()) + 1) + row
    columns = np.unique(key[railing])
    at = np.minimum(np.searchsorted(columns, key[low]), len(columns) - 1)
    out = roles.copy()
    out[low[columns[at] == key[low]]] = classes.RAILING
    return out


def height_above_ground(xyz: np.ndarray) -> np.ndarray:
    """(N,) float32 metres of each point of ``xyz`` (N, 3) (finite) above the ground surface:
    the per-cell lowest point (``GROUND_CELL_M`` cells), single-cell pits closed, then opened
    with a ``GROUND_WINDOW_M`` square (objects narrower than that are not ground)."""
    col, row = _cell_index(xyz[:, 0], GROUND_CELL_M), _cell_index(xyz[:, 1], GROUND_CELL_M)
    shape = (int(col.max()) + 1, int(row.max()) + 1)
    flat = col * shape[1] + row
    lowest = np.full(shape[0] * shape[1], np.inf)
    np.minimum.at(lowest, flat, xyz[:, 2])
    grid = _fill_empty(lowest.reshape(shape))
    grid = ndimage.grey_closing(grid, size=(3, 3), mode="nearest")  # a stray low point
    window = max(1, round(GROUND_WINDOW_M / GROUND_CELL_M))
    grid = ndimage.grey_opening(grid, size=(window, window), mode="nearest")
    return (xyz[:, 2] - grid.ravel()[flat]).astype(np.float32)


def _cell_index(values: np.ndarray, size: float) -> np.ndarray:
    """(N,) int64 index of ``values`` (N,) metres in cells of ``size`` metres from their minimum."""
    return ((values - values.min()) * (1.0 / size)).astype(np.int64)


def _fill_empty(grid: np.ndarray) -> np.ndarray:
    """``grid`` (H, W) with its +inf cells given the value of the nearest finite cell."""
    empty = ~np.isfinite(grid)
    if not empty.any():
        return grid
    _, (rows, cols) = ndimage.distance_transform_edt(empty, return_indices=True)
    return grid[rows, cols]


def part_roles(xy: np.ndarray, height: np.ndarray) -> np.ndarray:
    """(N,) uint8 roles of above-ground points: ``xy`` (N, 2) metres, ``height`` (N,) metres
    above the ground (all ≥ ``GROUND_TOLERANCE_M``), by the size of the 3D connected part of
    ``VOXEL_M`` voxels each point is in (see the module's rules)."""
    idx = (
        _cell_index(xy[:, 0], VOXEL_M),
        _cell_index(xy[:, 1], VOXEL_M),
        (np.minimum(height, MAX_HEIGHT_M) * (1.0 / VOXEL_M)).astype(np.int64),
    )
    dims = np.array([int(i.max()) + 1 for i in idx])
    keys, voxel_of_point = np.unique(_keys(np.stack(idx, axis=-1), dims), return_inverse=True)
    cells = np.stack(np.unravel_index(keys, tuple(int(d) for d in dims)), axis=1)
    part = connected_voxels(cells)
    table = _rules(_part_sizes(cells, part, int(part.max()) + 1, VOXEL_M))
    return table[part[voxel_of_point]]


def connected_voxels(cells: np.ndarray) -> np.ndarray:
    """(V,) int part of each occupied voxel ``cells`` (V, 3) int (distinct, ≥ 0): the
    26-connected components, numbered from 0. Sparse (sorted keys and a graph of the
    neighbours found), so its memory grows with the points, not with the crop's extent."""
    dims = cells.max(axis=0) + 3  # a margin of one voxel: a neighbour's key never wraps
    keys = _keys(cells + 1, dims)
    order = np.argsort(keys)
    keys = keys[order]
    src, dst = [], []
    for step in _HALF_NEIGHBOURHOOD:
        wanted = keys + _keys(step, dims)
        at = np.minimum(np.searchsorted(keys, wanted), len(keys) - 1)
        hit = np.flatnonzero(keys[at] == wanted)
        src.append(hit)
        dst.append(at[hit])
    i, j = np.concatenate(src), np.concatenate(dst)
    graph = sparse.coo_matrix((np.ones(len(i), np.int8), (i, j)), shape=(len(keys),) * 2)
    _, sorted_part = csgraph.connected_components(graph, directed=False)
    part = np.empty(len(keys), np.int64)
    part[order] = sorted_part
    return part


def _keys(cells: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """One int64 per voxel (..., 3) of a grid ``dims`` (3,)."""
    return (cells[..., 0] * dims[1] + cells[..., 1]) * dims[2] + cells[..., 2]


# the 13 of the 26 neighbours with a larger key: each pair of touching voxels is found once
_HALF_NEIGHBOURHOOD = np.array([d for d in np.ndindex(3, 3, 3) if d > (1, 1, 1)], np.int64) - 1


def _part_sizes(cells: np.ndarray, part: np.ndarray, n: int, voxel: float) -> dict[str, np.ndarray]:
    """Per part (``n`` parts, numbered from 0 in ``part`` (V,), one per voxel of ``cells``
    (V, 3)), metres: ``length`` and ``width`` of its footprint (the spread of
    its voxels along and across their main horizontal axis, as a uniform bar's ``√(12·var)``,
    plus one voxel), ``top`` (its highest voxel's top above the ground) and ``fill`` (the
    share of that length × width its footprint's columns cover)."""
    count = np.bincount(part, minlength=n).astype(np.float64)
    x, y = (cells[:, 0] + 0.5) * voxel, (cells[:, 1] + 0.5) * voxel
    safe = np.maximum(count, 1)
    mx, my = np.bincount(part, x, n) / safe, np.bincount(part, y, n) / safe
    dx, dy = x - mx[part], y - my[part]
    sxx = np.bincount(part, dx * dx, n) / safe
    syy = np.bincount(part, dy * dy, n) / safe
    sxy = np.bincount(part, dx * dy, n) / safe
    mid, half = (sxx + syy) / 2, np.sqrt(((sxx - syy) / 2) ** 2 + sxy**2)
    length = np.sqrt(12 * (mid + half)) + voxel
    width = np.sqrt(12 * np.maximum(mid - half, 0.0)) + voxel
    top = np.zeros(n)
    np.maximum.at(top, part, (cells[:, 2] + 1) * voxel)
    bottom = np.full(n, np.inf)
    np.minimum.at(bottom, part, cells[:, 2] * voxel)
    # footprint columns: distinct (part, x, y) of the voxels
    nx, ny = int(cells[:, 0].max()) + 1, int(cells[:, 1].max()) + 1
    columns = np.unique((part * nx + cells[:, 0]) * ny + cells[:, 1])
    per_part = np.bincount(columns // (nx * ny), minlength=n)
    fill = per_part * voxel**2 / (length * width)
    return {"length": length, "width": width, "top": top, "bottom": bottom, "fill": fill}


def _rules(size: dict[str, np.ndarray]) -> np.ndarray:
    """(P,) uint8 role of each part from its sizes (:func:`_part_sizes`); later rules win."""
    length, width, top, fill = size["length"], size["width"], size["top"], size["fill"]
    role = np.full(len(length), classes.VEGETATION, np.uint8)
    vehicle = (
        _within(top, VEHICLE_TOP_M)
        & _within(length, VEHICLE_LENGTH_M)
        & _within(width, VEHICLE_WIDTH_M)
    )
    role[vehicle] = classes.CAR
    outline = (fill < BUILDING_FILL) | (width < BUILDING_WIDTH_M)
    role[(top > BUILDING_TOP_M) & (length > BUILDING_LENGTH_M) & outline] = classes.BUILDING
    thin = (width <= RAILING_WIDTH_M) & (top <= RAILING_TOP_M)
    role[thin] = classes.RAILING
    small = (length <= SMALL_LENGTH_M) & (width <= SMALL_WIDTH_M)
    role[small] = np.where(top[small] > POLE_TOP_M, classes.POLE, classes.FURNITURE)
    # a small part that does not reach down to the ground is no pole, bin or bench: a sparse
    # LiDAR breaks a tree's crown into such pieces (docs/TUNING.md, sixteenth round)
    role[small & (size["bottom"] > FLOATING_BOTTOM_M)] = classes.VEGETATION
    role[top < LOW_PART_M] = classes.GROUND
    return role


def _within(value: np.ndarray, bounds: tuple[float, float]) -> np.ndarray:
    return (value >= bounds[0]) & (value <= bounds[1])
