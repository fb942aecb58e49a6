"""One ray caster for both the laser scanner and the camera: numba kernels over rays.

Primitives live in a *street frame* (x along the street, y across, z up, metres):

* ``BOX``: axis-aligned box, params ``(xmin, ymin, zmin, xmax, ymax, zmax)``;
* ``CYL``: vertical cylinder with caps, params ``(cx, cy, radius, z0, z1, -)``;
* ``ELL``: axis-aligned ellipsoid, params ``(cx, cy, cz, rx, ry, rz)``.

A uniform 2D grid over x–y lists the primitives whose footprint touches each cell; a ray
walks the cells it crosses (2D DDA, Amanatides & Woo 1987) and tests only their primitives,
stopping once its nearest hit lies before the exit of the current cell. Large primitives
(road, sidewalks, ground) are kept out of the grid and tested once per ray.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

BOX, CYL, ELL = 0, 1, 2
_EPS = 1e-9
_BIG_AREA_M2 = 400.0  # footprints larger than this are tested once per ray, not per cell


@dataclass(frozen=True)
class Grid:
    """Primitives of one epoch of one street, with their x–y acceleration grid.

    kind : (P,) int8; params : (P, 6) float64 street frame metres; big : (B,) int32 indices
    of primitives tested for every ray; cell_start : (nx·ny + 1,) int64 and cell_items :
    (M,) int32 a CSR list of the primitives per cell (row-major, y then x); cell_ztop :
    (nx·ny,) float64 the highest point of any primitive in a cell (rays passing above skip
    it); x0, y0, cell_m, nx, ny the grid geometry; zmin, zmax the vertical extent of
    everything in the grid.
    """

    kind: np.ndarray
    params: np.ndarray
    big: np.ndarray
    cell_start: np.ndarray
    cell_items: np.ndarray
    cell_ztop: np.ndarray
    x0: float
    y0: float
    cell_m: float
    nx: int
    ny: int
    zmin: float
    zmax: float

    def args(self) -> tuple:
        """Positional arguments of the kernels, in their order."""
        return (
            self.kind,
            self.params,
            self.big,
            self.cell_start,
            self.cell_items,
            self.cell_ztop,
            self.x0,
            self.y0,
            self.cell_m,
            self.nx,
            self.ny,
            self.zmin,
            self.zmax,
        )


def footprints(kind: np.ndarray, params: np.ndarray) -> np.ndarray:
    """(P, 6) float64 axis-aligned bounds ``(xmin, ymin, zmin, xmax, ymax, zmax)``."""
    b = np.empty((len(kind), 6))
    p = params
    box, cyl, ell = kind == BOX, kind == CYL, kind == ELL
    b[box] = p[box]
    r = p[cyl, 2]
    b[cyl] = np.column_stack(
        [p[cyl, 0] - r, p[cyl, 1] - r, p[cyl, 3], p[cyl, 0] + r, p[cyl, 1] + r, p[cyl, 4]]
    )
    b[ell, :3] = p[ell, :3] - p[ell, 3:]
    b[ell, 3:] = p[ell, :3] + p[ell, 3:]
    return b


def build_grid(kind: np.ndarray, params: np.ndarray, cell_m: float = 2.0) -> Grid:
    """Bin primitives ``kind`` (P,) int8 / ``params`` (P, 6) into a 2D grid of ``cell_m``."""
    kind = np.ascontiguousarray(kind, dtype=np.int8)
    params = np.ascontiguousarray(params, dtype=np.float64)
    bounds = footprints(kind, params)
    area = (bounds[:, 3] - bounds[:, 0]) * (bounds[:, 4] - bounds[:, 1])
    big = np.flatnonzero(area > _BIG_AREA_M2).astype(np.int32)
    small = np.flatnonzero(area <= _BIG_AREA_M2)
    sb = bounds[small]
    if len(small):
        x0, y0 = math.floor(sb[:, 0].min()) - 1.0, math.floor(sb[:, 1].min()) - 1.0
        nx = int(math.ceil((sb[:, 3].max() - x0) / cell_m)) + 1
        ny = int(math.ceil((sb[:, 4].max() - y0) / cell_m)) + 1
        zmin, zmax = float(sb[:, 2].min()), float(sb[:, 5].max())
    else:
        x0 = y0 = 0.0
        nx = ny = 1
        zmin, zmax = 0.0, 0.0
    ix0 = np.floor((sb[:, 0] - x0) / cell_m).astype(np.int64)
    ix1 = np.floor((sb[:, 3] - x0) / cell_m).astype(np.int64)
    iy0 = np.floor((sb[:, 1] - y0) / cell_m).astype(np.int64)
    iy1 = np.floor((sb[:, 4] - y0) / cell_m).astype(np.int64)
    cell_start, cell_items, ztop = _fill_cells(
        small.astype(np.int32), sb[:, 5].copy(), ix0, ix1, iy0, iy1, nx, ny
    )
    return Grid(
        kind,
        params,
        big,
        cell_start,
        cell_items,
        ztop,
        float(x0),
        float(y0),
        float(cell_m),
        nx,
        ny,
        zmin,
        zmax,
    )


@njit(cache=True)
def _fill_cells(items, top, ix0, ix1, iy0, iy1, nx, ny):  # pragma: no cover - numba
    counts = np.zeros(nx * ny + 1, np.int64)
    ztop = np.full(nx * ny, -np.inf)
    for k in range(len(items)):
        for iy in range(iy0[k], iy1[k] + 1):
            for ix in range(ix0[k], ix1[k] + 1):
                counts[iy * nx + ix + 1] += 1
                ztop[iy * nx + ix] = max(ztop[iy * nx + ix], top[k])
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    out = np.empty(start[-1], np.int32)
    for k in range(len(items)):  # in primitive order, so cell lists are deterministic
        for iy in range(iy0[k], iy1[k] + 1):
            for ix in range(ix0[k], ix1[k] + 1):
                c = iy * nx + ix
                out[fill[c]] = items[k]
                fill[c] += 1
    return start, out, ztop


# --- ray / primitive intersection (nearest t > tmin, or inf) ------------------------------


@njit(cache=True, inline="always")
def _hit_box(ox, oy, oz, dx, dy, dz, p, tmin):  # pragma: no cover - numba
    t0 = -np.inf
    t1 = np.inf
    for a in range(3):
        o = ox if a == 0 else (oy if a == 1 else oz)
        d = dx if a == 0 else (dy if a == 1 else dz)
        lo, hi = p[a], p[a + 3]
        if abs(d) < _EPS:
            if o < lo or o > hi:
                return np.inf
        else:
            ta = (lo - o) / d
            tb = (hi - o) / d
            if ta > tb:
                ta, tb = tb, ta
            if ta > t0:
                t0 = ta
            if tb < t1:
                t1 = tb
    if t0 > t1 or t0 <= tmin:  # a ray starting inside a box does not hit it
        return np.inf
    return t0


@njit(cache=True, inline="always")
def _hit_cyl(ox, oy, oz, dx, dy, dz, p, tmin):  # pragma: no cover - numba
    cx, cy, r, z0, z1 = p[0], p[1], p[2], p[3], p[4]
    best = np.inf
    fx, fy = ox - cx, oy - cy
    a = dx * dx + dy * dy
    if a > _EPS:
        b = fx * dx + fy * dy
        c = fx * fx + fy * fy - r * r
        disc = b * b - a * c
        if disc >= 0.0:
            t = (-b - math.sqrt(disc)) / a
            if t > tmin:
                z = oz + t * dz
                if z0 <= z <= z1:
                    best = t
    if abs(dz) > _EPS:  # caps
        for zc in (z0, z1):
            t = (zc - oz) / dz
            if tmin < t < best:
                x, y = fx + t * dx, fy + t * dy
                if x * x + y * y <= r * r:
                    best = t
    return best


@njit(cache=True, inline="always")
def _hit_ell(ox, oy, oz, dx, dy, dz, p, tmin):  # pragma: no cover - numba
    fx, fy, fz = (ox - p[0]) / p[3], (oy - p[1]) / p[4], (oz - p[2]) / p[5]
    ex, ey, ez = dx / p[3], dy / p[4], dz / p[5]
    a = ex * ex + ey * ey + ez * ez
    b = fx * ex + fy * ey + fz * ez
    c = fx * fx + fy * fy + fz * fz - 1.0
    disc = b * b - a * c
    if disc < 0.0 or c < 0.0:  # miss, or origin inside
        return np.inf
    t = (-b - math.sqrt(disc)) / a
    return t if t > tmin else np.inf


@njit(cache=True, inline="always")
def _hit(k, ox, oy, oz, dx, dy, dz, kind, params, tmin):  # pragma: no cover - numba
    p = params[k]
    if kind[k] == 0:
        return _hit_box(ox, oy, oz, dx, dy, dz, p, tmin)
    if kind[k] == 1:
        return _hit_cyl(ox, oy, oz, dx, dy, dz, p, tmin)
    return _hit_ell(ox, oy, oz, dx, dy, dz, p, tmin)


@njit(cache=True)
def normal_at(k, x, y, z, dx, dy, dz, kind, params):  # pragma: no cover - numba
    """Unit outward normal of primitive ``k`` at surface point (x, y, z), facing the ray."""
    p = params[k]
    if kind[k] == 0:
        # the face whose plane is nearest to the point (relative to the box size)
        best, nx, ny, nz = np.inf, 0.0, 0.0, 1.0
        for a in range(3):
            c = x if a == 0 else (y if a == 1 else z)
            for s in range(2):
                dist = abs(c - p[a + 3 * s])
                if dist < best:
                    best = dist
                    sign = -1.0 if s == 0 else 1.0
                    nx = sign if a == 0 else 0.0
                    ny = sign if a == 1 else 0.0
                    nz = sign if a == 2 else 0.0
        return nx, ny, nz
    if kind[k] == 1:
        if abs(z - p[4]) < 1e-6:
            return 0.0, 0.0, 1.0
        if abs(z - p[3]) < 1e-6:
            return 0.0, 0.0, -1.0
        nx, ny = x - p[0], y - p[1]
        n = math.sqrt(nx * nx + ny * ny) + 1e-12
        return nx / n, ny / n, 0.0
    nx = (x - p[0]) / (p[3] * p[3])
    ny = (y - p[1]) / (p[4] * p[4])
    nz = (z - p[2]) / (p[5] * p[5])
    n = math.sqrt(nx * nx + ny * ny + nz * nz) + 1e-12
    return nx / n, ny / n, nz / n


@njit(cache=True)
def trace(
    ox,
    oy,
    oz,
    dx,
    dy,
    dz,
    tmin,
    tmax,
    any_hit,
    kind,
    params,
    big,
    cell_start,
    cell_items,
    cell_ztop,
    x0,
    y0,
    cell_m,
    nx,
    ny,
    zmin,
    zmax,
):  # pragma: no cover - numba
    """Nearest primitive hit by the ray ``o + t d`` with ``tmin < t < tmax``.

    ``d`` need not be unit length; ``t`` is in its units. Returns (t, k): k = -1 for a miss
    (t = tmax). With ``any_hit`` it returns at the first hit found (shadow rays).
    """
    best_t = tmax
    best_k = -1
    for j in range(len(big)):
        k = big[j]
        if dz >= 0.0 and kind[k] == 0 and oz > params[k, 5]:
            continue  # a ray rising from above a (ground) box cannot hit it
        t = _hit(k, ox, oy, oz, dx, dy, dz, kind, params, tmin)
        if t < best_t:
            best_t = t
            best_k = big[j]
            if any_hit:
                return best_t, best_k
    # clip the ray to the grid's box
    gx1, gy1 = x0 + nx * cell_m, y0 + ny * cell_m
    t0, t1 = tmin, best_t
    for a in range(3):
        o = ox if a == 0 else (oy if a == 1 else oz)
        d = dx if a == 0 else (dy if a == 1 else dz)
        lo = x0 if a == 0 else (y0 if a == 1 else zmin)
        hi = gx1 if a == 0 else (gy1 if a == 1 else zmax)
        if abs(d) < _EPS:
            if o < lo or o > hi:
                return best_t, best_k
        else:
            ta, tb = (lo - o) / d, (hi - o) / d
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
    if t0 > t1:
        return best_t, best_k
    px, py = ox + t0 * dx, oy + t0 * dy
    ix = min(max(int((px - x0) / cell_m), 0), nx - 1)
    iy = min(max(int((py - y0) / cell_m), 0), ny - 1)
    step_x = 1 if dx > 0 else -1
    step_y = 1 if dy > 0 else -1
    if abs(dx) > _EPS:
        next_x = x0 + (ix + (1 if dx > 0 else 0)) * cell_m
        tx = (next_x - ox) / dx
        dtx = cell_m / abs(dx)
    else:
        tx, dtx = np.inf, np.inf
    if abs(dy) > _EPS:
        next_y = y0 + (iy + (1 if dy > 0 else 0)) * cell_m
        ty = (next_y - oy) / dy
        dty = cell_m / abs(dy)
    else:
        ty, dty = np.inf, np.inf
    t_enter = t0
    while True:
        c = iy * nx + ix
        t_exit = min(tx, ty)
        # skip the cell when the ray passes above everything in it
        z_low = oz + (t_enter if dz > 0 else min(t_exit, t1)) * dz
        if z_low > cell_ztop[c]:
            j0 = cell_start[c + 1]
        else:
            j0 = cell_start[c]
        for j in range(j0, cell_start[c + 1]):
            k = cell_items[j]
            t = _hit(k, ox, oy, oz, dx, dy, dz, kind, params, tmin)
            if t < best_t:
                best_t = t
                best_k = k
                if any_hit:
                    return best_t, best_k
        if best_t <= t_exit or t_exit > t1:
            break
        t_enter = t_exit
        if tx < ty:
            ix += step_x
            tx += dtx
            if ix < 0 or ix >= nx:
                break
        else:
            iy += step_y
            ty += dty
            if iy < 0 or iy >= ny:
                break
    return best_t, best_k


@njit(cache=True, parallel=True)
def cast_kernel(
    origins,
    dirs,
    tmax,
    kind,
    params,
    big,
    cell_start,
    cell_items,
    cell_ztop,
    x0,
    y0,
    cell_m,
    nx,
    ny,
    zmin,
    zmax,
):  # pragma: no cover - numba
    """Nearest hits of rays ``origins`` (N, 3) + t ``dirs`` (N, 3): (t (N,), k (N,), n (N, 3))."""
    n = origins.shape[0]
    t_out = np.full(n, np.inf)
    k_out = np.full(n, -1, np.int32)
    n_out = np.zeros((n, 3), np.float32)
    for i in prange(n):
        ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        t, k = trace(
            ox,
            oy,
            oz,
            dx,
            dy,
            dz,
            1e-6,
            tmax,
            False,
            kind,
            params,
            big,
            cell_start,
            cell_items,
            cell_ztop,
            x0,
            y0,
            cell_m,
            nx,
            ny,
            zmin,
            zmax,
        )
        if k >= 0:
            t_out[i] = t
            k_out[i] = k
            a, b, c = normal_at(k, ox + t * dx, oy + t * dy, oz + t * dz, dx, dy, dz, kind, params)
            n_out[i, 0], n_out[i, 1], n_out[i, 2] = a, b, c
    return t_out, k_out, n_out


def cast(grid: Grid, origins: np.ndarray, dirs: np.ndarray, tmax: float = np.inf):
    """Nearest hits of rays against ``grid``'s primitives (street frame).

    origins, dirs : (N, 3) float64 metres / direction (any length; t is in its units).
    Returns t (N,) float64 (inf for a miss), k (N,) int32 primitive index (−1 for a miss),
    normals (N, 3) float32 unit outward normals.
    """
    origins = np.ascontiguousarray(origins, dtype=np.float64)
    dirs = np.ascontiguousarray(dirs, dtype=np.float64)
    return cast_kernel(origins, dirs, float(tmax), *grid.args())
