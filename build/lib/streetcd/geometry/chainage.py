"""Chainage: where a point lies along a street's centre line (ours; issue 17).

A city's road network gives each street a centre line; a fixed piece of it (from chainage
``k·L`` to ``(k+1)·L`` metres from the line's first vertex) is the same stretch of street
every night, whatever images arrive. Pure array kernels on polylines in the CRS.
"""

from __future__ import annotations

import numpy as np


def project_on_polyline(points: np.ndarray, line: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nearest point of a polyline to each of ``points``: its chainage and distance.

    points : (N, 2) float64, metres (CRS x/y). line : (K, 2) float64, metres, K ≥ 2 vertices.
    Returns ``(chainage, distance)``: (N,) metres along the line from its first vertex, and
    (N,) metres from the point to the line. Ties go to the earlier part of the line.
    """
    p = np.asarray(points, np.float64).reshape(-1, 2)
    v = np.asarray(line, np.float64).reshape(-1, 2)
    a, d = v[:-1], np.diff(v, axis=0)  # (S, 2) part starts and directions
    length = np.hypot(d[:, 0], d[:, 1])
    start = np.concatenate([[0.0], np.cumsum(length)[:-1]])
    sq = np.maximum(length**2, 1e-300)  # a zero-length part: t = 0
    # t (N, S): the foot of each point on each part, clamped to the part
    t = np.clip(((p[:, None, :] - a[None]) * d[None]).sum(axis=2) / sq, 0.0, 1.0)
    foot = a[None] + t[..., None] * d[None]
    dist = np.hypot(*(p[:, None, :] - foot).transpose(2, 0, 1))
    best = np.argmin(dist, axis=1)  # the first minimum: ties to the earlier part
    rows = np.arange(len(p))
    return start[best] + t[rows, best] * length[best], dist[rows, best]
