"""Triangulation and rasterisation options for the view surface (paper §3.2–3.3), timed.

Usage: ``python benchmarks/surface_choices.py [--runs 5] [--sizes 2mp,12mp]``

Builds a synthetic street (a façade with window texture, a ground plane, parked boxes and a
pole, sampled at 900 pts/m² with MLS-like jitter) seen from 13 m, projects it, z-buffers it
with the WWZB (eq. 1–3, with the metric test, as ``surface_for_view`` runs it) and times on ONE
core (OpenCV and BLAS threads set to 1; numba kernels are serial), after a warm-up, the median
CPU time of ``--runs`` runs:

* triangulation (with the paper's depth-jump and edge filters) of the z-buffered points by
  scipy's Delaunay (qhull), OpenCV's Subdiv2D, and streetcd's grid Voronoi dual at 5 px cells
  (the z-buffer window) and at 1 px cells;
* rasterisation of the same triangles into depth / class rasters: streetcd's numba kernel and
  a vectorised numpy version;
* the weighted z-buffer as the paper writes it and with the metric test, with the number of
  occluded (> 0.3 m behind the ray-cast surface) and visible points each z-buffer keeps;
* the whole ``surface_for_view``.

Quality columns compare each triangulation's depth raster with the one from scipy's Delaunay:
``cover`` = covered pixels / pixels Delaunay covers, ``miss`` = share of Delaunay's pixels left
empty, ``|dz|>1cm`` = share of commonly covered pixels whose depth differs by more than 1 cm.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial import Delaunay  # noqa: E402

from streetcd import classes as cls  # noqa: E402
from streetcd.config import DetectParams, scale_px  # noqa: E402
from streetcd.detect.surface import _triangulate, rasterise, surface_for_view  # noqa: E402
from streetcd.detect.zbuffer import block_zbuffer, project_cloud, weighted_zbuffer  # noqa: E402
from streetcd.geometry.camera import look_at  # noqa: E402
from streetcd.types import Intrinsics

cv2.setNumThreads(1)

SIZES = {"2mp": (1920, 1080), "12mp": (4000, 3000)}
HFOV_DEG = 70.0
DENSITY = 900.0  # points per m²


# --- synthetic street ----------------------------------------------------------------------


def _sample(rng, density, corner, e1, e2):
    """MLS-like sampling of a parallelogram: a jittered lattice at ``density`` pts/m²."""
    e1, e2 = np.asarray(e1, float), np.asarray(e2, float)
    step = 1.0 / np.sqrt(density)
    n1 = max(int(np.linalg.norm(e1) / step), 1)
    n2 = max(int(np.linalg.norm(e2) / step), 1)
    s, t = np.meshgrid((np.arange(n1) + 0.5) / n1, (np.arange(n2) + 0.5) / n2)
    s = (s.ravel() + rng.normal(0, 0.25 / n1, s.size))[:, None]
    t = (t.ravel() + rng.normal(0, 0.25 / n2, t.size))[:, None]
    return np.asarray(corner, float) + s * e1 + t * e2


def _box(rng, density, lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    dx, dy, dz = hi - lo
    faces = [
        (lo, [dx, 0, 0], [0, 0, dz]),
        (lo + [0, dy, 0], [dx, 0, 0], [0, 0, dz]),
        (lo, [0, dy, 0], [0, 0, dz]),
        (lo + [dx, 0, 0], [0, dy, 0], [0, 0, dz]),
        (lo + [0, 0, dz], [dx, 0, 0], [0, dy, 0]),
    ]
    return np.vstack([_sample(rng, density, *f) for f in faces])


# Axis-aligned boxes (lo, hi, class); the façade and the ground are boxes of zero thickness.
SCENE = [
    ((-12, 12, 0), (12, 12, 14), cls.BUILDING),
    ((-12, 0.5, 0), (12, 12, 0), cls.ROAD),
    ((-7, 5, 0), (-2.5, 6.8, 1.5), cls.CAR),
    ((1, 5.2, 0), (5.5, 7.0, 1.6), cls.CAR),
    ((6, 9, 0), (8.5, 10.5, 2.8), cls.FURNITURE),
    ((-1.1, 8, 0), (-0.9, 8.2, 6), cls.POLE),
]


def street(seed: int = 0):
    """(xyz (N, 3) float64 m, classes (N,) uint8): the visible faces of SCENE, sampled."""
    rng = np.random.default_rng(seed)
    parts = []
    for lo, hi, c in SCENE:
        flat = np.asarray(hi, float) - lo
        if (flat == 0).any():  # façade or ground
            axes = [np.eye(3)[i] * flat[i] for i in range(3) if flat[i] > 0]
            parts.append((_sample(rng, DENSITY, lo, *axes), c))
        else:
            parts.append((_box(rng, DENSITY * (4 if c == cls.POLE else 1), lo, hi), c))
    xyz = np.vstack([p for p, _ in parts])
    labels = np.concatenate([np.full(len(p), c, np.uint8) for p, c in parts])
    return xyz, labels


def camera(size: str) -> Intrinsics:
    w, h = SIZES[size]
    f = (w / 2) / np.tan(np.radians(HFOV_DEG / 2))
    return Intrinsics(w, h, f, f, (w - 1) / 2, (h - 1) / 2)


def render(intr, pose, rng, rows=256):
    """The image of SCENE by ray casting: class colours, façade windows, noise, sky.

    Returns the image (H, W, 3) uint8 and the true depth (H, W) float64 metres (inf = sky).
    """
    palette = np.zeros((256, 3), np.int16)
    palette[0] = (150, 190, 230)  # sky
    palette[cls.BUILDING] = (180, 160, 140)
    palette[cls.ROAD] = (90, 90, 95)
    palette[cls.CAR] = (30, 60, 150)
    palette[cls.FURNITURE] = (60, 140, 60)
    palette[cls.POLE] = (200, 200, 40)
    img = np.empty((intr.height, intr.width, 3), np.uint8)
    true_depth = np.empty((intr.height, intr.width))
    for r0 in range(0, intr.height, rows):
        v, uu = np.mgrid[r0 : min(r0 + rows, intr.height), 0 : intr.width]
        rays = (
            np.stack([(uu - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(uu.shape)], -1)
            @ pose.R
        )  # world directions
        best = np.full(uu.shape, np.inf)
        label = np.zeros(uu.shape, np.uint8)
        with np.errstate(divide="ignore", invalid="ignore"):
            for lo, hi, c in SCENE:
                t1 = (np.asarray(lo) - pose.center) / rays
                t2 = (np.asarray(hi) - pose.center) / rays
                near = np.nanmax(np.minimum(t1, t2), axis=-1)
                far = np.nanmin(np.maximum(t1, t2), axis=-1)
                hit = (near <= far + 1e-9) & (near > 0) & (near < best)
                best[hit], label[hit] = near[hit], c
        x = pose.center + rays * best[..., None]
        block = palette[label] + rng.integers(-3, 4, label.shape + (3,))
        window = (
            (label == cls.BUILDING) & (np.mod(x[..., 0], 3) > 1) & (np.mod(x[..., 2], 3.5) > 1.5)
        )
        block[window] = (40, 50, 60)
        img[r0 : r0 + len(v)] = np.clip(block, 0, 255)
        true_depth[r0 : r0 + len(v)] = best  # rays have camera z = 1, so t is the depth
    return img, true_depth


# --- triangulation options -----------------------------------------------------------------


def _filter(tris, uv, depth, params, width):
    z = depth[tris]
    edge = scale_px(params.max_edge_px, width)
    p = uv[tris]
    lengths = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2)
    keep = (z.max(1) - z.min(1) <= params.max_depth_jump_m) & (lengths.max(1) <= edge)
    return tris[keep].astype(np.int32)


def tri_scipy(uv, depth, shape, params):
    return _filter(Delaunay(uv).simplices, uv, depth, params, shape[1])


def tri_subdiv(uv, depth, shape, params):
    h, w = shape
    sub = cv2.Subdiv2D((-1, -1, w + 2, h + 2))
    p32 = uv.astype(np.float32)
    sub.insert(p32)
    t = sub.getTriangleList().reshape(-1, 3, 2)
    inside = ((t >= -1) & (t[..., :1] < w + 1) & (t[..., 1:] < h + 1)).all(axis=(1, 2))
    t = t[inside]
    # map vertex coordinates back to point indices (Subdiv2D gives coordinates only)
    key = p32.view(np.int32).astype(np.int64)
    key = (key[:, 0] << 32) | (key[:, 1] & 0xFFFFFFFF)
    order = np.argsort(key)
    tk = t.reshape(-1, 2).view(np.int32).astype(np.int64)
    tk = (tk[:, 0] << 32) | (tk[:, 1] & 0xFFFFFFFF)
    idx = order[np.searchsorted(key, tk, sorter=order)].reshape(-1, 3)
    return _filter(idx, uv, depth, params, w)


def tri_grid(cell):
    def run(uv, depth, shape, params):
        return _triangulate(uv, depth, shape, shape[1], params, cell)

    return run


# --- rasterisation options -----------------------------------------------------------------


def raster_numba(uv, depth, labels, tris, shape):
    return rasterise(uv, depth, labels, tris, shape).depth


def raster_numpy(uv, depth, labels, tris, shape, chunk=200_000):
    """Vectorised barycentric inverse-depth rasterisation (pixels of each bounding box)."""
    h, w = shape
    inv = np.zeros(h * w)
    for s in range(0, len(tris), chunk):
        t = tris[s : s + chunk]
        p = uv[t]
        lo = np.maximum(np.ceil(p.min(1)).astype(np.int64), 0)
        hi = np.minimum(np.floor(p.max(1)).astype(np.int64), [w - 1, h - 1])
        nx, ny = np.maximum(hi - lo + 1, 0).T
        count = nx * ny
        tid = np.repeat(np.arange(len(t)), count)
        k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
        col = lo[tid, 0] + k % nx[tid]
        row = lo[tid, 1] + k // nx[tid]
        a, b, c = p[tid, 0], p[tid, 1], p[tid, 2]
        area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        wa = ((b[:, 0] - col) * (c[:, 1] - row) - (b[:, 1] - row) * (c[:, 0] - col)) / area
        wb = ((c[:, 0] - col) * (a[:, 1] - row) - (c[:, 1] - row) * (a[:, 0] - col)) / area
        wc = 1 - wa - wb
        ok = (wa >= -1e-9) & (wb >= -1e-9) & (wc >= -1e-9)
        iz = 1.0 / depth[t[tid]]
        zi = (wa * iz[:, 0] + wb * iz[:, 1] + wc * iz[:, 2])[ok]
        np.maximum.at(inv, (row * w + col)[ok], zi)
    with np.errstate(divide="ignore"):
        out = np.where(inv > 0, 1.0 / inv, np.nan)
    return out.reshape(h, w).astype(np.float32)


# --- timing --------------------------------------------------------------------------------


def timed(fn: Callable, runs: int):
    """Median CPU time of ``runs`` calls after a warm-up, and the last result.

    CPU time of this process (``time.process_time``), not wall time: every option runs on one
    thread, and on a shared machine wall time mostly measures the neighbours.
    """
    fn()  # warm-up (numba compile / cache load, page faults)
    times, result = [], None
    for _ in range(runs):
        t0 = time.process_time()
        result = fn()
        times.append(time.process_time() - t0)
    return statistics.median(times), result


def bench(size: str, runs: int) -> None:
    intr = camera(size)
    shape = (intr.height, intr.width)
    pose = look_at([0.0, -1.0, 2.0], [0.0, 12.0, 3.0])
    xyz, labels = street()
    image, true_depth = render(intr, pose, np.random.default_rng(1))
    params = DetectParams()
    sp = params.surface

    t_proj, pts = timed(lambda: project_cloud(xyz, labels, intr, pose, params.max_range_m), runs)
    t_bw, b5 = timed(lambda: block_zbuffer(pts.uv, pts.depth, shape, 5), runs)
    t_paper, keep_paper = timed(
        lambda: weighted_zbuffer(pts.uv, pts.depth, image, params.zbuffer), runs
    )
    t_ww, keep = timed(
        lambda: weighted_zbuffer(pts.uv, pts.depth, image, params.zbuffer, focal_px=intr.fx),
        runs,
    )
    kept = pts.take(keep)
    uv, depth = kept.uv, kept.depth
    print(
        f"\n## {size}: {intr.width}x{intr.height}, cloud {len(xyz):,} pts, in view "
        f"{len(pts):,}, BWZB(5) {len(b5):,}, WWZB {len(kept):,} (edge filter "
        f"{scale_px(sp.max_edge_px, intr.width):.1f} px)"
    )
    print(
        f"project {t_proj:.3f} s | block z-buffer {t_bw:.3f} s | weighted z-buffer: paper "
        f"{t_paper:.3f} s, + metric test {t_ww:.3f} s"
    )
    # z-buffer quality: a point is occluded when it lies > 0.3 m behind the true surface
    col, row = np.floor(pts.uv + 0.5).astype(int).T
    occluded = pts.depth > true_depth[row, col] + 0.3
    b10 = block_zbuffer(pts.uv, pts.depth, shape, 10)
    print(
        "\n| points | in view | BWZB w=5 | BWZB w=10 | WWZB paper | WWZB + metric |"
        "\n|---|---|---|---|---|---|"
    )
    for name, sel in (("occluded (back-face)", occluded), ("visible", ~occluded)):
        counts = [sel.sum(), sel[b5].sum(), sel[b10].sum(), sel[keep_paper].sum(), sel[keep].sum()]
        print(f"| {name} | " + " | ".join(f"{c:,}" for c in counts) + " |")

    options = {
        "scipy Delaunay (qhull)": tri_scipy,
        "cv2.Subdiv2D": tri_subdiv,
        "grid Voronoi dual, 5 px": tri_grid(5),
        "grid Voronoi dual, 1 px": tri_grid(1),
    }
    print("\n| triangulation | time s | x scipy | triangles | cover | miss | |dz|>1cm |")
    print("|---|---|---|---|---|---|---|")
    ref_depth, ref_time = None, None
    for name, fn in options.items():
        t, tris = timed(lambda fn=fn: fn(uv, depth, shape, sp), runs)
        z = raster_numba(uv, depth, kept.classes, tris, shape)
        if ref_depth is None:
            ref_depth, ref_time = z, t
        rv, zv = ~np.isnan(ref_depth), ~np.isnan(z)
        both = rv & zv
        cover = zv.sum() / rv.sum()
        miss = (rv & ~zv).sum() / rv.sum()
        bad = (np.abs(z[both] - ref_depth[both]) > 0.01).mean()
        print(
            f"| {name} | {t:.3f} | {t / ref_time:.2f} | {len(tris):,} | {cover:.4f} | "
            f"{miss:.4f} | {bad:.4f} |"
        )

    tris = tri_grid(5)(uv, depth, shape, sp)
    print("\n| rasterisation (grid-dual triangles) | time s | x numba |")
    print("|---|---|---|")
    t_nb, z_nb = timed(lambda: raster_numba(uv, depth, kept.classes, tris, shape), runs)
    t0 = time.process_time()  # pure numpy, nothing to warm up; one run is enough to compare
    z_np = raster_numpy(uv, depth, kept.classes, tris, shape)
    t_np = time.process_time() - t0
    same = np.allclose(z_nb, z_np, equal_nan=True, atol=1e-4)
    print(f"| numba kernel (depth + class) | {t_nb:.3f} | 1.00 |")
    print(f"| numpy vectorised (depth only) | {t_np:.3f} | {t_np / t_nb:.1f} | same: {same} |")

    t_all, (surf, _) = timed(lambda: surface_for_view(xyz, labels, image, intr, pose, params), runs)
    print(
        f"\nsurface_for_view (project → WWZB → grid dual 5 px → raster): {t_all:.3f} s, "
        f"surface on {surf.valid.mean():.1%} of the image"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--sizes", default="2mp,12mp")
    args = ap.parse_args()
    print(
        f"one core; median of {args.runs} runs after a warm-up; numba {__import__('numba').__version__}, "
        f"scipy {__import__('scipy').__version__}, opencv {cv2.__version__}"
    )
    for size in args.sizes.split(","):
        bench(size.strip(), args.runs)


if __name__ == "__main__":
    main()
