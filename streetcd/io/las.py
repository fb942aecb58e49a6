"""LAS/LAZ reading and writing with laspy (lazrs backend for LAZ).

Coordinates are returned as local float64 metres relative to an ``origin`` (by default the
file header's offset), so georeferenced values of 10⁵–10⁶ m never lose precision:
``local = X_int · scale + (offset − origin)``.

We write LAS 1.4, point format 7 (XYZ, intensity, 8-bit classification, GPS time, RGB) with the
CRS as a WKT VLR (pyproj builds the WKT), scale 1 mm and an offset rounded to the kilometre.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from datetime import date
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from streetcd.errors import CorruptFileError, CRSMismatchError, InputError, MissingInputError
from streetcd.types import PointCloud

if TYPE_CHECKING:
    import laspy


def crs_string(crs: object) -> str:
    """Normalise a pyproj CRS to ``"EPSG:XXXX"`` where it has an EPSG code, else its WKT."""
    import pyproj

    c = pyproj.CRS.from_user_input(crs)
    code = c.to_epsg()
    return f"EPSG:{code}" if code is not None else c.to_wkt()


def header_crs(header: laspy.LasHeader, path: Path) -> str | None:
    """The CRS a LAS header states (WKT or GeoTIFF keys), normalised, or None if it has none."""
    try:
        parsed = header.parse_crs()
    except Exception as exc:  # laspy raises several types for a malformed CRS VLR
        raise InputError(f"{path}: field 'CRS VLR' cannot be parsed: {exc}") from None
    return None if parsed is None else crs_string(parsed)


def write_las(
    path: str | Path,
    xyz: np.ndarray,
    classification: np.ndarray,
    *,
    origin: np.ndarray | None = None,
    intensity: np.ndarray | None = None,
    rgb: np.ndarray | None = None,
    gps_time: np.ndarray | None = None,
    crs: str | None = None,
    scale: float = 0.001,
    creation_date: date | None = None,
) -> Path:
    """Write points to ``path`` (``.laz`` compresses with lazrs).

    xyz : (N, 3) float64 metres, local coordinates relative to ``origin`` (CRS metres);
        without ``origin`` they are CRS coordinates.
    creation_date : the header's creation day (default today); fix it for reproducible files.
    """
    import laspy  # here, not at the top: Dask workers crop from the tile store without it

    path = Path(path)
    origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.all(np.isfinite(xyz)):
        raise InputError(f"{path}: xyz must be finite (N, 3), got shape {xyz.shape}")
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = np.array([scale, scale, scale])
    if creation_date is not None:
        header.creation_date = creation_date
    lo = xyz.min(axis=0) + origin if len(xyz) else origin
    header.offsets = np.floor(lo / 1000.0) * 1000.0
    if crs is not None:
        import pyproj

        header.add_crs(pyproj.CRS.from_user_input(crs))
    las = laspy.LasData(header)
    # Integer coordinates computed from local values: (xyz + origin − offset) / scale,
    # with origin − offset folded first so that no large number meets a small one in float32.
    shift = origin - header.offsets
    ints = np.round((xyz + shift) / scale).astype(np.int64)
    las.X, las.Y, las.Z = ints[:, 0], ints[:, 1], ints[:, 2]
    las.classification = np.asarray(classification, dtype=np.uint8)
    if intensity is not None:
        las.intensity = np.asarray(intensity, dtype=np.uint16)
    if gps_time is not None:
        las.gps_time = np.asarray(gps_time, dtype=np.float64)
    if rgb is not None:
        rgb = np.asarray(rgb, dtype=np.uint16)
        las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{path.suffix}")
    las.write(tmp)
    tmp.replace(path)  # atomic: a reader never sees a half-written file
    return path


def _points_to_cloud(
    points: laspy.ScaleAwarePointRecord,
    header: laspy.LasHeader,
    origin: np.ndarray,
    crs: str | None,
) -> PointCloud:
    shift = np.asarray(header.offsets, dtype=np.float64) - origin
    scales = np.asarray(header.scales, dtype=np.float64)
    xyz = np.column_stack(
        [
            np.asarray(points.X, dtype=np.float64) * scales[0] + shift[0],
            np.asarray(points.Y, dtype=np.float64) * scales[1] + shift[1],
            np.asarray(points.Z, dtype=np.float64) * scales[2] + shift[2],
        ]
    )
    names = set(points.point_format.dimension_names)
    rgb = None
    if {"red", "green", "blue"} <= names:
        rgb = np.column_stack([points.red, points.green, points.blue]).astype(np.uint16)
    return PointCloud(
        xyz=xyz,
        origin=origin,
        classification=np.asarray(points.classification, dtype=np.uint8),
        intensity=np.asarray(points.intensity, dtype=np.uint16) if "intensity" in names else None,
        rgb=rgb,
        gps_time=np.asarray(points.gps_time, dtype=np.float64) if "gps_time" in names else None,
        crs=crs,
    )


def read_las(path: str | Path, origin: np.ndarray | None = None) -> PointCloud:
    """Read a whole LAS/LAZ file into a :class:`PointCloud` (local to ``origin``, default the
    header offset). For files larger than memory use :func:`iter_las_chunks`; this is its
    one-chunk case, so both report missing, corrupt, truncated and non-finite input alike."""
    info = las_info(path)
    chunks = list(iter_las_chunks(path, chunk_points=max(1, info.point_count), origin=origin))
    if chunks:
        assert len(chunks) == 1, "one chunk of point_count points holds the whole file"
        return chunks[0]
    # A valid file without points: an empty cloud in the frame its header gives.
    org = info.offsets if origin is None else np.asarray(origin, dtype=np.float64)
    return PointCloud(np.empty((0, 3)), org, np.empty(0, np.uint8), crs=info.crs)


# --- chunked reading (files larger than memory) ------------------------------------------


@dataclass(frozen=True)
class LasInfo:
    """What a LAS/LAZ header says, read without touching the points.

    mins, maxs : (3,) float64, metres in the CRS (the header's bounding box).
    offsets, scales : (3,) float64, the header's integer-coordinate transform.
    """

    path: Path
    point_count: int
    crs: str | None
    mins: np.ndarray
    maxs: np.ndarray
    offsets: np.ndarray
    scales: np.ndarray


def las_info(path: str | Path) -> LasInfo:
    """Read the header of ``path``; MissingInputError / CorruptFileError name the file."""
    import laspy

    path = Path(path)
    if not path.exists():
        raise MissingInputError(f"point cloud file not found: {path}")
    try:
        with laspy.open(path) as reader:
            h = reader.header
            return LasInfo(
                path,
                int(h.point_count),
                header_crs(h, path),
                np.asarray(h.mins, dtype=np.float64),
                np.asarray(h.maxs, dtype=np.float64),
                np.asarray(h.offsets, dtype=np.float64),
                np.asarray(h.scales, dtype=np.float64),
            )
    except InputError:
        raise
    except (laspy.errors.LaspyException, OSError, ValueError, RuntimeError) as exc:
        raise CorruptFileError(f"{path}: cannot be read as LAS/LAZ: {exc}") from None


def iter_las_chunks(
    path: str | Path, chunk_points: int = 1_000_000, origin: np.ndarray | None = None
) -> Iterator[PointCloud]:
    """Stream ``path`` as :class:`PointCloud` chunks of at most ``chunk_points`` points.

    Coordinates are local to ``origin`` (3,) float64 CRS metres (default the header offset),
    exactly as :func:`read_las` computes them, so the chunks concatenated equal the whole file.
    Memory is one chunk. A truncated file raises CorruptFileError once the missing part is
    reached (earlier chunks have been yielded); non-finite coordinates raise InputError.
    """
    import laspy

    path = Path(path)
    if chunk_points < 1:
        raise InputError(f"chunk_points must be >= 1, got {chunk_points}")
    if not path.exists():
        raise MissingInputError(f"point cloud file not found: {path}")
    seen = 0
    try:
        with laspy.open(path) as reader:
            header = reader.header
            crs = header_crs(header, path)
            org = np.asarray(header.offsets if origin is None else origin, dtype=np.float64)
            for points in reader.chunk_iterator(chunk_points):
                if len(points) == 0:
                    break
                seen += len(points)
                cloud = _points_to_cloud(points, header, org, crs)
                if not np.all(np.isfinite(cloud.xyz)):
                    raise InputError(
                        f"{path}: field 'X/Y/Z' has non-finite coordinates "
                        f"(header scales {list(header.scales)}, "
                        f"offsets {list(header.offsets)})"
                    )
                yield cloud
            expected = int(header.point_count)
    except InputError:
        raise
    except (laspy.errors.LaspyException, OSError, ValueError, RuntimeError) as exc:
        raise CorruptFileError(
            f"{path}: cannot be read as LAS/LAZ after {seen} points: {exc}"
        ) from None
    if seen != expected:
        raise CorruptFileError(f"{path}: truncated: header says {expected} points, read {seen}")


def load_clouds(paths: Sequence[str | Path]) -> PointCloud:
    """Read several LAS/LAZ files into one cloud in one local frame (the first file's offset).

    Files have different header offsets, so every file is read relative to the same origin.
    CRSMismatchError if two files state different CRSs.
    """
    if not paths:
        raise MissingInputError("no point cloud file given")
    first = read_las(paths[0])
    clouds = [first] + [read_las(p, origin=first.origin) for p in paths[1:]]
    crss = {c.crs for c in clouds if c.crs is not None}
    if len(crss) > 1:
        listed = ", ".join(f"{p}: {c.crs}" for p, c in zip(paths, clouds, strict=True))
        raise CRSMismatchError(f"point cloud files have different CRSs ({listed})")
    return PointCloud(
        xyz=np.concatenate([c.xyz for c in clouds]),
        origin=first.origin,
        classification=np.concatenate([c.classification for c in clouds]),
        # colours only when every file has them (the appearance check needs all or none)
        rgb=(
            np.concatenate([c.rgb for c in clouds])
            if all(c.rgb is not None for c in clouds)
            else None
        ),
        crs=next(iter(crss), None),
    )
