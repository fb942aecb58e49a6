"""Change objects for people and GIS tools (``streetcd query``): sorted, limited, a box given
in any CRS, written as CSV or GeoPackage (through pyogrio, GDAL's writer), with the paths of
masks, overlays and images relative to the run folder so the files travel with it.

Coordinates stay in the index's CRS (metres); the GeoPackage names it. GeoJSON, whose
RFC 7946 coordinates are WGS 84 longitude/latitude, is refused when the index has no CRS
(:func:`check_geojson_crs`): UTM numbers written as degrees put a city in the ocean.
"""

from __future__ import annotations

import csv
import io
import os
import struct
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from streetcd.errors import CRSMismatchError, InputError

SORTS = ("score", "time")
COLUMNS = (
    "id", "kind", "class", "class_name", "confidence", "x", "y", "z",
    "min_x", "min_y", "min_z", "max_x", "max_y", "max_z", "segment", "n_views",
    "first_seen", "last_seen", "review_status", "review_who", "review_at", "review_note",
    "transient", "views", "masks", "overlays", "images",
)  # fmt: skip


def sort_objects(objects: Sequence[dict], by: str) -> list[dict]:
    """``score``: highest confidence first; ``time``: last seen latest first (then first
    seen, then confidence). Ties by id, so the order is the same every time."""
    if by == "score":
        return sorted(objects, key=lambda o: (-float(o["confidence"]), str(o["id"])))
    if by == "time":
        out = sorted(objects, key=lambda o: (-float(o["confidence"]), str(o["id"])))
        out.sort(key=lambda o: (o.get("last_seen") or "", o.get("first_seen") or ""), reverse=True)
        return out
    raise InputError(f"--sort {by!r} must be one of {', '.join(SORTS)}")


def bbox_in_index_crs(
    bbox: tuple[float, float, float, float], bbox_crs: str | None, index_crs: str | None
) -> tuple[float, float, float, float]:
    """``bbox`` (min_x, min_y, max_x, max_y) given in ``bbox_crs`` (None: the index's own),
    as a box in the index's CRS that holds it (edges densified, so a lon/lat box bends
    right). CRSMismatchError when a CRS is given but the index has none."""
    if bbox_crs is None:
        return bbox
    from pyproj import CRS, Transformer
    from pyproj.exceptions import CRSError

    if index_crs is None:
        raise CRSMismatchError(
            f"--bbox-crs {bbox_crs}: the index has no CRS (a local frame), so a box in another"
            " CRS cannot be placed in it; give --bbox in the index's coordinates"
        )
    try:
        source = CRS.from_user_input(bbox_crs)
    except CRSError as exc:
        raise InputError(f"--bbox-crs {bbox_crs!r} is not a CRS ({exc})") from None
    move = Transformer.from_crs(source, CRS.from_user_input(index_crs), always_xy=True)
    x0, y0, x1, y1 = move.transform_bounds(*bbox, densify_pts=21)
    return float(x0), float(y0), float(x1), float(y1)


def check_geojson_crs(crs: str | None, native_crs: bool) -> None:
    """InputError when GeoJSON in WGS 84 is asked of an index without a CRS."""
    if crs is None and not native_crs:
        raise InputError(
            "GeoJSON needs WGS 84 longitude/latitude (RFC 7946) and this index has no CRS "
            "(its coordinates are in a local frame): use --format csv or gpkg, or "
            "--native-crs for GeoJSON in the local frame"
        )


def _relative_to(base: Path | None) -> Callable[[str | None], str]:
    """A function giving a stored path relative to ``base`` (None: as stored), with both
    sides' folders resolved through links: each folder resolved and made relative once, the
    file's own name kept (resolving every path, an lstat per folder of it, was 2.3 of the 2.8
    s the CSV of a 10,000-view city's 2,490 objects took: docs/BENCHMARKS.md)."""
    if base is None:
        return lambda path: str(path) if path else ""
    root = base.resolve()
    folders: dict[str, str] = {}  # a stored folder: its path from root, "" for root itself

    def relative(path: str | None) -> str:
        if not path:
            return ""
        folder, name = os.path.split(str(path))
        prefix = folders.get(folder)
        if prefix is None:
            up = Path(os.path.relpath(os.path.realpath(folder), root)).as_posix()
            prefix = folders[folder] = "" if up == "." else up + "/"
        return prefix + name

    return relative


