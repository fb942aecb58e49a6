"""Procedural materials: albedo (linear RGB reflectance in [0, 1]) at a surface point.

Each primitive carries a material code, a base colour (linear RGB) and four texture
parameters whose meaning depends on the material (see the table below). Textures are
functions of the street-frame hit point (metres) and normal, built from a hashed value
noise, so they are deterministic and need no image files.

=========  ==========================================================================
material   tex parameters
=========  ==========================================================================
FACADE     floor height m, bay width m, variant (0 plaster, 1 brick), seed
SIGN       facing (+1: face towards +y, −1: towards −y), symbol variant, seed, –
BOARD      facing, seed, –, –
FOLIAGE    seed, –, –, –
PAINT      – (uniform single-colour paint, no texture: the base colour everywhere)
others     seed in tex[0] where noise needs one
=========  ==========================================================================
"""

from __future__ import annotations

import math

from numba import njit

ASPHALT, PAVING, CONCRETE, FACADE, ROOF, FOLIAGE, BARK, METAL = 0, 1, 2, 3, 4, 5, 6, 7
SIGN, BOARD, WOOD, CARPAINT, CABIN, RUBBER, CLOTH, GRASS, SKIN, LAMP = (
    8,
    9,
    10,
    11,
    12,
    13,
    14,
    15,
    16,
    17,
)
PAINT = 18  # plain paint: albedo is the base colour, with no texture at all


def srgb_to_linear(c: tuple[float, float, float]) -> tuple[float, float, float]:
    """8-bit-style sRGB triple in [0, 1] → linear reflectance (gamma 2.2 approximation)."""
    return (c[0] ** 2.2, c[1] ** 2.2, c[2] ** 2.2)


@njit(cache=True, inline="always")
def _hash(ix, iy, iz, s):  # pragma: no cover - numba
    """Uniform [0, 1] value for integer lattice point (ix, iy, iz) and seed s."""
    h = (ix * 374761393 + iy * 668265263 + iz * 1440662683 + s * 2246822519) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return h / 4294967295.0


@njit(cache=True)
def vnoise(x, y, z, s):  # pragma: no cover - numba
    """Smooth value noise in [0, 1] at (x, y, z) (lattice spacing 1), seed s."""
    fx, fy, fz = math.floor(x), math.floor(y), math.floor(z)
    ix, iy, iz = int(fx), int(fy), int(fz)
    ux, uy, uz = x - fx, y - fy, z - fz
    ux = ux * ux * (3.0 - 2.0 * ux)
    uy = uy * uy * (3.0 - 2.0 * uy)
    uz = uz * uz * (3.0 - 2.0 * uz)
    a = _hash(ix, iy, iz, s) + ux * (_hash(ix + 1, iy, iz, s) - _hash(ix, iy, iz, s))
    b = _hash(ix, iy + 1, iz, s) + ux * (_hash(ix + 1, iy + 1, iz, s) - _hash(ix, iy + 1, iz, s))
    c = _hash(ix, iy, iz + 1, s) + ux * (_hash(ix + 1, iy, iz + 1, s) - _hash(ix, iy, iz + 1, s))
    d = _hash(ix, iy + 1, iz + 1, s) + ux * (
        _hash(ix + 1, iy + 1, iz + 1, s) - _hash(ix, iy + 1, iz + 1, s)
    )
    ab = a + uy * (b - a)
    cd = c + uy * (d - c)
    return ab + uz * (cd - ab)


@njit(cache=True)
def fbm(x, y, z, s, octaves):  # pragma: no cover - numba
    """Fractal sum of ``octaves`` value-noise layers, in [0, 1]."""
    total, amp, norm, f = 0.0, 1.0, 0.0, 1.0
    for o in range(octaves):
        total += amp * vnoise(x * f, y * f, z * f, s + 17 * o)
        norm += amp
        amp *= 0.5
        f *= 2.03
    return total / norm


