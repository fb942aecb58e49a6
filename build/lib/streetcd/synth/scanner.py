"""Mobile laser scanner simulation: profile scanners on a vehicle driving down the road.

Two profile scanners (as on a Riegl VMX-250) sit on the vehicle roof, their scan planes
vertical and turned ±``yaw_deg`` from the across-street direction, so surfaces facing along
the street also get points. Each sweeps a full circle every ``profile_spacing_m`` of
travel; every ray keeps its first hit, so surfaces hidden from the road get nothing and
density falls with range. Range noise is Gaussian along the ray,
σ(r) = clip(0.005 + 0.001 r, 0.005, 0.02) m.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from streetcd.synth.raycast import cast
from streetcd.synth.render import point_albedo
from streetcd.synth.scene import EPOCH1, Street


@dataclass(frozen=True)
class ScanParams:
    """Scanner geometry. Densities on a façade at 10 m: ~ 1 / (r·step · spacing / 2)."""

    profile_spacing_m: float = 0.09  # per scanner; two scanners halve it
    angle_step_deg: float = 0.3
    yaw_deg: float = 30.0
    height_m: float = 2.4
    speed_m_s: float = 8.0
    min_range_m: float = 1.5
    max_range_m: float = 80.0
    gps_time_start_s: float = 302_400.0  # GPS seconds of the week (Monday 12:00)

    def noise_sigma_m(self, r: np.ndarray) -> np.ndarray:
        return np.clip(0.005 + 0.001 * r, 0.005, 0.02)

    def as_dict(self) -> dict:
        return {
            "profile_spacing_m": self.profile_spacing_m,
            "angle_step_deg": self.angle_step_deg,
            "scanners": 2,
            "yaw_deg": [self.yaw_deg, -self.yaw_deg],
            "height_m": self.height_m,
            "speed_m_s": self.speed_m_s,
            "range_m": [self.min_range_m, self.max_range_m],
            "noise_sigma_m": "clip(0.005 + 0.001 * range_m, 0.005, 0.02)",
        }


def scan_street(
    street: Street,
    x0: float,
    x1: float,
    y: float,
    sun_street: np.ndarray,
    rng: np.random.Generator,
    params: ScanParams = ScanParams(),
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, np.ndarray]:
    """Scan epoch 1 of ``street`` driving along y = ``y`` from x0 to x1 (street frame).

    Returns, ordered by GPS time: ``xyz`` (N, 3) float64 street frame metres, ``cls`` (N,)
    uint8, ``rgb`` (N, 3) uint16, ``intensity`` (N,) uint16, ``gps_time`` (N,) float64 s,
    ``obj`` (N,) int32 object ids.
    """
    grid = street.grids[EPOCH1]
    theta = np.deg2rad(np.arange(-180.0, 180.0, params.angle_step_deg))
    yaws = np.deg2rad([params.yaw_deg, -params.yaw_deg])
    # one profile: both scanners' rays (2·A, 3); the scanner origin moves along x
    dirs = np.concatenate(
        [
            np.column_stack([np.cos(theta) * np.sin(a), np.cos(theta) * np.cos(a), np.sin(theta)])
            for a in yaws
        ]
    )
    frac = np.tile(np.arange(len(theta)) / len(theta), 2)  # time within a sweep
    xs = np.arange(x0, x1, params.profile_spacing_m)
    chunk = max(1, 400_000 // len(dirs))
    parts: list[dict[str, np.ndarray]] = []
    for start in range(0, len(xs), chunk):
        px = xs[start : start + chunk]
        origins = np.zeros((len(px), len(dirs), 3))
        origins[:, :, 0] = px[:, None]
        origins[:, :, 1] = y
        origins[:, :, 2] = params.height_m
        d = np.broadcast_to(dirs, origins.shape).reshape(-1, 3)
        t, k, n = cast(grid, origins.reshape(-1, 3), d, params.max_range_m)
        ok = (k >= 0) & (t >= params.min_range_m)
        t, k, n = t[ok], grid_rows(street, k[ok]), n[ok]
        o = origins.reshape(-1, 3)[ok]
        dd = d[ok]
        rt = t + rng.standard_normal(len(t)) * params.noise_sigma_m(t)
        xyz = o + rt[:, None] * dd
        surface = o + t[:, None] * dd
        time = (
            params.gps_time_start_s
            + (o[:, 0] - x0) / params.speed_m_s
            + np.tile(frac, len(px))[ok] * params.profile_spacing_m / params.speed_m_s
        )
        alb = point_albedo(surface, n, k, street.mat, street.color, street.tex, street.params)
        cos_sun = np.clip(n @ sun_street, 0.0, None)
        light = (0.55 + 0.6 * cos_sun)[:, None] * alb
        rgb8 = np.clip(light, 0, 1) ** (1 / 2.2) * 255.0
        incidence = np.abs(np.einsum("ij,ij->i", n, dd))
        refl = np.sqrt(alb.mean(axis=1)) * (0.3 + 0.7 * incidence) / (1.0 + 0.01 * t)
        parts.append(
            {
                "xyz": xyz,
                "cls": street.cls[k],
                "rgb": (np.round(rgb8).astype(np.uint16) * 257).astype(np.uint16),
                "intensity": np.clip(refl * 65535.0, 0, 65535).astype(np.uint16),
                "gps_time": time,
                "obj": street.obj[k],
            }
        )
        if progress is not None:
            progress(min(start + chunk, len(xs)), len(xs))
    out = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    order = np.argsort(out["gps_time"], kind="stable")  # the two scanners fire together
    return {key: v[order] for key, v in out.items()}


def grid_rows(street: Street, k: np.ndarray) -> np.ndarray:
    """Epoch-1 grid primitive numbers → rows of the street's primitive arrays."""
    return street.index[EPOCH1][k]
