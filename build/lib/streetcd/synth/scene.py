"""Scene description: primitives grouped into objects, two epochs, placed in a CRS.

A :class:`Street` holds its primitives in a *street frame* (x along the street from its
start, y across to the left, z up from the road surface, metres). ``rotation`` (3, 3) and
``offset`` (3,) place it in the scene's local frame: ``X_local = rotation @ X_street +
offset``, and ``X_crs = X_local + origin``. A :class:`Scene` is one or more streets that
share the local frame (one for :func:`generate_street`, several for :func:`generate_city`).

Every primitive belongs to an object and exists in epoch 1 (the scan), epoch 2 (the
images) or both (``epochs`` bit mask 1 | 2). An object that only changes shape between
epochs (a tree whose foliage grew) has primitives with different masks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from streetcd.synth.raycast import BOX, CYL, ELL, Grid, build_grid, footprints

EPOCH1, EPOCH2, BOTH = 1, 2, 3


@dataclass
class SceneBuilder:
    """Collects primitives and objects; object ids start at 1 (0 means "nothing")."""

    kind: list[int] = field(default_factory=list)
    params: list[tuple[float, ...]] = field(default_factory=list)
    obj: list[int] = field(default_factory=list)
    cls: list[int] = field(default_factory=list)
    mat: list[int] = field(default_factory=list)
    color: list[tuple[float, float, float]] = field(default_factory=list)
    tex: list[tuple[float, float, float, float]] = field(default_factory=list)
    epochs: list[int] = field(default_factory=list)
    objects: list[dict[str, Any]] = field(default_factory=list)
    first_id: int = 1

    def new_object(self, type_: str, cls: int, epochs: int = BOTH, **info: Any) -> int:
        oid = self.first_id + len(self.objects)
        self.objects.append(
            {
                "id": oid,
                "type": type_,
                "class": int(cls),
                "epochs": [e for e in (1, 2) if epochs & e],
                **info,
            }
        )
        return oid

    def _add(
        self,
        kind: int,
        params: tuple[float, ...],
        oid: int,
        cls: int,
        mat: int,
        color: tuple[float, float, float],
        tex: tuple[float, ...],
        epochs: int,
    ) -> int:
        self.kind.append(kind)
        self.params.append(tuple(float(v) for v in params))
        self.obj.append(oid)
        self.cls.append(int(cls))
        self.mat.append(int(mat))
        self.color.append(tuple(float(c) for c in color))  # type: ignore[arg-type]
        t = tuple(float(v) for v in tex) + (0.0,) * (4 - len(tex))
        self.tex.append(t)  # type: ignore[arg-type]
        self.epochs.append(epochs)
        return len(self.kind) - 1

    def box(self, oid: int, cls: int, mat: int, color, lo, hi, tex=(), epochs=BOTH) -> int:
        """Axis-aligned box from corner ``lo`` (3,) to ``hi`` (3,), street frame metres."""
        return self._add(BOX, (*lo, *hi), oid, cls, mat, color, tex, epochs)

    def cyl(self, oid, cls, mat, color, cx, cy, r, z0, z1, tex=(), epochs=BOTH) -> int:
        return self._add(CYL, (cx, cy, r, z0, z1, 0.0), oid, cls, mat, color, tex, epochs)

    def ell(self, oid, cls, mat, color, center, radii, tex=(), epochs=BOTH) -> int:
        return self._add(ELL, (*center, *radii), oid, cls, mat, color, tex, epochs)

    def object_epochs(self) -> None:
        """Set each object's ``epochs`` to the union of its primitives' epochs."""
        masks: dict[int, int] = {}
        for o, e in zip(self.obj, self.epochs, strict=True):
            masks[o] = masks.get(o, 0) | e
        for ob in self.objects:
            m = masks.get(ob["id"], 0)
            ob["epochs"] = [e for e in (1, 2) if m & e]


@dataclass(frozen=True)
class Street:
    """Primitives of one street (street frame) with per-epoch grids and placement.

    kind (P,) int8, params (P, 6) float64, obj (P,) int32 object ids, cls (P,) uint8 class
    codes, mat (P,) int32 materials, color (P, 3) float64 linear RGB, tex (P, 4) float64,
    epochs (P,) uint8 bit masks. ``grids[e]`` holds the primitives of epoch e (1 or 2) and
    ``index[e]`` maps its primitive numbers to rows of the arrays above.
    """

    name: str
    kind: np.ndarray
    params: np.ndarray
    obj: np.ndarray
    cls: np.ndarray
    mat: np.ndarray
    color: np.ndarray
    tex: np.ndarray
    epochs: np.ndarray
    grids: dict[int, Grid]
    index: dict[int, np.ndarray]
    rotation: np.ndarray
    offset: np.ndarray
    layout: dict[str, Any]

    @cached_property
    def bounds_local(self) -> np.ndarray:
        """(6,) local-frame axis-aligned bounds of everything in the street."""
        b = footprints(self.kind, self.params)
        lo, hi = b[:, :3].min(0), b[:, 3:].max(0)
        corners = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        pts = self.to_local(corners)
        return np.concatenate([pts.min(0), pts.max(0)])

    def to_street(self, points_local: np.ndarray) -> np.ndarray:
        """(N, 3) local → street frame."""
        p = np.asarray(points_local, dtype=np.float64) - self.offset
        return _rotate_z(p, self.rotation.T)

    def to_local(self, points_street: np.ndarray) -> np.ndarray:
        """(N, 3) street → local frame."""
        return _rotate_z(np.asarray(points_street, dtype=np.float64), self.rotation) + self.offset


def _rotate_z(p: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``p @ R.T`` for a rotation about z, element-wise (no BLAS threads for N × 3)."""
    out = np.empty_like(p)
    out[:, 0] = R[0, 0] * p[:, 0] + R[0, 1] * p[:, 1]
    out[:, 1] = R[1, 0] * p[:, 0] + R[1, 1] * p[:, 1]
    out[:, 2] = p[:, 2]
    return out


