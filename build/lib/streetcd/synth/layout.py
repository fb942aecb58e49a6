"""The content of one synthetic street: ground, buildings, furniture, changes, disturbances.

Street frame (metres): x along the street, y across (the *far* side, which the camera strip
looks at, is +y; the cameras walk the near sidewalk at −y), z up from the road surface.

Three independent random streams (spawned from the street's generator) drive the base
street, the changes and the disturbances, so the same seed gives the same base street
with or without changes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from streetcd import classes as C
from streetcd.synth import materials as M
from streetcd.synth.scene import BOTH, EPOCH1, EPOCH2, SceneBuilder

CURB_H = 0.12
FACADE_COLOURS = [  # sRGB plaster / brick tones
    (0.86, 0.80, 0.68),
    (0.80, 0.74, 0.62),
    (0.75, 0.75, 0.72),
    (0.90, 0.84, 0.60),
    (0.72, 0.45, 0.33),
    (0.62, 0.36, 0.28),
    (0.85, 0.70, 0.60),
    (0.70, 0.74, 0.78),
    (0.93, 0.90, 0.84),
    (0.66, 0.62, 0.52),
]
CAR_COLOURS = [
    (0.75, 0.75, 0.76),
    (0.1, 0.1, 0.11),
    (0.6, 0.05, 0.05),
    (0.15, 0.25, 0.5),
    (0.9, 0.9, 0.9),
    (0.35, 0.37, 0.4),
    (0.55, 0.5, 0.35),
    (0.1, 0.3, 0.15),
]
SIGN_COLOURS = [(0.05, 0.25, 0.65), (0.75, 0.08, 0.08), (0.95, 0.75, 0.05), (0.05, 0.45, 0.2)]
GREENS = [(0.25, 0.42, 0.12), (0.18, 0.35, 0.12), (0.32, 0.45, 0.15), (0.2, 0.38, 0.2)]
# uniform paints of plain streets (sRGB): municipal greys, greens, white, black, ochre, blue, red
PAINTS = [
    (0.45, 0.47, 0.48),
    (0.2, 0.25, 0.22),
    (0.85, 0.85, 0.82),
    (0.1, 0.1, 0.11),
    (0.6, 0.45, 0.1),
    (0.15, 0.25, 0.5),
    (0.7, 0.1, 0.08),
    (0.62, 0.6, 0.55),
]
PAINTED_TYPES = ("pole", "sign", "board", "bin", "bench", "railing")


def lin(c: tuple[float, float, float]) -> tuple[float, float, float]:
    return M.srgb_to_linear(c)


@dataclass
class Lane:
    """Occupied x-intervals of one lane of the sidewalk, to keep objects apart."""

    lo: float
    hi: float
    taken: list[tuple[float, float]] = field(default_factory=list)

    def free(self, x0: float, x1: float, gap: float = 0.6) -> bool:
        if x0 < self.lo or x1 > self.hi:
            return False
        return all(x1 + gap <= a or x0 - gap >= b for a, b in self.taken)

    def take(self, x0: float, x1: float) -> None:
        self.taken.append((x0, x1))

    def place(self, x: float, half: float, gap: float = 0.6) -> bool:
        if self.free(x - half, x + half, gap):
            self.take(x - half, x + half)
            return True
        return False


@dataclass
class StreetLayout:
    """Cross-section of a street and where things go (all metres, street frame)."""

    length: float
    road_half: float
    sidewalk: float
    setback_far: float
    setback_near: float

    @property
    def far_curb_y(self) -> float:
        return self.road_half + 0.55

    @property
    def far_mid_y(self) -> float:
        return self.road_half + 0.6 * self.sidewalk

    @property
    def far_line_y(self) -> float:  # property line between sidewalk and front yard
        return self.road_half + self.sidewalk + 0.4

    @property
    def far_facade_y(self) -> float:
        return self.road_half + self.sidewalk + self.setback_far

    @property
    def near_facade_y(self) -> float:
        return -(self.road_half + self.sidewalk + self.setback_near)

    @property
    def camera_y(self) -> float:
        return -(self.road_half + 0.65 * self.sidewalk)

    @property
    def scanner_y(self) -> float:
        return -0.5 * self.road_half

    def as_dict(self) -> dict[str, Any]:
        return {
            "length_m": self.length,
            "road_half_width_m": self.road_half,
            "sidewalk_width_m": self.sidewalk,
            "far_facade_y_m": self.far_facade_y,
            "near_facade_y_m": self.near_facade_y,
            "camera_y_m": self.camera_y,
            "scanner_y_m": self.scanner_y,
            "curb_height_m": CURB_H,
        }


# --- objects ----------------------------------------------------------------------------


def street_light(b: SceneBuilder, x: float, y: float, side: float, epochs: int, rng) -> int:
    """Light pole at (x, y); ``side`` = +1 on the far side (arm reaches towards −y)."""
    oid = b.new_object("pole", C.POLE, epochs)
    h = float(rng.uniform(6.5, 8.0))
    grey = lin((0.45, 0.47, 0.48) if rng.random() < 0.6 else (0.2, 0.25, 0.22))
    b.cyl(oid, C.POLE, M.METAL, grey, x, y, 0.16, CURB_H, 0.7, epochs=epochs)
    b.cyl(oid, C.POLE, M.METAL, grey, x, y, 0.09, 0.7, h, epochs=epochs)
    arm = 1.6 * side
    y0, y1 = sorted((y, y - arm))
    b.box(
        oid,
        C.POLE,
        M.METAL,
        grey,
        (x - 0.05, y0, h - 0.15),
        (x + 0.05, y1, h - 0.05),
        epochs=epochs,
    )
    ly = y - arm
    b.box(
        oid,
        C.POLE,
        M.LAMP,
        grey,
        (x - 0.25, ly - 0.3, h - 0.35),
        (x + 0.25, ly + 0.3, h - 0.12),
        epochs=epochs,
    )
    return oid


def sign(
    b: SceneBuilder,
    x: float,
    y: float,
    epochs: int,
    rng,
    facing: float = -1.0,
    look: tuple | None = None,
) -> tuple[int, tuple]:
    """Traffic sign: a post (class pole) with a thin plate (class sign) facing ``facing`` y."""
    look = look or (
        int(rng.integers(len(SIGN_COLOURS))),
        int(rng.integers(3)),
        int(rng.integers(1000)),
        float(rng.uniform(0.55, 0.75)),
    )
    colour, variant, seed, size = look
    oid = b.new_object("sign", C.SIGN, epochs)
    b.cyl(oid, C.POLE, M.METAL, lin((0.55, 0.56, 0.58)), x, y, 0.035, CURB_H, 2.75, epochs=epochs)
    yp = y + 0.05 * facing
    b.box(
        oid,
        C.SIGN,
        M.SIGN,
        lin(SIGN_COLOURS[colour]),
        (x - size / 2, yp - 0.015, 2.75 - size),
        (x + size / 2, yp + 0.015, 2.75),
        tex=(facing, variant, seed),
        epochs=epochs,
    )
    return oid, look


def board(b: SceneBuilder, x: float, y: float, epochs: int, rng, facing: float = -1.0) -> int:
    """Advertising board (thin planar, class sign) on two posts."""
    oid = b.new_object("board", C.SIGN, epochs)
    w = float(rng.uniform(1.8, 2.8))
    top = float(rng.uniform(2.3, 2.8))
    h = float(rng.uniform(1.2, 1.6))
    col = lin(tuple(rng.uniform(0.1, 0.9, 3)))
    grey = lin((0.3, 0.3, 0.32))
    for dx in (-0.4 * w, 0.4 * w):
        b.cyl(oid, C.SIGN, M.METAL, grey, x + dx, y, 0.05, CURB_H, top, epochs=epochs)
    b.box(
        oid,
        C.SIGN,
        M.BOARD,
        col,
        (x - w / 2, y - 0.04 + 0.07 * facing, top - h),
        (x + w / 2, y + 0.04 + 0.07 * facing, top),
        tex=(facing, int(rng.integers(1000))),
        epochs=epochs,
    )
    return oid


def railing(b: SceneBuilder, x0: float, x1: float, y: float, epochs: int, rng) -> int:
    """Fence of thin vertical bars between two rails, posts every 2 m."""
    oid = b.new_object("railing", C.RAILING, epochs)
    col = lin([(0.12, 0.2, 0.14), (0.15, 0.15, 0.16), (0.5, 0.5, 0.52)][int(rng.integers(3))])
    h = float(rng.uniform(0.9, 1.2))
    z0 = CURB_H
    for xp in np.arange(x0, x1 + 1e-6, 2.0):
        b.box(
            oid,
            C.RAILING,
            M.METAL,
            col,
            (xp - 0.03, y - 0.03, z0),
            (xp + 0.03, y + 0.03, z0 + h),
            epochs=epochs,
        )
    for zr in (z0 + 0.12, z0 + h - 0.08):
        b.box(
            oid,
            C.RAILING,
            M.METAL,
            col,
            (x0, y - 0.02, zr),
            (x1, y + 0.02, zr + 0.04),
            epochs=epochs,
        )
    for xb in np.arange(x0 + 0.12, x1 - 0.06, 0.12):
        b.box(
            oid,
            C.RAILING,
            M.METAL,
            col,
            (xb - 0.01, y - 0.01, z0 + 0.12),
            (xb + 0.01, y + 0.01, z0 + h - 0.06),
            epochs=epochs,
        )
    return oid


def hedge(b: SceneBuilder, x0: float, x1: float, y: float, epochs: int, rng) -> int:
    """Irregular hedge: a leafy core with overlapping ellipsoid bumps."""
    oid = b.new_object("hedge", C.VEGETATION, epochs)
    green = lin(GREENS[int(rng.integers(len(GREENS)))])
    seed = int(rng.integers(1000))
    h = float(rng.uniform(0.9, 1.3))
    b.box(
        oid,
        C.VEGETATION,
        M.FOLIAGE,
        green,
        (x0 + 0.2, y - 0.3, CURB_H),
        (x1 - 0.2, y + 0.3, CURB_H + h - 0.25),
        tex=(seed,),
        epochs=epochs,
    )
    for xc in np.arange(x0 + 0.35, x1 - 0.3, 0.45):
        c = (
            xc + rng.uniform(-0.1, 0.1),
            y + rng.uniform(-0.08, 0.08),
            CURB_H + h * rng.uniform(0.5, 0.65),
        )
        r = (rng.uniform(0.35, 0.5), rng.uniform(0.35, 0.45), h * rng.uniform(0.45, 0.6))
        b.ell(oid, C.VEGETATION, M.FOLIAGE, green, c, r, tex=(seed,), epochs=epochs)
    return oid


def wall(b: SceneBuilder, x0: float, x1: float, y: float, rng) -> int:
    """Plain garden wall (class building, one uniform paint, no texture) 3.0–3.6 m high, so
    that it is the whole background of a board 1 m in front of it seen from 1.7 m."""
    oid = b.new_object("wall", C.BUILDING, BOTH)
    colour = lin(FACADE_COLOURS[int(rng.integers(len(FACADE_COLOURS)))])
    h = float(rng.uniform(3.0, 3.6))
    b.box(oid, C.BUILDING, M.PAINT, colour, (x0, y - 0.12, 0.0), (x1, y + 0.12, h))
    return oid


def paint_plain(b: SceneBuilder, rng: np.random.Generator, changes: list[dict]) -> None:
    """Repaint the street inventory (:data:`PAINTED_TYPES`) in one uniform colour per object
    with no texture; a moved object keeps its paint."""
    same = {ch["to_object"]: ch["from_object"] for ch in changes if "to_object" in ch}
    colour: dict[int, tuple[float, float, float]] = {}
    for ob in b.objects:  # ids ascend, and a moved object's old one comes first
        if ob["type"] in PAINTED_TYPES:
            oid = ob["id"]
            pick = lin(PAINTS[int(rng.integers(len(PAINTS)))])
            colour[oid] = colour.get(same.get(oid, -1), pick)
    for i, oid in enumerate(b.obj):
        if oid in colour:
            b.mat[i] = M.PAINT
            b.color[i] = colour[oid]


def tree(b: SceneBuilder, x: float, y: float, rng, grow: np.random.Generator | None) -> int:
    """Tree: trunk and a cluster of ellipsoids; with ``grow`` some foliage differs in epoch 2."""
    oid = b.new_object("tree", C.VEGETATION, BOTH)
    b.cyl(
        oid,
        C.VEGETATION,
        M.BARK,
        lin((0.35, 0.27, 0.2)),
        x,
        y,
        float(rng.uniform(0.12, 0.2)),
        CURB_H,
        3.4,
    )
    green = lin(GREENS[int(rng.integers(len(GREENS)))])
    seed = int(rng.integers(1000))
    zc = float(rng.uniform(4.3, 5.5))
    n = int(rng.integers(22, 34))
    blobs = []
    for _ in range(n):  # many small blobs on a rough ellipsoid shell give a ragged crown
        a = rng.uniform(0, 2 * np.pi)
        e = rng.uniform(-0.9, 1.2)
        rr = rng.uniform(0.6, 1.0)
        c = (
            x + 1.7 * rr * np.cos(a) * np.cos(e),
            y + 1.6 * rr * np.sin(a) * np.cos(e),
            zc + 1.3 * rr * np.sin(e),
        )
        r = tuple(rng.uniform(0.45, 0.95) * np.array([1.0, 1.0, rng.uniform(0.8, 1.1)]))
        blobs.append((c, r))
    changed: set[int] = set()
    if grow is not None:
        changed = set(grow.choice(n, size=int(grow.integers(1, 4)), replace=False).tolist())
    for i, (c, r) in enumerate(blobs):
        if grow is not None and i in changed:
            b.ell(oid, C.VEGETATION, M.FOLIAGE, green, c, r, tex=(seed,), epochs=EPOCH1)
            c2 = tuple(np.asarray(c) + grow.uniform(-0.5, 0.5, 3))
            r2 = tuple(np.asarray(r) * grow.uniform(1.05, 1.3))
            b.ell(oid, C.VEGETATION, M.FOLIAGE, green, c2, r2, tex=(seed,), epochs=EPOCH2)
        else:
            b.ell(oid, C.VEGETATION, M.FOLIAGE, green, c, r, tex=(seed,))
    return oid


def bench(b: SceneBuilder, x: float, y: float, epochs: int, rng, back: float = 1.0) -> int:
    oid = b.new_object("bench", C.FURNITURE, epochs)
    wood = lin([(0.55, 0.36, 0.2), (0.45, 0.3, 0.18), (0.3, 0.32, 0.3)][int(rng.integers(3))])
    metal = lin((0.2, 0.2, 0.21))
    w = float(rng.uniform(1.6, 2.0)) / 2
    for dx in (-w + 0.1, w - 0.1):
        b.box(
            oid,
            C.FURNITURE,
            M.METAL,
            metal,
            (x + dx - 0.03, y - 0.22, CURB_H),
            (x + dx + 0.03, y + 0.22, 0.45),
            epochs=epochs,
        )
    b.box(
        oid,
        C.FURNITURE,
        M.WOOD,
        wood,
        (x - w, y - 0.24, 0.45),
        (x + w, y + 0.24, 0.5),
        epochs=epochs,
    )
    yb = y + 0.22 * back
    b.box(
        oid,
        C.FURNITURE,
        M.WOOD,
        wood,
        (x - w, min(yb, yb + 0.05 * back), 0.55),
        (x + w, max(yb, yb + 0.05 * back), 0.92),
        epochs=epochs,
    )
    return oid


def bin_(b: SceneBuilder, x: float, y: float, epochs: int, rng) -> int:
    oid = b.new_object("bin", C.FURNITURE, epochs)
    col = lin([(0.1, 0.3, 0.15), (0.25, 0.25, 0.27), (0.6, 0.45, 0.1)][int(rng.integers(3))])
    r = float(rng.uniform(0.22, 0.3))
    b.cyl(oid, C.FURNITURE, M.METAL, col, x, y, r, CURB_H, 0.95, epochs=epochs)
    b.cyl(
        oid, C.FURNITURE, M.METAL, lin((0.15, 0.15, 0.15)), x, y, r + 0.03, 0.95, 1.0, epochs=epochs
    )
    return oid


def car(b: SceneBuilder, x: float, y: float, epochs: int, rng) -> int:
    oid = b.new_object("car", C.CAR, epochs)
    L = float(rng.uniform(4.0, 4.8)) / 2
    W = float(rng.uniform(1.7, 1.85)) / 2
    col = lin(CAR_COLOURS[int(rng.integers(len(CAR_COLOURS)))])
    roof = float(rng.uniform(1.4, 1.55))
    b.box(oid, C.CAR, M.CARPAINT, col, (x - L, y - W, 0.32), (x + L, y + W, 0.78), epochs=epochs)
    b.box(
        oid,
        C.CAR,
        M.CARPAINT,
        col,
        (x - L + 0.08, y - W + 0.05, 0.78),
        (x + L - 0.12, y + W - 0.05, 0.98),
        epochs=epochs,
    )  # shoulder, a little inset
    b.box(
        oid,
        C.CAR,
        M.CABIN,
        col,
        (x - L + 0.9, y - W + 0.12, 0.98),
        (x + L - 1.2, y + W - 0.12, roof),
        epochs=epochs,
    )
    dark = lin((0.12, 0.12, 0.13))
    for sx in (-1.0, 1.0):  # bumpers and lamps
        xb = x + sx * L
        b.box(
            oid,
            C.CAR,
            M.CONCRETE,
            dark,
            (min(xb, xb + 0.06 * sx), y - W + 0.02, 0.3),
            (max(xb, xb + 0.06 * sx), y + W - 0.02, 0.52),
            epochs=epochs,
        )
        lamp = lin((0.95, 0.95, 0.9) if sx > 0 else (0.7, 0.05, 0.05))
        for sy in (-1.0, 1.0):
            yl = y + sy * (W - 0.25)
            b.box(
                oid,
                C.CAR,
                M.LAMP if sx > 0 else M.CONCRETE,
                lamp,
                (min(xb, xb + 0.02 * sx), yl - 0.15, 0.66),
                (max(xb, xb + 0.02 * sx), yl + 0.15, 0.76),
                epochs=epochs,
            )
    tyre = lin((0.05, 0.05, 0.05))
    for dx in (-L + 0.75, L - 0.8):
        for sy in (-1.0, 1.0):
            yy = y + sy * W
            b.box(
                oid,
                C.CAR,
                M.RUBBER,
                tyre,
                (x + dx - 0.32, min(yy, yy - 0.24 * sy), 0.0),
                (x + dx + 0.32, max(yy, yy - 0.24 * sy) + 0.0, 0.62),
                epochs=epochs,
            )
    return oid


def pedestrian(b: SceneBuilder, x: float, y: float, rng) -> int:
    oid = b.new_object("pedestrian", C.PEDESTRIAN, EPOCH2)
    h = float(rng.uniform(1.55, 1.85))
    col = lin(tuple(rng.uniform(0.1, 0.8, 3)))
    b.cyl(oid, C.PEDESTRIAN, M.CLOTH, col, x, y, 0.2, CURB_H, CURB_H + h - 0.25, epochs=EPOCH2)
    b.ell(
        oid,
        C.PEDESTRIAN,
        M.SKIN,
        lin((0.8, 0.62, 0.5)),
        (x, y, CURB_H + h - 0.12),
        (0.1, 0.1, 0.13),
        epochs=EPOCH2,
    )
    return oid


def building(b: SceneBuilder, x0: float, x1: float, y_face: float, side: float, rng) -> int:
    """Block from the façade line ``y_face`` away from the road (``side`` = ±1)."""
    oid = b.new_object("building", C.BUILDING, BOTH)
    # the near side (behind the cameras) stays lower so the sun reaches the far façades
    h = float(rng.uniform(8.0, 22.0) if side > 0 else rng.uniform(6.0, 11.0))
    depth = 14.0
    ya, yb = sorted((y_face, y_face + side * depth))
    colour = lin(FACADE_COLOURS[int(rng.integers(len(FACADE_COLOURS)))])
    floor_h = float(rng.uniform(3.0, 3.6))
    bay = float(rng.uniform(2.6, 3.8))
    tex = (floor_h, bay, float(rng.random() < 0.25), int(rng.integers(1, 1000)))
    b.box(oid, C.BUILDING, M.FACADE, colour, (x0, ya, CURB_H), (x1, yb, h), tex=tex)
    stone = lin((0.6, 0.58, 0.55))
    out = 0.12 * side
    b.box(
        oid,
        C.BUILDING,
        M.CONCRETE,
        lin((0.42, 0.4, 0.38)),
        (x0, min(y_face - out, y_face + side), CURB_H),
        (x1, max(y_face - out, y_face + side), 0.7),
    )
    out = 0.35 * side
    b.box(
        oid,
        C.BUILDING,
        M.CONCRETE,
        stone,
        (x0, min(y_face - out, y_face + side), h - 0.45),
        (x1, max(y_face - out, y_face + side), h - 0.1),
    )
    if rng.random() < 0.35:  # balconies on upper floors
        n_floors = int((h - 1.0) / floor_h)
        for f in range(1, n_floors):
            for xb in np.arange(x0 + bay * 1.5, x1 - bay, bay * 2):
                z = CURB_H + f * floor_h - 0.1
                ya2, yb2 = sorted((y_face, y_face - 1.0 * side))
                b.box(
                    oid,
                    C.BUILDING,
                    M.CONCRETE,
                    stone,
                    (xb - 1.0, ya2, z),
                    (xb + 1.0, yb2, z + 0.15),
                )
                yf = y_face - 1.0 * side
                b.box(
                    oid,
                    C.BUILDING,
                    M.CONCRETE,
                    stone,
                    (xb - 1.0, min(yf, yf + 0.06 * side), z),
                    (xb + 1.0, max(yf, yf + 0.06 * side), z + 1.0),
                )
    return oid


# --- the street ---------------------------------------------------------------------------


def build_street(
    b: SceneBuilder,
    rng: np.random.Generator,
    length: float,
    with_changes: bool,
    plain: bool = False,
) -> tuple[StreetLayout, list[dict], list[dict]]:
    """Fill ``b`` with one street; returns its layout, change instances and disturbances.

    Change instances carry ``objects`` (ids) and ``kind`` (added / removed / moved /
    replaced); instance ids are assigned later by the caller.

    ``plain``: plain walls along the property line behind the far sidewalk's middle lane
    (behind every change there, and half the other segments), the inventory painted
    uniformly (:func:`paint_plain`).
    """
    base, chg, dist = rng.spawn(3)
    # the plain street's extra draws come from their own stream, spawned only when asked
    paint = rng.spawn(1)[0] if plain else None
    lay = StreetLayout(
        length=float(length),
        road_half=float(base.uniform(3.25, 3.75)),
        sidewalk=float(base.uniform(3.2, 3.8)),
        setback_far=float(base.uniform(1.8, 3.0)),
        setback_near=float(base.uniform(0.0, 2.0)),
    )
    _ground(b, lay, base)
    for side in (1.0, -1.0):
        _buildings(b, lay, side, base)

    lo, hi = -2.0, length + 2.0
    curb = Lane(lo, hi)
    mid = Lane(lo, hi)
    line = Lane(lo, hi)
    parking = Lane(lo - 10, hi + 10)
    changes = _changes(b, lay, chg, curb, mid, line, with_changes)
    disturb: list[dict] = []
    if paint is not None:  # a plain wall ~1 m behind each change of the middle lane
        for x0, x1 in list(mid.taken):
            if line.free(x0 - 1.5, x1 + 1.5):
                line.take(x0 - 1.5, x1 + 1.5)
                wall(b, x0 - 1.5, x1 + 1.5, lay.far_line_y, paint)

    # regular furniture, both epochs
    for x in np.arange(base.uniform(2, 12), hi, base.uniform(22, 30)):
        if curb.place(x, 0.5):
            street_light(b, x, lay.far_curb_y, 1.0, BOTH, base)
    for x in np.arange(base.uniform(8, 20), hi, base.uniform(24, 32)):
        street_light(b, x, -(lay.road_half + 0.55), -1.0, BOTH, base)
    for x in np.sort(base.uniform(lo, hi, max(2, int(length / 25)))):
        if curb.place(x, 1.6, gap=1.0):
            grow = dist.spawn(1)[0] if with_changes and dist.random() < 0.6 else None
            oid = tree(b, x, lay.far_curb_y + 0.3, base, grow)
            if grow is not None:
                disturb.append({"object": oid, "kind": "foliage"})
    for x in base.uniform(lo, hi, max(2, int(length / 30))):
        if curb.place(x, 0.4):
            sign(b, x, lay.far_curb_y, BOTH, base)
    for x in base.uniform(lo, hi, max(2, int(length / 25))):
        if curb.place(x, 0.4):
            bin_(b, x, lay.far_curb_y + 0.2, BOTH, base)
    for x in base.uniform(lo, hi, max(1, int(length / 40))):
        if mid.place(x, 1.1):
            bench(b, x, lay.far_mid_y, BOTH, base)
    for x in base.uniform(lo, hi, max(1, int(length / 60))):
        if mid.place(x, 1.5):
            board(b, x, lay.far_mid_y + 0.6, BOTH, base)
    x = lo + float(base.uniform(0, 4))
    while x < hi - 3:
        seg = float(base.uniform(4, 12))
        if line.free(x, x + seg):
            line.take(x, x + seg)
            r = base.random()
            if paint is not None and paint.random() < 0.5:
                wall(b, x, x + seg, lay.far_line_y, paint)
            elif r < 0.5:
                railing(b, x, x + seg, lay.far_line_y, BOTH, base)
            else:
                hedge(b, x, x + seg, lay.far_line_y, BOTH, base)
        x += seg + float(base.uniform(1.0, 6.0))

    # parked cars on the far side; some leave or arrive between the epochs (disturbances)
    x = lo - 8 + float(base.uniform(0, 5))
    y_car = lay.road_half - 1.1
    while x < hi + 8:
        half = 2.6
        if base.random() < 0.65 and parking.place(x, half, gap=0.3):
            r = dist.random()
            if with_changes and r < 0.2:
                oid = car(b, x, y_car, EPOCH1, base)
                disturb.append({"object": oid, "kind": "car"})
            elif with_changes and r < 0.4:
                oid = car(b, x, y_car, EPOCH2, base)
                disturb.append({"object": oid, "kind": "car"})
            else:
                car(b, x, y_car, BOTH, base)
        x += 2 * half + float(base.uniform(0.5, 4.0))
    if with_changes:  # one new car in a free bay, and pedestrians on the far sidewalk
        for _ in range(20):
            x = float(dist.uniform(lo, hi))
            if parking.place(x, 2.5, gap=0.3):
                disturb.append({"object": car(b, x, y_car, EPOCH2, dist), "kind": "car"})
                break
        for _ in range(max(1, int(length / 50))):
            for _ in range(20):
                x = float(dist.uniform(lo + 3, hi - 3))
                if mid.place(x, 0.3, gap=0.3):
                    y = lay.far_mid_y + float(dist.uniform(-0.6, 0.3))
                    disturb.append({"object": pedestrian(b, x, y, dist), "kind": "pedestrian"})
                    break
    if paint is not None:
        paint_plain(b, paint, changes)
    return lay, changes, disturb


def _ground(b: SceneBuilder, lay: StreetLayout, rng) -> None:
    L, rh, sw = lay.length, lay.road_half, lay.sidewalk
    x0, x1 = -60.0, L + 60.0
    road = b.new_object("road", C.ROAD)
    b.box(road, C.ROAD, M.ASPHALT, (1, 1, 1), (x0, -rh, -0.3), (x1, rh, 0.0), tex=(0, rh))
    for side in (1.0, -1.0):
        walk = b.new_object("sidewalk", C.GROUND)
        ya, yb = sorted((side * rh, side * (rh + sw)))
        paving = lin((0.68, 0.66, 0.62) if side > 0 else (0.62, 0.6, 0.58))
        b.box(walk, C.GROUND, M.PAVING, paving, (x0, ya, -0.3), (x1, yb, CURB_H))
        ya, yb = sorted((side * rh, side * (rh + 0.18)))
        b.box(
            walk,
            C.GROUND,
            M.CONCRETE,
            lin((0.62, 0.62, 0.6)),
            (x0, ya, -0.3),
            (x1, yb, CURB_H + 0.005),
        )
        yard = b.new_object("ground", C.GROUND)
        ya, yb = sorted((side * (rh + sw), side * 70.0))
        b.box(
            yard,
            C.GROUND,
            M.GRASS,
            lin((0.36, 0.42, 0.22)),
            (x0, ya, -0.3),
            (x1, yb, CURB_H - 0.02),
        )


def _buildings(b: SceneBuilder, lay: StreetLayout, side: float, rng) -> None:
    y_face = lay.far_facade_y if side > 0 else lay.near_facade_y
    x = -55.0
    while x < lay.length + 55.0:
        w = float(rng.uniform(9.0, 22.0))
        building(b, x, x + w, y_face, side, rng)
        x += w + (float(rng.uniform(2.0, 6.0)) if rng.random() < 0.3 else 0.0)
    # a taller back row fills the sky between blocks
    bg = b.new_object("building", C.BUILDING)
    x = -55.0
    while x < lay.length + 55.0:
        w = float(rng.uniform(15.0, 20.0))
        ya, yb = sorted((y_face + side * 22.0, y_face + side * 32.0))
        colour = lin(FACADE_COLOURS[int(rng.integers(len(FACADE_COLOURS)))])
        tex = (
            float(rng.uniform(3.0, 3.5)),
            float(rng.uniform(2.8, 3.6)),
            0.0,
            int(rng.integers(1, 1000)),
        )
        b.box(
            bg,
            C.BUILDING,
            M.FACADE,
            colour,
            (x, ya, CURB_H),
            (x + w, yb, float(rng.uniform(16, 30))),
            tex=tex,
        )
        x += w


def _changes(
    b: SceneBuilder, lay: StreetLayout, rng, curb: Lane, mid: Lane, line: Lane, create: bool
) -> list[dict]:
    """Reserve places for the changes (always, so the base street does not depend on
    ``create``) and, with ``create``, add the epoch-1-only and epoch-2-only objects."""
    L = lay.length
    rng, looks = rng.spawn(2)  # placement draws never depend on ``create``
    kinds = ["added_pole", "removed_board", "railing_to_hedge", "moved_sign", "added_bench"]
    if L >= 100:
        kinds += ["added_board", "removed_bin"]
    order = rng.permutation(len(kinds))
    xs = np.linspace(0.12, 0.88, len(kinds)) * L
    out: list[dict] = []
    for slot, k in zip(xs[np.argsort(order)], kinds, strict=True):
        x = float(slot + rng.uniform(-1.0, 1.0))
        if k == "added_pole" and curb.place(x, 0.5):
            if create:
                oid = street_light(b, x, lay.far_curb_y, 1.0, EPOCH2, looks)
                out.append({"kind": "added", "type": "pole", "objects": [oid]})
        elif k == "removed_board" and mid.place(x, 1.5):
            if create:
                oid = board(b, x, lay.far_mid_y + 0.6, EPOCH1, looks)
                out.append({"kind": "removed", "type": "board", "objects": [oid]})
        elif k == "added_board" and mid.place(x, 1.5):
            if create:
                oid = board(b, x, lay.far_mid_y + 0.6, EPOCH2, looks)
                out.append({"kind": "added", "type": "board", "objects": [oid]})
        elif k == "railing_to_hedge":
            seg = float(rng.uniform(5.0, 7.0))
            if line.free(x - seg / 2, x + seg / 2):
                line.take(x - seg / 2, x + seg / 2)
                if create:
                    old = railing(b, x - seg / 2, x + seg / 2, lay.far_line_y, EPOCH1, looks)
                    new = hedge(b, x - seg / 2, x + seg / 2, lay.far_line_y, EPOCH2, looks)
                    out.append(
                        {
                            "kind": "replaced",
                            "type": "railing",
                            "objects": [old, new],
                            "removed_objects": [old],
                            "added_objects": [new],
                            "new_type": "hedge",
                        }
                    )
        elif k == "moved_sign":
            shift = float(rng.uniform(3.0, 5.0)) * (1 if rng.random() < 0.5 else -1)
            if not curb.free(x + shift - 0.4, x + shift + 0.4):
                shift = -shift
            if curb.free(x - 0.4, x + 0.4) and curb.free(x + shift - 0.4, x + shift + 0.4):
                curb.take(x - 0.4, x + 0.4)
                curb.take(x + shift - 0.4, x + shift + 0.4)
                if create:
                    old, plate = sign(b, x, lay.far_curb_y, EPOCH1, looks)
                    new, _ = sign(b, x + shift, lay.far_curb_y, EPOCH2, looks, look=plate)
                    out.append(
                        {
                            "kind": "moved",
                            "type": "sign",
                            "objects": [old, new],
                            "from_object": old,
                            "to_object": new,
                            "shift_m": shift,
                        }
                    )
        elif k == "added_bench" and mid.place(x, 1.1):
            if create:
                oid = bench(b, x, lay.far_mid_y, EPOCH2, looks)
                out.append({"kind": "added", "type": "bench", "objects": [oid]})
        elif k == "removed_bin" and curb.place(x, 0.4):
            if create:
                oid = bin_(b, x, lay.far_curb_y + 0.2, EPOCH1, looks)
                out.append({"kind": "removed", "type": "bin", "objects": [oid]})
    if create and len(out) != len(kinds):  # a layout bug, not a user error
        raise RuntimeError(f"placed {len(out)} of {len(kinds)} changes on a {L} m street")
    return out