@njit(cache=True)
def _facade(p, tex, cr, cg, cb, x, y, z, nx, ny, nz):  # pragma: no cover - numba
    if nz > 0.5:  # roof or cornice top
        g = 0.05 + 0.03 * vnoise(x * 3.0, y * 3.0, 0.0, 11)
        return g, g, g * 1.05
    floor_h, bay_w, variant, seed = tex[0], tex[1], tex[2], int(tex[3])
    u = x if abs(ny) >= abs(nx) else y
    v = z - p[2]  # height above the building's base
    n = fbm(u * 1.3, v * 1.3, seed * 0.37, seed, 3)
    # weathering: vertical rain streaks and a darker band of dirt near the ground
    streak = vnoise(u * 1.5, v * 0.08, seed * 0.11, seed + 5)
    k = (0.85 + 0.3 * n) * (0.9 + 0.12 * streak) * (0.85 + 0.15 * min(v / 1.2, 1.0))
    r, g, b = cr * k, cg * k, cb * k
    if variant > 0.5:  # brick bond with mortar joints and per-brick tone
        row = math.floor(v / 0.075)
        shift = 0.12 if int(row) % 2 == 0 else 0.0
        col = math.floor((u + shift) / 0.24)
        fu = (u + shift) - col * 0.24
        fv = v - row * 0.075
        if fu < 0.012 or fv < 0.012:
            r, g, b = 0.30, 0.28, 0.25
        else:
            k = 0.8 + 0.4 * _hash(int(col), int(row), 3, seed)
            r, g, b = r * k, g * k, b * k
    f = math.floor(v / floor_h)
    fv = v - f * floor_h
    bay = math.floor((u + seed * 0.731) / bay_w)
    fu = (u + seed * 0.731) - bay * bay_w
    if fv > floor_h - 0.12 and f >= 1:  # string course between floors
        return r * 0.75, g * 0.75, b * 0.75
    if f < 1:  # ground floor: shop windows and doors
        door = _hash(int(bay), 0, 7, seed) < 0.3
        if door:
            if abs(fu - 0.5 * bay_w) < 0.55 and fv < 2.25:
                if abs(fu - 0.5 * bay_w) > 0.48 or fv > 2.18:
                    return 0.6, 0.6, 0.58
                k = _hash(int(bay), 1, 7, seed)
                return 0.08 + 0.1 * k, 0.05 + 0.05 * k, 0.03
            return r, g, b
        x0, x1, y0, y1 = 0.35, bay_w - 0.35, 0.55, min(2.7, floor_h - 0.4)
    else:
        ww = min(1.3, 0.5 * bay_w)
        x0, x1, y0, y1 = 0.5 * (bay_w - ww), 0.5 * (bay_w + ww), 0.9, min(2.45, floor_h - 0.5)
    if x0 <= fu <= x1 and y0 <= fv <= y1:
        if fu - x0 < 0.07 or x1 - fu < 0.07 or fv - y0 < 0.07 or y1 - fv < 0.07:
            return 0.75, 0.75, 0.72  # frame
        if abs(fu - 0.5 * (x0 + x1)) < 0.03 and f >= 1:
            return 0.7, 0.7, 0.68  # mullion
        k = _hash(int(bay), int(f), 5, seed)
        t = (fv - y0) / (y1 - y0)
        if k < 0.3:  # curtain
            return 0.45 * (0.7 + 0.3 * t), 0.4 * (0.7 + 0.3 * t), 0.33 * (0.7 + 0.3 * t)
        sky = 0.04 + 0.1 * t * k
        return sky * 0.8, sky * 0.95, sky * 1.3
    if f >= 1 and x0 - 0.1 <= fu <= x1 + 0.1 and y0 - 0.12 <= fv < y0:
        return 0.6, 0.6, 0.58  # sill
    return r, g, b


@njit(cache=True)
def _planar_face(p, facing, x, z):  # pragma: no cover - numba
    """Face coordinates (s, t) in [0, 1] of a thin box facing ±y: s along x, t up."""
    s = (x - p[0]) / max(p[3] - p[0], 1e-6)
    t = (z - p[2]) / max(p[5] - p[2], 1e-6)
    if facing < 0:
        s = 1.0 - s
    return s, t


