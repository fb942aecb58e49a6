"""Camera rendering: depth and object ids for any view, and shaded images.

A pixel's ray is ``C + t · Rᵀ [x_n, y_n, 1]`` with ``(x_n, y_n)`` its undistorted normalised
coordinates, so the ray parameter ``t`` *is* the depth (camera z, metres) of the hit.
Shading is Lambert under a sun (with cast shadows, traced by the same kernel) plus a sky
ambient term; the sky itself is a vertical gradient with soft clouds.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from streetcd.geometry.camera import pixel_grid, pixel_rays
from streetcd.synth import materials as M
from streetcd.synth.raycast import normal_at, trace
from streetcd.synth.scene import EPOCH2, Scene, Street
from streetcd.types import View

SUN_IRRADIANCE = 2.2  # relative to the sky term; a sunny day
SKY_IRRADIANCE = 0.55


def normalised_coords(intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised pixel coordinates: xn, yn (H, W) float64 (maybe broadcast)."""
    h, w = intrinsics.height, intrinsics.width
    if not intrinsics.has_distortion:
        xn = (np.arange(w, dtype=np.float64) - intrinsics.cx) / intrinsics.fx
        yn = (np.arange(h, dtype=np.float64) - intrinsics.cy) / intrinsics.fy
        return np.broadcast_to(xn[None, :], (h, w)), np.broadcast_to(yn[:, None], (h, w))
    rays = pixel_rays(pixel_grid(h, w), intrinsics)
    return rays[:, 0].reshape(h, w), rays[:, 1].reshape(h, w)


def camera_in_street(view_local: View, street: Street) -> tuple[np.ndarray, np.ndarray]:
    """(cam→street rotation (3, 3), camera centre (3,) street frame) for a local-frame view."""
    R = view_local.pose.R @ street.rotation  # world(street)→camera
    c = street.to_street(view_local.pose.center[None])[0]
    return np.ascontiguousarray(R.T), c