def rotation_z(heading_deg: float) -> np.ndarray:
    """(3, 3) rotation about z by ``heading_deg`` (counter-clockwise from +x, i.e. east)."""
    a = math.radians(heading_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def freeze(
    builder: SceneBuilder, name: str, heading_deg: float, offset: np.ndarray, layout: dict[str, Any]
) -> Street:
    """Turn a builder into a :class:`Street` with one ray-casting grid per epoch."""
    kind = np.asarray(builder.kind, dtype=np.int8)
    params = np.asarray(builder.params, dtype=np.float64).reshape(-1, 6)
    epochs = np.asarray(builder.epochs, dtype=np.uint8)
    grids, index = {}, {}
    for e in (EPOCH1, EPOCH2):
        idx = np.flatnonzero(epochs & e).astype(np.int32)
        grids[e] = build_grid(kind[idx], params[idx])
        index[e] = idx
    return Street(
        name=name,
        kind=kind,
        params=params,
        obj=np.asarray(builder.obj, dtype=np.int32),
        cls=np.asarray(builder.cls, dtype=np.uint8),
        mat=np.asarray(builder.mat, dtype=np.int32),
        color=np.asarray(builder.color, dtype=np.float64).reshape(-1, 3),
        tex=np.asarray(builder.tex, dtype=np.float64).reshape(-1, 4),
        epochs=epochs,
        grids=grids,
        index=index,
        rotation=rotation_z(heading_deg),
        offset=np.asarray(offset, dtype=np.float64),
        layout=layout,
    )


@dataclass(frozen=True)
class Scene:
    """Streets in one local frame; ``origin`` (3,) CRS metres; ``crs`` e.g. "EPSG:32648".

    objects : every object, ``{id, type, class, epochs, street, ...}``.
    changes : change instances ``{instance_id, kind, type, objects, ...}``.
    disturbances : ``{object, kind}`` for differences that are not changes (cars,
        pedestrians, foliage).
    sun : (3,) unit vector towards the sun, local frame.
    """

    streets: tuple[Street, ...]
    origin: np.ndarray
    crs: str
    objects: tuple[dict[str, Any], ...]
    changes: tuple[dict[str, Any], ...]
    disturbances: tuple[dict[str, Any], ...]
    sun: np.ndarray
    params: dict[str, Any]

    def change_of_object(self) -> dict[int, int]:
        """Object id → change instance id, for objects that take part in a change."""
        out = {}
        for ch in self.changes:
            for oid in ch["objects"]:
                out[oid] = ch["instance_id"]
        return out

    def disturbance_objects(self) -> set[int]:
        return {d["object"] for d in self.disturbances}