@njit(cache=True)
def albedo(mat, p, tex, cr, cg, cb, x, y, z, nx, ny, nz):  # pragma: no cover - numba
    """Linear RGB albedo of material ``mat`` at street-frame point (x, y, z), normal n.

    ``p`` (6,) the primitive's parameters, ``tex`` (4,) its texture parameters, (cr, cg,
    cb) its base colour.
    """
    if mat == ASPHALT:
        n = 0.6 * vnoise(x * 25.0, y * 25.0, 0.0, 1) + 0.4 * fbm(x * 0.4, y * 0.4, 0.0, 2, 3)
        g = 0.045 + 0.035 * n
        hw = tex[1]
        if hw > 0.0:
            dash = (x - 9.0 * math.floor(x / 9.0)) < 4.0
            if (abs(y) < 0.07 and dash) or abs(abs(y) - (hw - 0.35)) < 0.07:
                g = 0.55 + 0.1 * n
        return g, g, g * 1.04
    if mat == PAVING:
        tile = 0.3
        ix, iy = math.floor(x / tile), math.floor(y / tile)
        fu, fv = x - ix * tile, y - iy * tile
        if fu < 0.012 or fv < 0.012:
            return cr * 0.45, cg * 0.45, cb * 0.45
        k = 0.82 + 0.3 * _hash(int(ix), int(iy), 9, 4) + 0.15 * vnoise(x * 30, y * 30, 0.0, 5)
        return cr * k, cg * k, cb * k
    if mat == RUBBER and abs(ny) > 0.5:  # tyre seen from the side: rim and hub
        du = x - 0.5 * (p[0] + p[3])
        dv = z - 0.5 * (p[2] + p[5])
        rr = math.sqrt(du * du + dv * dv)
        if rr < 0.19:
            g = 0.35 + 0.1 * (rr < 0.05)
            return g, g, g * 1.02
    if mat == CONCRETE or mat == METAL or mat == RUBBER or mat == CLOTH or mat == SKIN:
        n = vnoise(x * 12.0, y * 12.0, z * 12.0, 6)
        k = 0.9 + 0.2 * n
        if mat == CLOTH and z < p[3] + 0.48 * (p[4] - p[3]):  # trousers below the waist
            return 0.05 * k, 0.06 * k, 0.09 * k
        return cr * k, cg * k, cb * k
    if mat == FACADE:
        return _facade(p, tex, cr, cg, cb, x, y, z, nx, ny, nz)
    if mat == ROOF:
        g = 0.05 + 0.03 * vnoise(x * 2.0, y * 2.0, z, 8)
        return g, g * 0.95, g * 0.9
    if mat == FOLIAGE:
        s = int(tex[0])
        n = fbm(x * 7.0, y * 7.0, z * 7.0, s, 3)
        m = vnoise(x * 1.2, y * 1.2, z * 1.2, s + 3)
        k = 0.35 + 1.1 * n * n
        return cr * k * (0.8 + 0.4 * m), cg * k, cb * k * (1.2 - 0.4 * m)
    if mat == BARK:
        n = fbm(x * 20.0, y * 20.0, z * 3.0, 12, 2)
        return cr * (0.6 + 0.6 * n), cg * (0.6 + 0.6 * n), cb * (0.6 + 0.6 * n)
    if mat == SIGN or mat == BOARD:
        facing = tex[0]
        if ny * facing <= 0.5:  # back and edges
            return 0.25, 0.25, 0.26
        s, t = _planar_face(p, facing, x, z)
        border = 0.06
        if s < border or s > 1 - border or t < border or t > 1 - border:
            return (0.7, 0.7, 0.7) if mat == SIGN else (0.05, 0.05, 0.05)
        if mat == SIGN:
            variant = int(tex[1])
            if variant == 0 and abs(t - 0.5) < 0.12 and abs(s - 0.5) < 0.33:
                return 0.8, 0.8, 0.8
            if variant == 1 and (s - 0.5) ** 2 + (t - 0.5) ** 2 < 0.07:
                return 0.8, 0.8, 0.8
            if variant == 2 and abs((s - 0.5) - (t - 0.5)) < 0.08:
                return 0.02, 0.02, 0.02
            return cr, cg, cb
        seed = int(tex[1])
        cell = int(math.floor(s * 3.0)) + 3 * int(math.floor(t * 2.0))
        h = _hash(cell, 0, 1, seed)
        if t < 0.35 and (int(math.floor(t * 40.0)) % 3 == 0) and 0.1 < s < 0.9:
            return 0.9, 0.9, 0.9  # "text" lines
        if h < 0.33:
            return cr, cg, cb
        if h < 0.66:
            return cb * 0.8 + 0.1, cr * 0.8, cg * 0.6
        return 0.8 * _hash(cell, 1, 1, seed), 0.6 * _hash(cell, 2, 1, seed), 0.5
    if mat == WOOD:
        n = (
            vnoise(x * 3.0, y * 3.0, z * 60.0, 13)
            if abs(nz) < 0.5
            else vnoise(x * 2.0, y * 40.0, z * 2.0, 13)
        )
        return cr * (0.7 + 0.5 * n), cg * (0.7 + 0.5 * n), cb * (0.7 + 0.5 * n)
    if mat == CARPAINT:
        k = 1.0 + 0.25 * max(nz, 0.0)
        return cr * k, cg * k, cb * k
    if mat == CABIN:
        if nz > 0.5:
            return cr, cg, cb
        along = x if abs(ny) > abs(nx) else y
        lo = p[0] if abs(ny) > abs(nx) else p[1]
        hi = p[3] if abs(ny) > abs(nx) else p[4]
        if along - lo < 0.12 or hi - along < 0.12 or z > p[5] - 0.06:
            return cr, cg, cb
        t = (z - p[2]) / (p[5] - p[2])
        return 0.03 + 0.06 * t, 0.035 + 0.07 * t, 0.045 + 0.09 * t
    if mat == GRASS:
        n = fbm(x * 6.0, y * 6.0, 0.0, 14, 3)
        return cr * (0.6 + 0.8 * n), cg * (0.6 + 0.8 * n), cb * (0.6 + 0.8 * n)
    if mat == LAMP:
        return 0.9, 0.9, 0.85
    return cr, cg, cb  # PAINT and any material without a texture
