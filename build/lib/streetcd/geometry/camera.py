"""Pinhole camera with OpenCV radial/tangential distortion; projection and back-projection.

Conventions (one for the whole project; importers convert to it):

* **Pose** is world→camera: ``x_cam = R @ X + t`` with ``R`` (3, 3) float64 orthonormal and
  ``t`` (3,) float64 metres. The camera centre is ``C = -Rᵀ t``. This is COLMAP's convention.
* **Camera frame** is OpenCV's: x right, y down, z forward (viewing direction).
* **Depth** means camera-frame z in metres (not the range along the ray).
* **Pixels** are OpenCV's: the centre of the top-left pixel is (0, 0); u is the column, v the
  row. (COLMAP puts that centre at (0.5, 0.5); its importer shifts the principal point.)
* **World frame** is a local Cartesian frame: the CRS coordinates minus an origin (the LAS
  offset or the tile origin). Never project raw UTM-sized coordinates in float32.

Distortion follows OpenCV's model (Brown–Conrady), normalised coordinates x, y, r² = x² + y²::

    x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²)
    y_d = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2 y²) + 2 p2 x y
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from streetcd.errors import InputError
from streetcd.types import Intrinsics, Pose

_FLIP_YZ = np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes <-> photogrammetric (x, y up, z back)


def look_at(
    center: np.ndarray | Sequence[float],
    target: np.ndarray | Sequence[float],
    up: np.ndarray | Sequence[float] = (0.0, 0.0, 1.0),
) -> Pose:
    """Pose of a camera at ``center`` looking at ``target``, image "up" towards ``up``.

    All arguments (3,) metres in the world frame; ``up`` must not be parallel to the view.
    """
    center = np.asarray(center, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - center
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    norm = np.linalg.norm(right)
    if norm < 1e-9:
        raise InputError("look_at: 'up' is parallel to the viewing direction")
    right /= norm
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])  # rows: camera axes expressed in the world frame
    return Pose.from_center(R, center)


# --- distortion -------------------------------------------------------------------------


def distort(
    xn: np.ndarray, yn: np.ndarray, dist: tuple[float, ...]
) -> tuple[np.ndarray, np.ndarray]:
    """Apply OpenCV distortion to normalised coordinates (any matching shapes, unitless)."""
    k1, k2, p1, p2, k3 = dist
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
    return xd, yd


def undistort(
    xd: np.ndarray, yd: np.ndarray, dist: tuple[float, ...], iterations: int = 20
) -> tuple[np.ndarray, np.ndarray]:
    """Invert :func:`distort` by fixed-point iteration (as ``cv2.undistortPoints`` does).

    Converges to < 1e-9 for the mild distortion of street cameras (|k1| < 0.5).
    """
    k1, k2, p1, p2, k3 = dist
    xn, yn = xd.astype(np.float64, copy=True), yd.astype(np.float64, copy=True)
    for _ in range(iterations):
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
        dy = p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
        xn = (xd - dx) / radial
        yn = (yd - dy) / radial
    return xn, yn


# --- projection -------------------------------------------------------------------------


def to_camera(points: np.ndarray, pose: Pose) -> np.ndarray:
    """World (N, 3) float64 metres → camera frame (N, 3) float64 metres: ``R X + t``."""
    return np.asarray(points, dtype=np.float64) @ pose.R.T + pose.t


def project(
    points: np.ndarray, intrinsics: Intrinsics, pose: Pose
) -> tuple[np.ndarray, np.ndarray]:
    """Project world points into the image.

    Parameters
    ----------
    points : (N, 3) float64, metres, local world frame.

    Returns
    -------
    uv : (N, 2) float64, pixels (u column, v row), OpenCV convention. Points with depth ≤ 0
        get NaN.
    depth : (N,) float64, metres, camera-frame z (≤ 0 behind the camera).

    ``u = fx · x_d + cx``, ``v = fy · y_d + cy`` with ``(x_d, y_d)`` the distorted
    normalised coordinates of ``(x/z, y/z)``.
    """
    pc = to_camera(points, pose)
    depth = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = np.where(depth > 0, pc[:, 0] / depth, np.nan)
        yn = np.where(depth > 0, pc[:, 1] / depth, np.nan)
    if intrinsics.has_distortion:
        xn, yn = distort(xn, yn, intrinsics.dist)
    uv = np.column_stack([intrinsics.fx * xn + intrinsics.cx, intrinsics.fy * yn + intrinsics.cy])
    return uv, depth


def pixel_rays(uv: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """Camera-frame ray directions (N, 3) with z = 1 for pixels ``uv`` (N, 2) float64."""
    xd = (uv[:, 0] - intrinsics.cx) / intrinsics.fx
    yd = (uv[:, 1] - intrinsics.cy) / intrinsics.fy
    if intrinsics.has_distortion:
        xd, yd = undistort(xd, yd, intrinsics.dist)
    return np.column_stack([xd, yd, np.ones_like(xd)])


def backproject(
    uv: np.ndarray, depth: np.ndarray, intrinsics: Intrinsics, pose: Pose
) -> np.ndarray:
    """Inverse of :func:`project`: pixels (N, 2) with depths (N,) metres → world (N, 3).

    ``X = Rᵀ (z · [x_n, y_n, 1] - t)``.
    """
    rays = pixel_rays(np.asarray(uv, dtype=np.float64), intrinsics)
    pc = rays * np.asarray(depth, dtype=np.float64)[:, None]
    return (pc - pose.t) @ pose.R


def pixel_grid(height: int, width: int) -> np.ndarray:
    """(H·W, 2) float64 pixel centres in row-major order: (u, v) = (column, row)."""
    v, u = np.mgrid[0:height, 0:width]
    return np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)


def backproject_depth_map(depth: np.ndarray, intrinsics: Intrinsics, pose: Pose) -> np.ndarray:
    """Depth raster (H, W) float metres (NaN = no surface) → world points (H, W, 3) float64.

    Pixels without depth give NaN points.
    """
    h, w = depth.shape
    pts = backproject(pixel_grid(h, w), depth.ravel(), intrinsics, pose)
    return pts.reshape(h, w, 3)


def in_image(uv: np.ndarray, intrinsics: Intrinsics, margin: float = 0.0) -> np.ndarray:
    """(N,) bool: pixel centres inside the image grown by ``margin`` pixels (NaN → False)."""
    u, v = uv[:, 0], uv[:, 1]
    with np.errstate(invalid="ignore"):
        return (
            (u >= -0.5 - margin)
            & (u < intrinsics.width - 0.5 + margin)
            & (v >= -0.5 - margin)
            & (v < intrinsics.height - 0.5 + margin)
        )


# --- rotation parameterisations ----------------------------------------------------------


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """Unit quaternion (qw, qx, qy, qz), Hamilton convention (COLMAP's) → (3, 3) rotation."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation → unit quaternion (qw, qx, qy, qz) with qw ≥ 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    qa = np.array(q)
    qa /= np.linalg.norm(qa)
    return qa if qa[0] >= 0 else -qa


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def opk_to_rotation(omega_deg: float, phi_deg: float, kappa_deg: float) -> np.ndarray:
    """Omega/phi/kappa (degrees) → world→camera rotation in our (OpenCV) convention.

    Photogrammetric convention (as Pix4D and most aerial software): the rotation from the
    photogrammetric camera frame (x right, y up, z backwards, i.e. looking along −z) to the
    world frame is ``M = Rx(ω) · Ry(φ) · Rz(κ)``. Our camera frame flips y and z, so
    ``R_world→camera = diag(1, −1, −1) · Mᵀ``. ω = φ = κ = 0 is a camera looking straight down.
    """
    M = _rx(math.radians(omega_deg)) @ _ry(math.radians(phi_deg)) @ _rz(math.radians(kappa_deg))
    return _FLIP_YZ @ M.T


def rotation_to_opk(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`opk_to_rotation`: world→camera (3, 3) → (ω, φ, κ) in degrees.

    φ is in [−90°, 90°]; at φ = ±90° (gimbal lock) κ is set to 0.
    """
    M = (_FLIP_YZ @ np.asarray(R, dtype=np.float64)).T
    # M = Rx(ω) Ry(φ) Rz(κ): M[0,2] = sin φ, M[1,2] = −sin ω cos φ, M[2,2] = cos ω cos φ,
    # M[0,0] = cos φ cos κ, M[0,1] = −cos φ sin κ.
    phi = math.asin(max(-1.0, min(1.0, M[0, 2])))
    if abs(math.cos(phi)) > 1e-9:
        omega = math.atan2(-M[1, 2], M[2, 2])
        kappa = math.atan2(-M[0, 1], M[0, 0])
    else:
        omega = math.atan2(M[2, 1], M[1, 1])
        kappa = 0.0
    return math.degrees(omega), math.degrees(phi), math.degrees(kappa)
