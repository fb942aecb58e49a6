"""Value objects shared by every layer: a camera (:class:`Intrinsics`, :class:`Pose`), a posed
image (:class:`View`, :class:`PoseSet`) and points in a local frame (:class:`PointCloud`).

Conventions (one for the whole project; importers convert to it):

* **Pose** is world→camera: ``x_cam = R @ X + t`` with ``R`` (3, 3) float64 orthonormal and
  ``t`` (3,) float64 metres. The camera centre is ``C = -Rᵀ t``. This is COLMAP's convention.
* **Camera frame** is OpenCV's: x right, y down, z forward (viewing direction).
* **Pixels** are OpenCV's: the centre of the top-left pixel is (0, 0).
* **World frame** is a local Cartesian frame: the CRS coordinates minus an origin (the LAS
  offset or the tile origin). Never project raw UTM-sized coordinates in float32.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from streetcd.errors import InputError, MissingInputError

# np.allclose(R Rᵀ, I, atol=1e-6)'s test (|a − b| ≤ atol + rtol·|b|, rtol 1e-5) without its
# overhead: planning a 10,000-view city builds 20,000 poses
_EYE3 = np.eye(3)
_ROTATION_TOL = 1e-6 + 1e-5 * _EYE3


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels, OpenCV pixel convention, image ``width × height``.

    ``dist`` is OpenCV's ``(k1, k2, p1, p2, k3)``; all zeros means an ideal pinhole.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"image size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise InputError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        values = (self.fx, self.fy, self.cx, self.cy, *self.dist)
        if not all(math.isfinite(v) for v in values):
            raise InputError(f"intrinsics must be finite, got {values}")
        if len(self.dist) != 5:
            raise InputError(f"dist must be (k1, k2, p1, p2, k3), got {self.dist}")

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(d != 0.0 for d in self.dist)

    def scaled(self, factor: float) -> Intrinsics:
        """Intrinsics of the same camera with the image resized by ``factor``.

        Pixel centres map as ``u' = (u + 0.5) * factor - 0.5`` (OpenCV's ``resize``).
        """
        return Intrinsics(
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            dist=self.dist,
        )


@dataclass(frozen=True)
class Pose:
    """World→camera rigid transform: ``x_cam = R @ X + t`` (see module docstring)."""

    R: np.ndarray = field(repr=False)
    t: np.ndarray

    def __post_init__(self) -> None:
        R = np.asarray(self.R, dtype=np.float64)
        t = np.asarray(self.t, dtype=np.float64).reshape(3)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)) or not np.all(np.isfinite(t)):
            raise InputError(f"pose must be a finite 3x3 R and 3-vector t, got R={R}, t={t}")
        if not (np.abs(R @ R.T - _EYE3) <= _ROTATION_TOL).all() or np.linalg.det(R) < 0:
            raise InputError(f"pose R is not a rotation (RᵀR ≠ I or det < 0): {R.tolist()}")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    @cached_property
    def center(self) -> np.ndarray:
        """(3,) float64 camera centre in the world frame, ``C = -Rᵀ t``; read-only (computed
        once: planning a city asked each pose for it ~45 times)."""
        c = -self.R.T @ self.t
        c.setflags(write=False)
        return c

    @property
    def direction(self) -> np.ndarray:
        """(3,) unit viewing direction (camera +z) in the world frame."""
        return self.R[2].copy()

    @classmethod
    def from_center(cls, R: np.ndarray, center: np.ndarray) -> Pose:
        """Pose from a world→camera rotation and a camera centre: ``t = -R C``."""
        R = np.asarray(R, dtype=np.float64)
        return cls(R, -R @ np.asarray(center, dtype=np.float64))

    def shifted(self, origin: np.ndarray) -> Pose:
        """The same pose in a frame whose origin is ``origin`` (world coordinates).

        Used to move a georeferenced pose into a local frame: ``X_local = X - origin``.
        """
        # R is unchanged and already validated (planning shifts every view many times, and
        # the orthonormality check dominated that)
        center = self.center - np.asarray(origin, dtype=np.float64)
        return Pose.of_rotation(self.R, -self.R @ center)

    @classmethod
    def of_rotation(cls, R: np.ndarray, t: np.ndarray) -> Pose:
        """``Pose(R, t)`` without its checks, for an ``R`` that is a (3, 3) float64 rotation
        by construction and a finite (3,) float64 ``t``: the caller vouches for both."""
        pose = object.__new__(cls)
        object.__setattr__(pose, "R", R)
        object.__setattr__(pose, "t", t)
        return pose

    def __reduce__(self) -> tuple[Any, tuple[bytes, bytes]]:
        """Pickled as the 96 bytes of R and t, in the pickle itself: a night sends each Dask
        batch with ~60 poses, and as numpy arrays each became an out-of-band frame of its
        own (77 frames a batch). The cached centre is left to be recomputed."""
        return _pose_from_bytes, (
            np.asarray(self.R, dtype=np.float64).tobytes(),
            np.asarray(self.t, dtype=np.float64).tobytes(),
        )


def _pose_from_bytes(R: bytes, t: bytes) -> Pose:
    """The :class:`Pose` that :meth:`Pose.__reduce__` pickled (bit for bit)."""
    return Pose.of_rotation(
        np.frombuffer(R, dtype=np.float64).reshape(3, 3).copy(),
        np.frombuffer(t, dtype=np.float64).copy(),
    )


@dataclass(frozen=True)
class PointCloud:
    """Points in a local frame.

    xyz : (N, 3) float64, metres, ``X_crs − origin``.
    origin : (3,) float64, metres in the CRS.
    classification : (N,) uint8, codes of :mod:`streetcd.classes`.
    intensity : (N,) uint16 or None.
    rgb : (N, 3) uint16 or None (LAS colours are 16-bit).
    gps_time : (N,) float64 or None, seconds.
    crs : the CRS as ``"EPSG:XXXX"`` when it has an EPSG code, else WKT, or None.
    """

    xyz: np.ndarray
    origin: np.ndarray
    classification: np.ndarray
    intensity: np.ndarray | None = None
    rgb: np.ndarray | None = None
    gps_time: np.ndarray | None = None
    crs: str | None = None

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    def subset(self, mask: np.ndarray) -> PointCloud:
        """The points where ``mask`` (N,) bool (or an index array) selects."""

        def pick(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[mask]

        return PointCloud(
            self.xyz[mask],
            self.origin,
            self.classification[mask],
            pick(self.intensity),
            pick(self.rgb),
            pick(self.gps_time),
            self.crs,
        )


@dataclass(frozen=True)
class View:
    """One posed image.

    ``pose`` is world→camera in the frame of the pose file (usually the CRS, so its centre
    has georeferenced-size coordinates); call :meth:`local` before projecting local points.
    ``image`` is the image path when known. ``time`` is the acquisition time in seconds
    (GPS or Unix) when the pose file gives one, else the view's order in the file.
    """

    name: str
    intrinsics: Intrinsics
    pose: Pose
    image: Path | None = None
    time: float | None = None

    @property
    def stem(self) -> str:
        return Path(self.name).stem

    @property
    def center(self) -> np.ndarray:
        return self.pose.center

    def local(self, origin: np.ndarray) -> View:
        """The same view in the frame ``X - origin`` (origin (3,) float64, world metres)."""
        return replace(self, pose=self.pose.shifted(origin))


@dataclass(frozen=True)
class PoseSet:
    """Views read from one pose file, with the CRS the file states (``"EPSG:32648"``) or None."""

    views: tuple[View, ...]
    crs: str | None = None
    source: Path | None = None

    def __len__(self) -> int:
        return len(self.views)

    def by_name(self) -> dict[str, View]:
        return {v.name: v for v in self.views}

    def get(self, name: str) -> View:
        """The view called ``name`` (its file name or stem); MissingInputError if absent."""
        for v in self.views:
            if v.name == name or v.stem == name:
                return v
        where = f" in {self.source}" if self.source else ""
        raise MissingInputError(f"no pose for view {name!r}{where} ({len(self.views)} views)")
