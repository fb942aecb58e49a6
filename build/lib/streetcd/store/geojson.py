"""The change index's query results as GeoJSON (WGS 84 for GIS tools, or the native CRS)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from streetcd.classes import NAMES
from streetcd.store.records import FlaggedRow, SegmentRow


def to_geojson(
    rows: Sequence[FlaggedRow],
    segments: Sequence[SegmentRow],
    crs: str | None,
    *,
    wgs84: bool = True,
) -> dict:
    """A GeoJSON FeatureCollection of flagged segments and change regions.

    Segments are LineStrings (a Point for a one-view segment) with ``kind: "segment"``;
    regions are Polygons (their x/y box) with ``kind: "region"`` and their z range and
    dominant class in the properties; a flagged view without a located region is a Point at
    its camera with ``kind: "view"``.

    With ``wgs84`` and a known ``crs``, coordinates are reprojected to EPSG:4326 longitude /
    latitude (RFC 7946, what QGIS expects). Otherwise they stay in ``crs`` and, when it is
    known, the legacy GeoJSON-2008 ``crs`` member names it. The source CRS is always in
    the foreign member ``streetcd.source_crs``.
    """
    transform = _to_wgs84(crs) if (wgs84 and crs is not None) else (lambda xs, ys: (xs, ys))

    def pts(coords: Sequence[Sequence[float]]) -> list[list[float]]:
        xs, ys = transform([c[0] for c in coords], [c[1] for c in coords])
        nd = 7 if (wgs84 and crs is not None) else 3
        return [[round(float(x), nd), round(float(y), nd)] for x, y in zip(xs, ys, strict=True)]

    by_segment: dict[str | None, list[FlaggedRow]] = {}
    for r in rows:
        by_segment.setdefault(r.segment_id, []).append(r)
    features: list[dict[str, Any]] = []
    for s in segments:
        flagged = by_segment.get(s.segment_id, [])
        line = pts(s.polyline)
        geometry = (
            {"type": "LineString", "coordinates": line}
            if len(line) > 1
            else {"type": "Point", "coordinates": line[0]}
        )
        features.append(
            {
                "type": "Feature",
                "geometry": geometry,
                "properties": {
                    "kind": "segment",
                    "segment_id": s.segment_id,
                    "n_views": s.n_views,
                    "length_m": round(s.length_m, 2),
                    "n_flagged": len(flagged),
                    "max_score": max((r.score for r in flagged), default=None),
                },
            }
        )
    for r in rows:
        base = {
            "view": r.view,
            "segment_id": r.segment_id,
            "view_score": r.score,
            "changed_fraction": r.changed_fraction,
            "mask_path": r.mask_path,
            "detected_at": r.detected_at,
            "captured_at": r.captured_at,
        }
        located = [g for g in r.regions if g.located]
        if not located and r.center is not None:
            features.append(
                {
                    "type": "Feature",
                    "properties": {"kind": "view", **base},
                    "geometry": {"type": "Point", "coordinates": pts([r.center])[0]},
                }
            )
        for g in located:
            (x0, y0, z0), (x1, y1, z1) = g.bbox_min, g.bbox_max  # type: ignore[misc]
            ring = pts([(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)])
            features.append(
                {
                    "type": "Feature",
                    "geometry": {"type": "Polygon", "coordinates": [ring]},
                    "properties": {
                        "kind": "region",
                        **base,
                        "label": g.label,
                        "score": g.score,
                        "pixels": g.pixels,
                        "dominant_class": g.dominant_class,
                        "class_name": NAMES.get(g.dominant_class, "unknown"),
                        "centroid": [round(v, 3) for v in g.centroid or ()],
                        "min_z": z0,
                        "max_z": z1,
                    },
                }
            )
    out: dict = {"type": "FeatureCollection", "features": features, "streetcd": {"source_crs": crs}}
    if crs is not None and not wgs84:
        out["crs"] = {"type": "name", "properties": {"name": _ogc_urn(crs)}}
    return out


def objects_to_geojson(objects: Sequence[dict], crs: str | None, *, wgs84: bool = True) -> dict:
    """A GeoJSON FeatureCollection with one feature per change object
    (:func:`streetcd.store.objects.list_objects`'s dicts): its x/y box as a Polygon (a Point
    where the box has no area), and in the properties its id, kind, class, confidence,
    centroid and box in the source CRS, nights, review, transient reason, its views and the
    overlay paths of those that see the change. Coordinates as :func:`to_geojson`."""
    transform = _to_wgs84(crs) if (wgs84 and crs is not None) else (lambda xs, ys: (xs, ys))
    nd = 7 if (wgs84 and crs is not None) else 3

    def pts(coords: Sequence[Sequence[float]]) -> list[list[float]]:
        xs, ys = transform([c[0] for c in coords], [c[1] for c in coords])
        return [[round(float(x), nd), round(float(y), nd)] for x, y in zip(xs, ys, strict=True)]

    features = []
    for o in objects:
        x0, y0, _, x1, y1, _ = o["bbox"]
        if x1 > x0 and y1 > y0:
            ring = pts([(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)])
            geometry: dict[str, Any] = {"type": "Polygon", "coordinates": [ring]}
        else:
            geometry = {"type": "Point", "coordinates": pts([o["centroid"]])[0]}
        props = {k: v for k, v in o.items() if k != "views"}
        props["class_name"] = NAMES.get(o["class"], "unknown")
        props["views"] = o["views"]
        props["overlays"] = [v["overlay"] for v in o["views"] if v["sees_change"] and v["overlay"]]
        features.append({"type": "Feature", "geometry": geometry, "properties": props})
    out: dict = {"type": "FeatureCollection", "features": features, "streetcd": {"source_crs": crs}}
    if crs is not None and not wgs84:
        out["crs"] = {"type": "name", "properties": {"name": _ogc_urn(crs)}}
    return out


def _to_wgs84(crs: str) -> Any:
    import pyproj

    return pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform


def _ogc_urn(crs: str) -> str:
    """``EPSG:32648`` → ``urn:ogc:def:crs:EPSG::32648`` (the legacy ``crs`` member's form)."""
    if crs.upper().startswith("EPSG:"):
        return f"urn:ogc:def:crs:EPSG::{crs.split(':', 1)[1]}"
    return crs
