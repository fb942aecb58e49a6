"""The change index's value objects: what a view's processing produced (:class:`ViewRecord`,
with its :class:`RegionRecord`), and what a query returns (:class:`FlaggedRow`,
:class:`SegmentRow`). Coordinates are metres in the index's CRS. The index itself is
:mod:`streetcd.store.index`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from streetcd.errors import InputError

if TYPE_CHECKING:  # numpy and the camera types load with the camera helpers below: a query
    from streetcd.types import View  # reads records and needs neither (docs/BENCHMARKS.md)


@dataclass(frozen=True)
class RegionRecord:
    """One changed region located in 3D; coordinates are metres in the CRS.

    centroid, bbox_min, bbox_max are None when the region could not be located (none of its
    pixels has a reference surface behind it). foot_class is the old cloud's class behind the
    region's lowest pixels (:class:`streetcd.detect.regions.Region`), 0 when unknown.
    depth_fraction is where the change stands, as a fraction of the camera depth of the old
    surface behind it (:mod:`streetcd.detect.locate`), None when unknown (and in an index of
    schema 4, which did not keep it).
    """

    label: int
    pixels: int
    score: float
    centroid: tuple[float, float, float] | None
    bbox_min: tuple[float, float, float] | None
    bbox_max: tuple[float, float, float] | None
    dominant_class: int
    foot_class: int = 0
    depth_fraction: float | None = None

    @property
    def located(self) -> bool:
        return self.centroid is not None and self.bbox_min is not None and self.bbox_max is not None


@dataclass(frozen=True)
class ViewRecord:
    """What processing one view produced, as the index stores it.

    status is ``"done"`` or ``"failed"`` (then ``error`` says why, naming the file or view).
    A view is flagged when ``flagged`` is true; only then are score, regions and the mask
    path listed in the ``flagged`` table. ``center`` is the camera centre in the CRS.
    ``captured_at`` is when the image was taken (index timestamp format), None if unknown.
    ``view`` is the view's lasting key (:func:`streetcd.run.plan.lasting_key`), ``image`` the
    image's name (None: the part of the key before ``#``), ``image_path`` where it was read,
    ``camera`` its pose and intrinsics as :func:`camera_json` writes them (None: not known,
    e.g. a view that failed at planning).
    """

    view: str
    input_hash: str
    params_hash: str
    segment_id: str | None
    status: str
    error: str | None = None
    flagged: bool = False
    score: float = 0.0
    changed_fraction: float = 0.0
    regions: tuple[RegionRecord, ...] = ()
    mask_path: str | None = None
    overlay_path: str | None = None
    center: tuple[float, float, float] | None = None
    detect_s: float | None = None
    total_s: float | None = None
    cpu_s: float | None = None
    captured_at: str | None = None
    image: str | None = None
    image_path: str | None = None
    camera: str | None = None

    def __post_init__(self) -> None:
        if self.status not in ("done", "failed"):
            raise InputError(f"view {self.view!r}: status {self.status!r} must be done or failed")


@dataclass(frozen=True)
class FlaggedRow:
    """A row of a query: one flagged view with its regions (coordinates in the CRS)."""

    view: str
    segment_id: str | None
    score: float
    changed_fraction: float
    n_regions: int
    mask_path: str | None
    overlay_path: str | None
    detected_at: str
    center: tuple[float, float, float] | None
    regions: tuple[RegionRecord, ...] = field(default=())
    captured_at: str | None = None
    image: str | None = None


@dataclass(frozen=True)
class SegmentRow:
    segment_id: str
    n_views: int
    length_m: float
    bbox: tuple[float, float, float, float]
    polyline: list[list[float]]


def camera_json(view: View) -> str:
    """A view's camera as compact JSON: ``R`` (3x3, world→camera), ``t`` (3,) metres in the
    CRS, and the intrinsics ``w, h, fx, fy, cx, cy`` (pixels; lens distortion is left out:
    what the index uses it for, whether a point is in view, does not need it)."""
    import numpy as np

    i = view.intrinsics
    return json.dumps(
        {
            "R": np.round(view.pose.R, 9).tolist(),
            "t": np.round(view.pose.t, 6).tolist(),
            "w": i.width,
            "h": i.height,
            "fx": i.fx,
            "fy": i.fy,
            "cx": i.cx,
            "cy": i.cy,
        },
        separators=(",", ":"),
    )


def camera_from_json(name: str, text: str) -> View:
    """The :class:`View` (without its image) of :func:`camera_json`'s text."""
    import numpy as np

    from streetcd.types import Intrinsics, Pose, View

    d = json.loads(text)
    intr = Intrinsics(int(d["w"]), int(d["h"]), d["fx"], d["fy"], d["cx"], d["cy"])
    return View(name, intr, Pose(np.asarray(d["R"], np.float64), np.asarray(d["t"], np.float64)))