@njit(cache=True, parallel=True)
def _camera_cast(
    xn,
    yn,
    want,
    A,
    c,
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
    h, w = xn.shape
    depth = np.full((h, w), np.inf, np.float32)
    prim = np.full((h, w), -1, np.int32)
    normal = np.zeros((h, w, 3), np.float32)
    use_want = want.shape[0] == h
    for v in prange(h):
        for u in range(w):
            if use_want and want[v, u] == 0:
                continue
            a, b = xn[v, u], yn[v, u]
            dx = A[0, 0] * a + A[0, 1] * b + A[0, 2]
            dy = A[1, 0] * a + A[1, 1] * b + A[1, 2]
            dz = A[2, 0] * a + A[2, 1] * b + A[2, 2]
            t, k = trace(
                c[0],
                c[1],
                c[2],
                dx,
                dy,
                dz,
                1e-6,
                1e4,
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
                depth[v, u] = t
                prim[v, u] = k
                n0, n1, n2 = normal_at(
                    k, c[0] + t * dx, c[1] + t * dy, c[2] + t * dz, dx, dy, dz, kind, params
                )
                normal[v, u, 0], normal[v, u, 1], normal[v, u, 2] = n0, n1, n2
    return depth, prim, normal


VIEW_RANGE_M = 100.0  # a camera sees only the streets whose extent lies within this range


def _distance_2d(point: np.ndarray, street: Street) -> float:
    """Horizontal distance (m) from a local-frame point to a street's bounding box."""
    lo, hi = street.bounds_local[:2], street.bounds_local[3:5]
    d = np.maximum(np.maximum(lo - point[:2], point[:2] - hi), 0.0)
    return float(np.hypot(*d))


def cast_view(scene: Scene, view_local: View, epoch: int, want: np.ndarray | None = None):
    """Nearest hits of a view's pixel rays over all streets of ``scene`` in one epoch.

    view_local : a view whose pose is in the scene's local frame.
    want : optional (H, W) bool; only those pixels are traced (others report no hit).
    Returns depth (H, W) float32 metres (inf = nothing), street (H, W) int8 (−1 = none),
    prim (H, W) int32 row in that street's primitive arrays (−1 = none), normal (H, W, 3)
    float32 in that street's frame.
    """
    intr = view_local.intrinsics
    xn, yn = normalised_coords(intr)
    w = np.zeros((0, 0), np.uint8) if want is None else np.ascontiguousarray(want, np.uint8)
    near = [
        s
        for s, st in enumerate(scene.streets)
        if _distance_2d(view_local.pose.center, st) <= VIEW_RANGE_M
    ]
    if len(near) == 1:  # the common case: no merging
        street = scene.streets[near[0]]
        A, c = camera_in_street(view_local, street)
        d, k, n = _camera_cast(xn, yn, w, A, c, *street.grids[epoch].args())
        hit = k >= 0
        k[hit] = street.index[epoch][k[hit]]
        return d, np.where(hit, near[0], -1).astype(np.int8), k, n
    best = np.full((intr.height, intr.width), np.inf, np.float32)
    street_of = np.full(best.shape, -1, np.int8)
    prim = np.full(best.shape, -1, np.int32)
    normal = np.zeros((*best.shape, 3), np.float32)
    for s in near:
        street = scene.streets[s]
        A, c = camera_in_street(view_local, street)
        grid = street.grids[epoch]
        d, k, n = _camera_cast(xn, yn, w, A, c, *grid.args())
        closer = d < best
        best[closer] = d[closer]
        street_of[closer] = s
        prim[closer] = street.index[epoch][k[closer]]
        normal[closer] = n[closer]
    return best, street_of, prim, normal


def render_depth(scene: Scene, view: View, epoch: int = EPOCH2) -> tuple[np.ndarray, np.ndarray]:
    """Depth and object id of every pixel of ``view`` in ``epoch`` (1: scan, 2: images).

    view : pose in the CRS (as written to / read from the pose files).
    Returns depth (H, W) float32 camera z in metres (NaN where the ray meets nothing) and
    ids (H, W) int32 object ids of ``scene.objects`` (0 where nothing).
    """
    local = view.local(scene.origin)
    depth, street_of, prim, _ = cast_view(scene, local, epoch)
    ids = np.zeros(depth.shape, np.int32)
    for s, street in enumerate(scene.streets):
        m = street_of == s
        ids[m] = street.obj[prim[m]]
    depth = np.where(np.isfinite(depth), depth, np.nan).astype(np.float32)
    return depth, ids


# --- shading ------------------------------------------------------------------------------


@njit(cache=True)
def sky_colour(dx, dy, dz):  # pragma: no cover - numba
    """Linear RGB of the sky in direction d (street or local frame: z is up)."""
    n = math.sqrt(dx * dx + dy * dy + dz * dz)
    e = max(dz / n, 0.0)
    t = math.sqrt(e)
    r = 0.62 * (1 - t) + 0.16 * t
    g = 0.70 * (1 - t) + 0.30 * t
    b = 0.82 * (1 - t) + 0.70 * t
    if e > 0.02:  # soft clouds on a plane 1 km up
        s = 1000.0 / dz * n
        cl = M.fbm(dx / n * s * 0.004, dy / n * s * 0.004, 0.0, 77, 4)
        k = min(max((cl - 0.5) * 3.0, 0.0), 1.0) * min(e * 8.0, 1.0)
        r, g, b = r + (0.85 - r) * k, g + (0.85 - g) * k, b + (0.86 - b) * k
    return r, g, b


@njit(cache=True, parallel=True)
def _shade(
    depth,
    owner,
    me,
    sky_too,
    prim,
    normal,
    xn,
    yn,
    A,
    c,
    sun,
    mat,
    color,
    tex,
    sparams,
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
    shadows,
):  # pragma: no cover - numba
    h, w = depth.shape
    out = np.zeros((h, w, 3), np.float32)
    for v in prange(h):
        for u in range(w):
            o = owner[v, u]
            a, b = xn[v, u], yn[v, u]
            dx = A[0, 0] * a + A[0, 1] * b + A[0, 2]
            dy = A[1, 0] * a + A[1, 1] * b + A[1, 2]
            dz = A[2, 0] * a + A[2, 1] * b + A[2, 2]
            if o < 0:
                if sky_too:
                    r, g, bb = sky_colour(dx, dy, dz)
                    out[v, u, 0], out[v, u, 1], out[v, u, 2] = r, g, bb
                continue
            if o != me:
                continue
            k = prim[v, u]
            t = depth[v, u]
            px, py, pz = c[0] + t * dx, c[1] + t * dy, c[2] + t * dz
            n0, n1, n2 = normal[v, u, 0], normal[v, u, 1], normal[v, u, 2]
            m = mat[k]
            r, g, bb = M.albedo(
                m, sparams[k], tex[k], color[k, 0], color[k, 1], color[k, 2], px, py, pz, n0, n1, n2
            )
            if m == M.FOLIAGE:  # leafy shading: perturb the normal with noise
                s = int(tex[k, 0])
                n0 += 1.4 * (M.vnoise(px * 9, py * 9, pz * 9, s + 1) - 0.5)
                n1 += 1.4 * (M.vnoise(px * 9, py * 9, pz * 9, s + 2) - 0.5)
                n2 += 1.4 * (M.vnoise(px * 9, py * 9, pz * 9, s + 3) - 0.5)
                nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2) + 1e-9
                n0, n1, n2 = n0 / nn, n1 / nn, n2 / nn
            cos_s = n0 * sun[0] + n1 * sun[1] + n2 * sun[2]
            lit = 0.0
            if cos_s > 0.0:
                lit = cos_s
                if shadows:
                    e = 0.01 + 1e-4 * t
                    gn0, gn1, gn2 = normal[v, u, 0], normal[v, u, 1], normal[v, u, 2]
                    _, hit = trace(
                        px + e * gn0,
                        py + e * gn1,
                        pz + e * gn2,
                        sun[0],
                        sun[1],
                        sun[2],
                        1e-4,
                        500.0,
                        True,
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
                    if hit >= 0:
                        lit = 0.0
            sky = SKY_IRRADIANCE * (0.7 + 0.3 * n2)
            # darker near the ground where the sky is half hidden (cheap ambient occlusion)
            sky *= 0.75 + 0.25 * min(max((pz - 0.1) / 1.5, 0.0), 1.0)
            ir = SUN_IRRADIANCE * lit * 1.0 + sky * 0.92
            ig = SUN_IRRADIANCE * lit * 0.96 + sky * 0.97
            ib = SUN_IRRADIANCE * lit * 0.88 + sky * 1.1
            out[v, u, 0], out[v, u, 1], out[v, u, 2] = r * ir, g * ig, bb * ib
    return out


def shade_view(
    scene: Scene, view_local: View, depth, street_of, prim, normal, *, shadows: bool = True
) -> np.ndarray:
    """Linear radiance (H, W, 3) float32 of a view from :func:`cast_view`'s epoch-2 hits."""
    intr = view_local.intrinsics
    xn, yn = normalised_coords(intr)
    out = np.zeros((intr.height, intr.width, 3), np.float32)
    owners = sorted(set(np.unique(street_of).tolist()) - {-1}) or [0]
    for s in owners:  # the first owner also paints the sky
        street = scene.streets[s]
        A, c = camera_in_street(view_local, street)
        sun = street.rotation.T @ scene.sun
        grid = street.grids[EPOCH2]
        # shadow rays use epoch-2 grid numbering; shading needs street rows: both given
        args = (
            depth,
            street_of,
            s,
            s == owners[0],
            prim,
            normal,
            xn,
            yn,
            A,
            c,
            sun,
            street.mat,
            street.color,
            street.tex,
            street.params,
            *grid.args(),
            shadows,
        )
        img = _shade(*args)
        out += img
    return out


@njit(cache=True, parallel=True)
def point_albedo(xyz, normal, prim, mat, color, tex, params):  # pragma: no cover - numba
    """Albedo (N, 3) float32 of surface points ``xyz`` (N, 3) street frame on ``prim``."""
    n = xyz.shape[0]
    out = np.empty((n, 3), np.float32)
    for i in prange(n):
        k = prim[i]
        r, g, b = M.albedo(
            mat[k],
            params[k],
            tex[k],
            color[k, 0],
            color[k, 1],
            color[k, 2],
            xyz[i, 0],
            xyz[i, 1],
            xyz[i, 2],
            normal[i, 0],
            normal[i, 1],
            normal[i, 2],
        )
        out[i, 0], out[i, 1], out[i, 2] = r, g, b
    return out
