"""Write a synthetic scene folder: epoch-1 LAZ archive, epoch-2 images, poses, ground truth.

Folder layout: see ``docs/CONTRACTS.md`` ("Synthetic scene folder"). Everything is a
function of the seed: the same seed gives byte-identical files (fixed LAS header date,
no timings in the manifest).

Ground truth, per image (true poses, rendered by :func:`streetcd.synth.render_depth`):

* ``mask`` 255 where the visible epoch-2 surface belongs to an added or moved-to object, or
  the visible epoch-1 surface to a removed or moved-from object (a replaced railing counts
  as removed, the hedge that replaces it as added);
* ``instances`` the change instance id (uint16) at those pixels;
* ``dontcare`` 255 where either epoch's visible surface is a disturbance that differs
  between the epochs (a parked car that came or went, a pedestrian, grown foliage) and the
  pixel is not a change: evaluations should ignore those pixels.

``manifest.json`` keys (beyond the contract's): ``generator`` (what :func:`load_scene`
needs), ``pose_noise.achieved_rms_px`` (measured on every 8th pixel of each view's visible
surface; per view in ``views[i].pose_error_rms_px``), ``scan`` (scanner model, noise and
point count), ``images`` (size, focal length), ``objects[i].bbox_local`` (local frame
bounds), ``object_counts`` (objects per type, for per-type tables such as the paper's
Table 2), ``changes[i].views`` (images that see it), ``views[i].changed_pixels`` and
``visible_objects`` (ids with at least 20 epoch-2 pixels), ``disturbances``, ``streets``.

A street of another kind (:mod:`streetcd.synth.kinds`: pedestrian paths, plain objects, a
cloud without colours, sparse, other class codes) adds ``street_kind`` (its settings) and,
with other codes, ``class_codes`` (scheme, roles, config file) to the manifest, and writes
``streetcd.yaml`` with the class map; the default street's files are unchanged.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import replace
from datetime import date
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from streetcd import classes
from streetcd.errors import InputError
from streetcd.geometry.camera import backproject, project
from streetcd.io.las import write_las
from streetcd.io.poses import write_colmap_text, write_opk_csv
from streetcd.synth.build import build_city_scene, build_street_scene, camera_strip
from streetcd.synth.kinds import StreetKind, resolve_kind
from streetcd.synth.raycast import footprints
from streetcd.synth.render import cast_view, shade_view
from streetcd.synth.scanner import ScanParams, scan_street
from streetcd.synth.scene import BOTH, EPOCH1, EPOCH2, Scene
from streetcd.types import Pose, View

Progress = Callable[[int, int], None]
LAS_DATE = date(2023, 5, 8)  # fixed header date: files are reproducible byte for byte
JPEG_QUALITY = 92
CLOUD_TILE_M = 50.0  # the archive is cut into files every 50 m of trajectory
IMAGE_TIME_START_S = 1_000_000.0  # epoch-2 image times, seconds
STREET_SCAN = ScanParams()
# the city demo scans more coarsely (~270 pts/m² at 10 m instead of ~420) to stay small
CITY_SCAN = ScanParams(profile_spacing_m=0.12, angle_step_deg=0.35)
CONFIG_NAME = "streetcd.yaml"  # the class map of a street written with other codes
DEFAULT_KIND = StreetKind()


def generate_street(
    out_dir: str | Path,
    *,
    seed: int = 0,
    n_images: int = 24,
    size: tuple[int, int] = (1920, 1080),
    pose_noise_px: float = 0.0,
    length_m: float = 150.0,
    changes: bool = True,
    progress: Progress | None = None,
    kind: str | StreetKind | None = None,
    path: str | None = None,
    plain: bool | None = None,
    colour: bool | None = None,
    density: float | None = None,
    point_spacing_m: float | None = None,
    class_codes: str | None = None,
) -> Path:
    """Generate one street with ground truth into ``out_dir``; returns the manifest path.

    ``changes=False`` gives an unchanged street: epoch 2 has exactly epoch 1's geometry,
    without disturbances either (no cars that come or go, no pedestrians, same foliage),
    so every truth mask and don't-care mask is empty.

    ``kind``: a preset of :data:`streetcd.synth.kinds.PRESETS` (or a StreetKind); ``path``,
    ``plain``, ``colour``, ``density``, ``point_spacing_m``, ``class_codes`` override its
    settings (see :mod:`streetcd.synth.kinds`). Without any, today's default street.
    """
    _check_args(n_images, size, pose_noise_px)
    sk = resolve_kind(
        kind,
        path=path,
        plain=plain,
        colour=colour,
        density=density,
        point_spacing_m=point_spacing_m,
        class_codes=class_codes,
    )
    scene = build_street_scene(seed, length_m, changes, plain=sk.plain)
    rng = np.random.default_rng(seed)
    cam_rng = rng.spawn(4)[3]  # independent of the scene's streams
    views = camera_strip(scene, 0, n_images, size, cam_rng, path=sk.path)
    return _write(out_dir, scene, [views], rng, pose_noise_px, progress, STREET_SCAN, sk)


def generate_city(
    out_dir: str | Path,
    *,
    seed: int = 0,
    n_streets: int = 3,
    images_per_street: int = 8,
    size: tuple[int, int] = (960, 540),
    pose_noise_px: float = 0.0,
    length_m: float = 50.0,
    changes: bool = True,
    progress: Progress | None = None,
    kind: str | StreetKind | None = None,
    **settings: Any,
) -> Path:
    """A small city: ``n_streets`` streets in one CRS, one archive, one image folder and
    one pose set; with ``changes`` every street but the second has changes. ``kind`` and
    ``settings`` as for :func:`generate_street`."""
    _check_args(images_per_street, size, pose_noise_px)
    sk = resolve_kind(kind, **settings)
    scene = build_city_scene(seed, n_streets, length_m, changes, plain=sk.plain)
    rng = np.random.default_rng(seed)
    cam_rngs = rng.spawn(4 + n_streets)[4:]
    views = [
        camera_strip(
            scene, s, images_per_street, size, cam_rngs[s], prefix=f"S{s}_IMG", path=sk.path
        )
        for s in range(n_streets)
    ]
    return _write(out_dir, scene, views, rng, pose_noise_px, progress, CITY_SCAN, sk)


def _check_args(n_images: int, size: tuple[int, int], pose_noise_px: float) -> None:
    if n_images < 1:
        raise InputError(f"number of images = {n_images} must be >= 1")
    if len(size) != 2 or min(size) < 16:
        raise InputError(f"image size = {size} must be (width, height), each >= 16 px")
    if not (math.isfinite(pose_noise_px) and pose_noise_px >= 0):
        raise InputError(f"pose_noise_px = {pose_noise_px} must be a finite number >= 0")


# --- the writer ----------------------------------------------------------------------------


def _write(
    out_dir: str | Path,
    scene: Scene,
    street_views: list[list[View]],
    rng: np.random.Generator,
    pose_noise_px: float,
    progress: Progress | None,
    scan: ScanParams = STREET_SCAN,
    kind: StreetKind = DEFAULT_KIND,
) -> Path:
    out = Path(out_dir)
    for sub in ("cloud", "images", "poses/colmap", "truth"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    scan = _scan_of(kind, scan)
    scan_rng, image_rng, noise_rng = rng.spawn(3)
    views = [v for vs in street_views for v in vs]
    n_scan = sum(
        math.ceil((s.layout["length_m"] + 6.0) / scan.profile_spacing_m) for s in scene.streets
    )
    total = n_scan + len(views) + 1
    done = [0]

    def tick(k: int = 1) -> None:
        done[0] += k
        if progress is not None:
            progress(min(done[0], total), total)

    cloud_files, n_points = _write_cloud(out, scene, scan, scan_rng, tick, kind)
    view_rngs = image_rng.spawn(len(views))
    noise_rngs = noise_rng.spawn(len(views))
    # per-view error targets vary (log-normal) around an overall RMS of pose_noise_px
    spread = noise_rng.lognormal(0.0, 0.3, len(views))
    targets = pose_noise_px * spread / np.sqrt(np.mean(spread**2))
    change_of = scene.change_of_object()
    disturbing = scene.disturbance_objects()
    written, view_entries = [], []
    sq_err, n_err = 0.0, 0
    times = IMAGE_TIME_START_S + 2.0 * np.arange(len(views))
    street_of_view = [s for s, vs in enumerate(street_views) for _ in vs]
    for i, view in enumerate(views):
        view = View(view.name, view.intrinsics, view.pose, None, float(times[i]))
        local = view.local(scene.origin)
        depth, street_of, prim, normal = cast_view(scene, local, EPOCH2)
        radiance = shade_view(scene, local, depth, street_of, prim, normal)
        image = _develop(radiance, view_rngs[i])
        _imwrite(
            out / "images" / view.name, image[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]
        )
        inst, dontcare, visible = _truth(scene, local, street_of, prim, change_of, disturbing)
        stem = Path(view.name).stem
        _imwrite(out / "truth" / f"{stem}.mask.png", np.where(inst > 0, 255, 0).astype(np.uint8))
        _imwrite(out / "truth" / f"{stem}.instances.png", inst)
        _imwrite(out / "truth" / f"{stem}.dontcare.png", dontcare)
        noisy, err = _perturb(local, depth, float(targets[i]), noise_rngs[i])
        sq_err += float(np.sum(err**2))
        n_err += len(err)
        written.append(
            View(
                view.name,
                view.intrinsics,
                Pose.from_center(noisy.pose.R, noisy.pose.center + scene.origin),
                None,
                view.time,
            )
        )
        ids, counts = np.unique(inst[inst > 0], return_counts=True)
        view_entries.append(
            {
                "name": view.name,
                "street": street_of_view[i],
                "image": f"images/{view.name}",
                "mask": f"truth/{stem}.mask.png",
                "instances": f"truth/{stem}.instances.png",
                "dontcare": f"truth/{stem}.dontcare.png",
                "changed_instances": [int(x) for x in ids],
                "changed_pixels": {str(int(a)): int(b) for a, b in zip(ids, counts, strict=True)},
                "dontcare_pixels": int(np.count_nonzero(dontcare)),
                "visible_objects": visible,
                "pose_error_rms_px": round(float(np.sqrt(np.mean(err**2))) if len(err) else 0.0, 4),
            }
        )
        views[i] = view
        tick()
    crs = scene.crs
    write_colmap_text(out / "poses" / "colmap", written, crs=crs)
    write_opk_csv(out / "poses" / "poses_opk.csv", written, crs)
    write_opk_csv(out / "truth" / "poses_true_opk.csv", views, crs)
    rms = math.sqrt(sq_err / n_err) if n_err else 0.0
    manifest = _manifest(
        scene, street_views, views, view_entries, cloud_files, n_points, scan, pose_noise_px, rms
    )
    if not kind.is_default:
        _describe_kind(out, manifest, kind)
    # the manifest comes last and atomically: its presence means the folder is complete
    path = out / "manifest.json"
    tmp = out / ".manifest.json.tmp"
    tmp.write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    tmp.replace(path)
    tick()
    return path


def _imwrite(path: Path, image: np.ndarray, params: list[int] | None = None) -> None:
    if not cv2.imwrite(str(path), image, params or []):
        raise OSError(f"cannot write image {path}")


def _scan_of(kind: StreetKind, scan: ScanParams) -> ScanParams:
    """The scanner of a street kind: with ``point_spacing_m`` s, rays every s / 10 m rad
    (s apart at 10 m) and each of the two scanners' profiles every 2 s along the road."""
    s = kind.point_spacing_m
    if s is None:
        return scan
    return replace(scan, profile_spacing_m=2.0 * s, angle_step_deg=math.degrees(s / 10.0))


