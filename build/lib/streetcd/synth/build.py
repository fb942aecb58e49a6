"""Scenes from a seed: one street, or a small city of streets, placed in a projected CRS.

Scenes are cheap to build (no ray casting), so readers of a generated folder rebuild them
from the ``generator`` block of ``manifest.json`` with :func:`load_scene` to render depth
and object ids for any view.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from streetcd.errors import InputError
from streetcd.geometry.camera import look_at
from streetcd.synth.layout import CURB_H, build_street
from streetcd.synth.scene import Scene, SceneBuilder, Street, freeze, rotation_z
from streetcd.types import Intrinsics, Pose, View

DEFAULT_CRS = "EPSG:32648"  # WGS 84 / UTM zone 48N
DEFAULT_ORIGIN_EN = (372_000.0, 143_000.0)


def _sun(rng: np.random.Generator, heading_deg: float) -> np.ndarray:
    """Sun direction (local frame) on the cameras' side of the street, 45–62° high, so the
    façades the cameras look at are lit and poles cast shadows on them."""
    elev = math.radians(float(rng.uniform(45.0, 62.0)))
    # from the side rather than from behind the cameras, so cast shadows are visible
    az = math.radians(float(rng.uniform(35.0, 65.0)) * (1 if rng.random() < 0.5 else -1))
    s_street = np.array(
        [math.cos(elev) * math.sin(az), -math.cos(elev) * math.cos(az), math.sin(elev)]
    )
    return rotation_z(heading_deg) @ s_street


def _origin(rng: np.random.Generator) -> np.ndarray:
    e = DEFAULT_ORIGIN_EN[0] + round(float(rng.uniform(0.0, 800.0)), 3)
    n = DEFAULT_ORIGIN_EN[1] + round(float(rng.uniform(0.0, 800.0)), 3)
    return np.array([e, n, round(float(rng.uniform(5.0, 25.0)), 3)])


def _finish(
    builder: SceneBuilder,
    street_changes: list[list[dict]],
    disturb: list[dict],
    streets: list[Street],
    origin,
    crs,
    sun,
    params,
) -> Scene:
    builder.object_epochs()
    changes: list[dict[str, Any]] = []
    for s, chs in enumerate(street_changes):
        for ch in chs:
            changes.append({"instance_id": len(changes) + 1, "street": s, **ch})
    return Scene(
        tuple(streets),
        np.asarray(origin, dtype=np.float64),
        crs,
        tuple(builder.objects),
        tuple(changes),
        tuple(disturb),
        np.asarray(sun, dtype=np.float64),
        params,
    )


def build_street_scene(
    seed: int = 0,
    length_m: float = 150.0,
    changes: bool = True,
    crs: str = DEFAULT_CRS,
    plain: bool = False,
) -> Scene:
    """One street ``length_m`` long (≥ 30 m) from ``seed``; see :mod:`streetcd.synth.layout`
    (``plain``: uniformly painted objects and plain walls)."""
    if not (30.0 <= length_m <= 1000.0):
        raise InputError(f"synthetic street length_m = {length_m} must be in [30, 1000] m")
    rng = np.random.default_rng(seed)
    place, content = rng.spawn(2)
    heading = float(place.uniform(10.0, 80.0))
    origin = _origin(place)
    sun = _sun(place, heading)
    b = SceneBuilder()
    lay, chs, dist = build_street(b, content, length_m, changes, plain)
    for ob in b.objects:
        ob["street"] = 0
    street = freeze(b, "street0", heading, np.zeros(3), {"heading_deg": heading, **lay.as_dict()})
    params = {
        "kind": "street",
        "seed": int(seed),
        "length_m": float(length_m),
        "changes": bool(changes),
        "crs": crs,
    }
    if plain:  # only then: the default manifest stays byte for byte what it was
        params["plain"] = True
    return _finish(b, [chs], dist, [street], origin, crs, sun, params)


def build_city_scene(
    seed: int = 0,
    n_streets: int = 3,
    length_m: float = 50.0,
    changes: bool = True,
    crs: str = DEFAULT_CRS,
    plain: bool = False,
) -> Scene:
    """``n_streets`` streets on a grid of blocks (alternately east–west and north–south),
    far enough apart that no street sees another; changes in every street but the second."""
    if n_streets < 1:
        raise InputError(f"n_streets = {n_streets} must be >= 1")
    if not (30.0 <= length_m <= 1000.0):
        raise InputError(f"synthetic street length_m = {length_m} must be in [30, 1000] m")
    rng = np.random.default_rng(seed)
    place, *contents = rng.spawn(1 + n_streets)
    origin = _origin(place)
    sun = _sun(place, 0.0)
    cell = length_m + 200.0  # streets see ~60 m sideways and past their ends
    b = SceneBuilder()
    streets, all_changes, disturb = [], [], []
    cols = math.ceil(math.sqrt(n_streets))
    for s in range(n_streets):
        heading = 0.0 if s % 2 == 0 else 90.0
        offset = np.array([(s % cols) * cell, (s // cols) * cell, 0.0])
        sb = SceneBuilder(first_id=b.first_id + len(b.objects))
        with_changes = changes and s != 1
        lay, chs, dist = build_street(sb, contents[s], length_m, with_changes, plain)
        for ob in sb.objects:
            ob["street"] = s
        streets.append(
            freeze(sb, f"street{s}", heading, offset, {"heading_deg": heading, **lay.as_dict()})
        )
        b.objects.extend(sb.objects)
        all_changes.append(chs)
        disturb.extend(dist)
    params = {
        "kind": "city",
        "seed": int(seed),
        "n_streets": int(n_streets),
        "length_m": float(length_m),
        "changes": bool(changes),
        "crs": crs,
    }
    if plain:
        params["plain"] = True
    return _finish(b, all_changes, disturb, streets, origin, crs, sun, params)


def load_scene(manifest: str | Path | dict[str, Any]) -> Scene:
    """Rebuild the scene of a generated folder from its ``manifest.json`` (path or dict)."""
    m = (
        manifest
        if isinstance(manifest, dict)
        else json.loads(Path(manifest).read_text(encoding="utf-8"))
    )
    g = m["generator"]
    plain = bool(g.get("plain", False))
    if g["kind"] == "street":
        return build_street_scene(g["seed"], g["length_m"], g["changes"], g["crs"], plain)
    return build_city_scene(g["seed"], g["n_streets"], g["length_m"], g["changes"], g["crs"], plain)


# --- the camera strip -------------------------------------------------------------------


def camera_strip(
    scene: Scene,
    street_index: int,
    n_images: int,
    size: tuple[int, int],
    rng: np.random.Generator,
    prefix: str = "IMG",
    path: str = "vehicle",
) -> list[View]:
    """Views along the near sidewalk looking across the street, in the CRS.

    Spacing fills the street; the horizontal field of view is chosen for ~75 % overlap of
    consecutive images on the far façades (clamped to 50–85°). ``path`` other than
    ``vehicle``: a pedestrian's views (:func:`pedestrian_strip`).
    """
    if path != "vehicle":
        return pedestrian_strip(scene, street_index, n_images, size, rng, prefix, path)
    street = scene.streets[street_index]
    lay = street.layout
    L = lay["length_m"]
    width, height = size
    margin = min(6.0, 0.1 * L)
    xs = np.linspace(margin, L - margin, n_images) if n_images > 1 else np.array([L / 2])
    spacing = (xs[-1] - xs[0]) / max(n_images - 1, 1) if n_images > 1 else L / 4
    dist = lay["far_facade_y_m"] - lay["camera_y_m"]
    hfov = 2 * math.atan(spacing / (1 - 0.75) / 2 / dist)
    hfov = min(max(hfov, math.radians(50)), math.radians(85))
    f = width / 2 / math.tan(hfov / 2)
    intr = Intrinsics(width, height, f, f, (width - 1) / 2, (height - 1) / 2)
    views = []
    for i, x in enumerate(xs):
        c = np.array(
            [
                x + rng.uniform(-0.3, 0.3),
                lay["camera_y_m"] + rng.uniform(-0.15, 0.15),
                CURB_H + rng.uniform(1.5, 1.7),
            ]
        )
        yaw = math.radians(rng.uniform(-3.0, 3.0))
        pitch = math.radians(rng.uniform(5.0, 10.0))
        fwd = np.array(
            [math.sin(yaw) * math.cos(pitch), math.cos(yaw) * math.cos(pitch), math.sin(pitch)]
        )
        roll = math.radians(rng.uniform(-1.0, 1.0))
        up = np.array([math.sin(roll) * math.cos(yaw), -math.sin(roll) * math.sin(yaw), 1.0])
        pose_s = look_at(c, c + fwd, up)  # street frame
        R = pose_s.R @ street.rotation.T  # local→camera
        centre = street.to_local(pose_s.center[None])[0] + scene.origin
        pose = Pose.from_center(R, centre)
        name = f"{prefix}_{i:04d}.jpg"
        views.append(View(name, intr, pose, None, 0.0))
    return views


PEDESTRIAN_HFOV_DEG = 65.0  # a phone or action camera held by a walker


def pedestrian_strip(
    scene: Scene,
    street_index: int,
    n_images: int,
    size: tuple[int, int],
    rng: np.random.Generator,
    prefix: str = "IMG",
    path: str = "sidewalk-right",
) -> list[View]:
    """Views of a pedestrian walking +x on a sidewalk, camera 1.5–1.7 m above it, in the CRS.

    ``sidewalk-right`` (the near sidewalk, −y): the walker looks 35–55° to the left of the
    street's direction, across at the far side, whose objects are then 10–20 m away;
    ``sidewalk-left`` (the far sidewalk, +y, 0.3 m inside its back edge, behind the
    furniture): the walker looks along the street, 10–25° towards the road, at the objects
    of its own sidewalk 8–20 m ahead. The walk is spread so that its views cover 0–L.
    """
    street = scene.streets[street_index]
    lay = street.layout
    L = lay["length_m"]
    width, height = size
    road_half, walk = lay["road_half_width_m"], lay["sidewalk_width_m"]
    if path == "sidewalk-right":
        y, yaw_deg, xs0, xs1 = -(road_half + 0.5 * walk), (35.0, 55.0), -5.0, L - 12.0
        dy = 0.2
    else:
        y, yaw_deg, xs0, xs1 = road_half + walk - 0.3, (-25.0, -10.0), -8.0, L - 10.0
        dy = 0.05  # the walker's lane between the furniture and the hedges is narrow
    xs = np.linspace(xs0, xs1, n_images) if n_images > 1 else np.array([(xs0 + xs1) / 2])
    f = width / 2 / math.tan(math.radians(PEDESTRIAN_HFOV_DEG) / 2)
    intr = Intrinsics(width, height, f, f, (width - 1) / 2, (height - 1) / 2)
    views = []
    for i, x in enumerate(xs):
        c = np.array(
            [x + rng.uniform(-0.3, 0.3), y + rng.uniform(-dy, dy), CURB_H + rng.uniform(1.5, 1.7)]
        )
        yaw = math.radians(rng.uniform(*yaw_deg))
        pitch = math.radians(rng.uniform(0.0, 5.0))
        # yaw from +x towards +y (the street frame's left)
        fwd = np.array(
            [math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)]
        )
        roll = math.radians(rng.uniform(-1.5, 1.5))
        side = np.array([-math.sin(yaw), math.cos(yaw), 0.0])  # the view's left, horizontal
        up = np.array([0.0, 0.0, 1.0]) * math.cos(roll) + side * math.sin(roll)
        pose_s = look_at(c, c + fwd, up)  # street frame
        R = pose_s.R @ street.rotation.T  # local→camera
        centre = street.to_local(pose_s.center[None])[0] + scene.origin
        views.append(View(f"{prefix}_{i:04d}.jpg", intr, Pose.from_center(R, centre), None, 0.0))
    return views
