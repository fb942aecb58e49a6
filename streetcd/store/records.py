"""The change index's value objects: what a view's processing produced (:class:`ViewRecord`,
with its :class:`RegionRecord`), and what a query returns (:class:`FlaggedRow`,
:class:`SegmentRow`). Coordinates are metres in the index's CRS. The index itself is
:mod:`streetcd.store.index`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from streetcd.errors import InputError


@dataclass(frozen=True)
class RegionRecord:
    """One changed region located in 3D; coordinates are metres in the CRS.

    centroid, bbox_min, bbox_max are None when the region could not be located (none of its
    pixels has a reference surface behind it).
    """

    label: int
    pixels: int
    score: float
    centroid: tuple[float, float, float] | None
    bbox_min: tuple[float, float, float] | None
    bbox_max: tuple[float, float, float] | None
    dominant_class: int

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


@dataclass(frozen=True)
class SegmentRow:
    segment_id: str
    n_views: int
    length_m: float
    bbox: tuple[float, float, float, float]
    polyline: list[list[float]]