def _describe_kind(out: Path, manifest: dict[str, Any], kind: StreetKind) -> None:
    """Manifest entries (and ``streetcd.yaml``) of a street that is not the default kind."""
    manifest["street_kind"] = kind.as_dict()
    manifest["scan"]["density"] = kind.density
    if kind.path != "vehicle":
        manifest["images"]["overlap_at_far_facade"] = None  # the formula assumes the strip
    if kind.class_codes is None:
        return
    scheme = kind.scheme()
    if scheme is None:  # every point unclassified: the detector's defaults are the config
        manifest["classes"] = {"1": "unclassified"}
        manifest["class_codes"] = {"scheme": kind.class_codes, "roles": {}, "config": None}
        return
    (out / CONFIG_NAME).write_text(scheme.config_text(), encoding="utf-8")
    manifest["classes"] = scheme.names()
    manifest["class_codes"] = {
        "scheme": scheme.name,
        "roles": {r: list(c) for r, c in scheme.roles.items()},
        "by_type": dict(scheme.by_type),
        "config": CONFIG_NAME,
    }


def _write_cloud(
    out: Path,
    scene: Scene,
    scan: ScanParams,
    rng: np.random.Generator,
    tick: Callable[[int], None],
    kind: StreetKind = DEFAULT_KIND,
) -> tuple[list[str], int]:
    files: list[str] = []
    n_total = 0
    rngs = rng.spawn(len(scene.streets))
    # spawned after the streets' streams, and only when thinning: the default is untouched
    thin = rng.spawn(1)[0] if kind.density < 1.0 else None
    codes = kind.scheme()
    objects = {o["id"]: o for o in scene.objects}
    last = [0]
    for s, street in enumerate(scene.streets):
        L = street.layout["length_m"]
        last[0] = 0

        def step(done: int, total: int) -> None:
            tick(done - last[0])
            last[0] = done

        sun = street.rotation.T @ scene.sun
        pts = scan_street(
            street, -3.0, L + 3.0, street.layout["scanner_y_m"], sun, rngs[s], scan, step
        )
        if thin is not None:  # a sparser scanner: keep a random share of the points
            keep = thin.random(len(pts["gps_time"])) < kind.density
            pts = {key: v[keep] for key, v in pts.items()}
        if codes is None:
            cls = np.full(len(pts["cls"]), classes.UNCLASSIFIED, np.uint8)
        elif kind.class_codes is None:
            cls = pts["cls"]
        else:
            cls = codes.codes(pts["cls"], pts["obj"], objects)
        along = (pts["gps_time"] - scan.gps_time_start_s) * scan.speed_m_s  # metres driven
        tile = np.floor(along / CLOUD_TILE_M).astype(int)
        xyz_local = street.to_local(pts["xyz"])
        for k in np.unique(tile):
            m = tile == k
            name = f"cloud/{street.name}_{k:03d}.laz"
            write_las(
                out / name,
                xyz_local[m],
                cls[m],
                origin=scene.origin,
                intensity=pts["intensity"][m],
                rgb=pts["rgb"][m] if kind.colour else None,
                gps_time=pts["gps_time"][m] + 1000.0 * s,
                crs=scene.crs,
                creation_date=LAS_DATE,
                point_format=7 if kind.colour else 6,
            )
            files.append(name)
        n_total += len(xyz_local)
    return files, n_total