def object_rows(objects: Sequence[dict], base: Path | None) -> list[dict[str, Any]]:
    """One flat record per object (:data:`COLUMNS`); lists of views, masks, overlays and
    images joined by ``;``, paths relative to ``base`` (the run folder; None: as stored)."""
    rows = []
    relative = _relative_to(base)
    for o in objects:
        review = o.get("review") or {}
        seen = [v for v in o.get("views") or () if v.get("sees_change", True)]
        x, y, z = (list(o.get("centroid") or ()) + [None] * 3)[:3]
        box = (list(o.get("bbox") or ()) + [None] * 6)[:6]
        rows.append(
            {
                "id": o["id"],
                "kind": o.get("kind"),
                "class": o.get("class"),
                "class_name": o.get("class_name"),
                "confidence": round(float(o["confidence"]), 4),
                "x": x,
                "y": y,
                "z": z,
                **dict(zip(COLUMNS[8:14], box, strict=True)),
                "segment": o.get("segment"),
                "n_views": len(seen),
                "first_seen": o.get("first_seen"),
                "last_seen": o.get("last_seen"),
                "review_status": review.get("status") or "",
                "review_who": review.get("who") or "",
                "review_at": review.get("at") or "",
                "review_note": review.get("note") or "",
                "transient": o.get("transient") or "",
                "views": ";".join(str(v["view"]) for v in seen),
                "masks": ";".join(relative(v.get("mask")) for v in seen),
                "overlays": ";".join(relative(v.get("overlay")) for v in seen),
                "images": ";".join(relative(v.get("image_path")) for v in seen),
            }
        )
    return rows


def to_csv(objects: Sequence[dict], base: Path | None) -> str:
    """The objects as CSV text (a header line, then one line per object)."""
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(object_rows(objects, base))
    return out.getvalue().rstrip("\n")


def write_gpkg(objects: Sequence[dict], crs: str | None, path: Path, base: Path | None) -> int:
    """Write the objects to the GeoPackage ``path`` (replaced), layer ``changes``: a point
    at each centroid (x, y in the CRS; z a column), the CRS named when known. Returns the
    number of features. pyogrio (GDAL) writes it."""
    import numpy as np
    import pyogrio.raw

    rows = [r for r in object_rows(objects, base) if r["x"] is not None]
    if not rows:
        raise InputError(f"{path}: no change object to write (a GeoPackage layer needs one)")
    # WKB points: little-endian, type 1, x, y
    geometry = np.array([struct.pack("<BIdd", 1, 1, r["x"], r["y"]) for r in rows], dtype=object)
    fields = [c for c in COLUMNS if c not in ("x", "y")]
    data = [_column([r[c] for r in rows]) for c in fields]
    wkt = None
    if crs is not None:
        from pyproj import CRS

        wkt = CRS.from_user_input(crs).to_wkt()
    path.unlink(missing_ok=True)
    pyogrio.raw.write(
        str(path), geometry, data, fields, layer="changes", driver="GPKG",
        geometry_type="Point", crs=wkt,
    )  # fmt: skip
    return len(rows)


def _column(values: list[Any]) -> Any:
    """A column for pyogrio: int64 or float64 where every value is a number, else text."""
    import numpy as np

    if all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        return np.asarray(values, dtype=np.int64)
    if all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        return np.asarray(values, dtype=np.float64)
    return np.asarray(["" if v is None else str(v) for v in values], dtype=object)


def run_folder(index_path: str | Path) -> Path | None:
    """The latest run's output folder as the index recorded it (``runs.config``), or None."""
    from streetcd.report.changes import pick_run
    from streetcd.store.index import ChangeIndex

    with ChangeIndex(index_path, readonly=True) as idx:
        run = pick_run(idx, None)
    out = ((run or {}).get("inputs") or {}).get("out")
    return Path(out) if out else None


def export_objects(
    objects: Sequence[dict],
    crs: str | None,
    fmt: str,
    index_path: str | Path,
    output: str | Path | None,
) -> str:
    """``streetcd query --format csv|gpkg``: the CSV text, or write the GeoPackage to
    ``output`` (required) and say so. Paths relative to the run folder."""
    base = run_folder(index_path)
    if fmt == "csv":
        return to_csv(objects, base)
    if fmt != "gpkg":
        raise InputError(f"--format {fmt!r}: export writes csv or gpkg")
    if output is None:
        raise InputError("--format gpkg writes a file: give -o FILE.gpkg")
    n = write_gpkg(objects, crs, Path(output), base)
    return f"wrote {n} change object(s) to {output} (layer 'changes', {crs or 'no CRS'})"