_GAMMA_LUT = (np.linspace(0.0, 1.0, 4096) ** (1 / 2.2) * 255.0).astype(np.float32)


def _develop(radiance: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Linear radiance (H, W, 3) float32 → 8-bit sRGB (H, W, 3) uint8 like a camera would:
    exposure and white-balance jitter, vignetting, gamma, lens blur, sensor noise."""
    h, w = radiance.shape[:2]
    gain = 0.5 * float(rng.uniform(0.85, 1.15))
    wb = (gain * rng.uniform(0.95, 1.05, 3)).astype(np.float32)
    yy = ((np.arange(h, dtype=np.float32) - h / 2) / (h / 2))[:, None]
    xx = ((np.arange(w, dtype=np.float32) - w / 2) / (w / 2))[None, :]
    vignette = 1.0 - 0.18 * (xx * xx + yy * yy) / 2.0
    x = radiance * wb[None, None, :] * vignette[:, :, None]
    idx = np.clip(x * np.float32(_GAMMA_LUT.size - 1), 0, _GAMMA_LUT.size - 1).astype(np.int32)
    x = _GAMMA_LUT[idx]  # gamma 1/2.2 through a table: the power function is slow
    x = cv2.GaussianBlur(x, (0, 0), 0.6)
    x += rng.standard_normal(x.shape, dtype=np.float32) * np.float32(1.5)
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


def _screen_box_mask(local: View, scene: Scene, epoch_only: int) -> np.ndarray:
    """(H, W) bool: pixels inside the projected bounds of primitives that exist only in
    ``epoch_only``: the only pixels where the other epoch's first hit can differ."""
    intr = local.intrinsics
    want = np.zeros((intr.height, intr.width), bool)
    for street in scene.streets:
        sel = np.flatnonzero(street.epochs == epoch_only)
        if not len(sel):
            continue
        b = footprints(street.kind[sel], street.params[sel])
        corners = np.stack([b[:, [i, j, k]] for i in (0, 3) for j in (1, 4) for k in (2, 5)], 1)
        pts = street.to_local(corners.reshape(-1, 3))
        uv, d = project(pts, intr, local.pose)
        uv, d = uv.reshape(-1, 8, 2), d.reshape(-1, 8)
        for q in range(len(sel)):
            if np.all(d[q] <= 0.05):
                continue
            if np.any(d[q] <= 0.05):  # straddles the camera plane: be conservative
                want[:] = True
                return want
            u0, v0 = np.floor(uv[q].min(0)).astype(int) - 1
            u1, v1 = np.ceil(uv[q].max(0)).astype(int) + 1
            u0, v0 = max(u0, 0), max(v0, 0)
            u1, v1 = min(u1, intr.width - 1), min(v1, intr.height - 1)
            if u0 <= u1 and v0 <= v1:
                want[v0 : v1 + 1, u0 : u1 + 1] = True
    return want


def _lookup(scene: Scene, street_of: np.ndarray, prim: np.ndarray):
    """Per pixel: object id (0 = none) and whether its primitive exists in one epoch only."""
    obj = np.zeros(prim.shape, np.int32)
    specific = np.zeros(prim.shape, bool)
    for s, street in enumerate(scene.streets):
        m = street_of == s
        obj[m] = street.obj[prim[m]]
        specific[m] = street.epochs[prim[m]] != BOTH
    return obj, specific


def _truth(
    scene: Scene, local: View, street_of2, prim2, change_of: dict[int, int], disturbing: set[int]
):
    """Instance ids (H, W) uint16, don't-care (H, W) uint8 0/255, visible object ids.

    A pixel is changed when its epoch-2 surface belongs to an added / moved-to object or
    its epoch-1 surface to a removed / moved-from one; it is don't-care (and not changed)
    when either epoch's surface there is a disturbance that differs between the epochs.
    """
    obj2, spec2 = _lookup(scene, street_of2, prim2)
    want = _screen_box_mask(local, scene, EPOCH1)
    if want.any():
        _, street_of1, prim1, _ = cast_view(scene, local, EPOCH1, want)
        obj1, spec1 = _lookup(scene, street_of1, prim1)
    else:
        obj1, spec1 = np.zeros_like(obj2), np.zeros_like(spec2)
    lut = np.zeros(max(o["id"] for o in scene.objects) + 1, np.uint16)
    for oid, instance in change_of.items():
        lut[oid] = instance
    dist = np.zeros(len(lut), bool)
    dist[list(disturbing)] = True
    to2 = np.where(spec2, lut[obj2], 0).astype(np.uint16)
    from1 = np.where(spec1, lut[obj1], 0).astype(np.uint16)
    inst = np.where(to2 > 0, to2, from1)
    dontcare = ((spec2 & dist[obj2]) | (spec1 & dist[obj1])) & (inst == 0)
    ids, counts = np.unique(obj2[obj2 > 0], return_counts=True)
    visible = [int(i) for i, c in zip(ids, counts, strict=True) if c >= 20]
    return inst, np.where(dontcare, 255, 0).astype(np.uint8), visible


def _perturb(local: View, depth: np.ndarray, target_px: float, rng: np.random.Generator):
    """Perturb a view's pose (local frame) so that scene points move by ``target_px`` RMS.

    The points are the view's own visible surface (every 8th pixel of the depth map).
    A random direction in (rotation, translation) space is scaled by a secant step, since
    the reprojection error grows linearly with a small perturbation. Returns the perturbed
    view and the per-point errors (px).
    """
    intr = local.intrinsics
    step = 8
    d = depth[::step, ::step]
    vv, uu = np.mgrid[0 : depth.shape[0] : step, 0 : depth.shape[1] : step]
    ok = np.isfinite(d)
    uv = np.column_stack([uu[ok], vv[ok]]).astype(np.float64)
    pts = backproject(uv, d[ok].astype(np.float64), intr, local.pose)
    omega = rng.standard_normal(3)
    shift = rng.standard_normal(3)
    if target_px <= 0 or len(pts) == 0:
        return local, np.zeros(len(pts))
    f = intr.fx
    z = float(np.median(d[ok]))

    def moved(k: float) -> tuple[View, np.ndarray]:
        dR, _ = cv2.Rodrigues(omega * (0.7 * k / f))
        R = dR @ local.pose.R
        pose = Pose.from_center(R, local.pose.center + shift * (0.7 * k * z / f))
        v = View(local.name, intr, pose, None, local.time)
        uv2, _ = project(pts, intr, pose)
        return v, np.linalg.norm(uv2 - uv, axis=1)

    k = target_px
    for _ in range(3):
        v, err = moved(k)
        rms = float(np.sqrt(np.mean(err**2)))
        k *= target_px / rms
    return moved(k)


def _object_bounds(scene: Scene) -> dict[int, list[float]]:
    """Object id → local-frame axis-aligned bounds [xmin, ymin, zmin, xmax, ymax, zmax]."""
    out: dict[int, list[float]] = {}
    for street in scene.streets:
        b = footprints(street.kind, street.params)
        corners = np.stack([b[:, [i, j, k]] for i in (0, 3) for j in (1, 4) for k in (2, 5)], 1)
        pts = street.to_local(corners.reshape(-1, 3)).reshape(-1, 8, 3)
        lo, hi = pts.min(1), pts.max(1)
        for oid in np.unique(street.obj):
            m = street.obj == oid
            out[int(oid)] = [round(float(v), 3) for v in (*lo[m].min(0), *hi[m].max(0))]
    return out


def _overlap(scene: Scene, street_views: list[list[View]]) -> float | None:
    """Mean overlap of consecutive images on the far façade plane of their street (0–1)."""
    values = []
    for street, views in zip(scene.streets, street_views, strict=True):
        d = street.layout["far_facade_y_m"] - street.layout["camera_y_m"]
        for a, b in zip(views, views[1:], strict=False):
            footprint = d * a.intrinsics.width / a.intrinsics.fx
            values.append(1.0 - float(np.linalg.norm(a.center - b.center)) / footprint)
    return round(float(np.mean(values)), 3) if values else None


def _manifest(
    scene: Scene,
    street_views,
    views,
    view_entries,
    cloud_files,
    n_points,
    scan: ScanParams,
    pose_noise_px: float,
    rms: float,
) -> dict[str, Any]:
    bounds = _object_bounds(scene)
    seen: dict[int, list[str]] = {}
    for e in view_entries:
        for inst in e["changed_instances"]:
            seen.setdefault(inst, []).append(e["name"])
    changes = []
    for ch in scene.changes:
        b = np.array([bounds[o] for o in ch["objects"]])
        changes.append(
            {
                **ch,
                "views": seen.get(ch["instance_id"], []),
                "bbox_local": [*b[:, :3].min(0).tolist(), *b[:, 3:].max(0).tolist()],
            }
        )
    objects = [{**o, "bbox_local": bounds[o["id"]]} for o in scene.objects]
    by_type: dict[str, int] = {}
    for o in objects:
        by_type[o["type"]] = by_type.get(o["type"], 0) + 1
    first = views[0].intrinsics
    return {
        "format": "streetcd-synth/1",
        "generator": scene.params,
        "crs": scene.crs,
        "origin": [float(v) for v in scene.origin],
        "seed": scene.params["seed"],
        "pose_noise_px": float(pose_noise_px),
        "pose_noise": {
            "requested_px": float(pose_noise_px),
            "achieved_rms_px": round(rms, 4),
            "measured_on": "visible surface points, every 8th pixel",
        },
        "classes": {str(k): v for k, v in classes.NAMES.items()},
        "streets": [
            {
                "name": s.name,
                "heading_deg": s.layout["heading_deg"],
                "offset_local": s.offset.tolist(),
                "layout": s.layout,
                "views": [v.name for v in street_views[i]],
            }
            for i, s in enumerate(scene.streets)
        ],
        "sun_local": [round(float(v), 6) for v in scene.sun],
        "scan": {**scan.as_dict(), "n_points": int(n_points), "epoch": 1},
        "images": {
            "count": len(views),
            "width": first.width,
            "height": first.height,
            "fx_px": first.fx,
            "hfov_deg": round(math.degrees(2 * math.atan(first.width / 2 / first.fx)), 3),
            "overlap_at_far_facade": _overlap(scene, street_views),
            "jpeg_quality": JPEG_QUALITY,
            "epoch": 2,
        },
        "objects": objects,
        "object_counts": dict(sorted(by_type.items())),
        "changes": changes,
        "disturbances": list(scene.disturbances),
        "views": view_entries,
        "files": {
            "cloud": cloud_files,
            "images": [e["image"] for e in view_entries],
            "poses_colmap": "poses/colmap",
            "poses_opk": "poses/poses_opk.csv",
            "poses_true_opk": "truth/poses_true_opk.csv",
            "truth": "truth",
        },
    }


__all__ = ["generate_city", "generate_street", "EPOCH1", "EPOCH2"]
