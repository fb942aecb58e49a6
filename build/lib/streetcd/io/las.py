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
        # pyproj quotes the whole WKT, line breaks and all: one line, cut short
        text = " ".join(str(exc).split())
        text = text if len(text) <= 300 else f"{text[:150]} … {text[-150:]}"
        raise InputError(f"{path}: field 'CRS VLR' cannot be parsed: {text}") from None
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
    point_format: int = 7,
) -> Path:
    """Write points to ``path`` (``.laz`` compresses with lazrs).

    xyz : (N, 3) float64 metres, local coordinates relative to ``origin`` (CRS metres);
        without ``origin`` they are CRS coordinates.
    creation_date : the header's creation day (default today); fix it for reproducible files.
    point_format : LAS 1.4 point format, 7 (with RGB) or 6 (without: ``rgb`` must be None).
    """
    import laspy  # here, not at the top: Dask workers crop from the tile store without it

    path = Path(path)
    origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.all(np.isfinite(xyz)):
        raise InputError(f"{path}: xyz must be finite (N, 3), got shape {xyz.shape}")
    if point_format not in (6, 7) or (point_format == 6 and rgb is not None):
        raise InputError(f"{path}: point_format = {point_format} must be 7, or 6 without rgb")
    header = laspy.LasHeader(point_format=point_format, version="1.4")
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


# Header values no real survey has: a CRS coordinate beyond ±1e8 m (2.5 times the Earth's
# circumference: every projected CRS, false easting and zone prefix included, stays well
# inside; float64 keeps 15 nm there), a scale of zero, below zero or coarser than 1 m.
MAX_COORD_M = 1e8
MAX_SCALE_M = 1.0
_AXES = "xyz"


def las_info(path: str | Path) -> LasInfo:
    """Read the header of ``path`` and check that it can be real (:func:`check_header`);
    MissingInputError / CorruptFileError / InputError name the file and the field."""
    import laspy

    path = Path(path)
    if not path.exists():
        raise MissingInputError(f"point cloud file not found: {path}")
    if not path.is_file():
        raise InputError(f"{path}: is not a file (a LAS/LAZ archive lists files)")
    _check_layout(path)
    try:
        with laspy.open(path) as reader:
            h = reader.header
            info = LasInfo(
                path,
                int(h.point_count),
                header_crs(h, path),
                np.asarray(h.mins, dtype=np.float64),
                np.asarray(h.maxs, dtype=np.float64),
                np.asarray(h.offsets, dtype=np.float64),
                np.asarray(h.scales, dtype=np.float64),
            )
            compressed = bool(h.are_points_compressed)
            record = int(h.point_format.size)
            start = int(h.offset_to_point_data)
            minor = int(h.version.minor)
    except InputError:
        raise
    except Exception as exc:  # laspy/lazrs raise many types for a malformed header
        raise CorruptFileError(
            f"{path}: cannot be read as LAS/LAZ: {type(exc).__name__}: {exc}"
        ) from None
    check_header(info)
    _check_point_count(path, info.point_count, minor, None if compressed else (start, record))
    return info


def _check_layout(path: Path) -> None:
    """CorruptFileError naming the field where the header's layout fields (LAS 1.0–1.4
    public header block) point outside the file. laspy trusts them: a header claiming
    2 billion VLRs made it loop (and grow) for ever, one bit flip in ``number_of_vlrs``."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(375)
    if len(head) < 227 or head[:4] != b"LASF":
        return  # laspy names what is wrong with it (signature, short header)

    def u(at: int, n: int) -> int:
        return int.from_bytes(head[at : at + n], "little")

    header_size, start, n_vlrs = u(94, 2), u(96, 4), u(100, 4)
    if not header_size <= start <= size:
        raise CorruptFileError(
            f"{path}: header field 'offset_to_point_data' is {start}: not between the header "
            f"size ({header_size}) and the file size ({size} bytes)"
        )
    if n_vlrs * 54 > start - header_size:  # a VLR header alone is 54 bytes
        raise CorruptFileError(
            f"{path}: header field 'number_of_vlrs' is {n_vlrs}: more than the "
            f"{start - header_size} bytes before the points can hold"
        )
    if head[25] >= 4 and len(head) >= 247:
        evlr_start, n_evlrs = u(235, 8), u(243, 4)
        if n_evlrs and (evlr_start > size or n_evlrs * 60 > size - evlr_start):
            raise CorruptFileError(
                f"{path}: header field 'number_of_evlrs' is {n_evlrs} from byte {evlr_start}: "
                f"more than the file ({size} bytes) holds"
            )


def check_header(info: LasInfo) -> None:
    """InputError, naming the file and the header field, where the scales, offsets or
    bounds of ``info`` cannot be those of a real survey (see ``MAX_COORD_M``)."""
    for k, axis in enumerate(_AXES):
        scale = info.scales[k]
        if not (np.isfinite(scale) and 0 < scale <= MAX_SCALE_M):
            raise InputError(
                f"{info.path}: header field '{axis} scale' is {scale}: it must be a number of "
                f"metres > 0 and <= {MAX_SCALE_M:g} (e.g. 0.001)"
            )
        for name, value in ((f"{axis} offset", info.offsets[k]),):
            if not (np.isfinite(value) and abs(value) <= MAX_COORD_M):
                raise InputError(
                    f"{info.path}: header field '{name}' is {value}: no CRS has it (a finite "
                    f"number of metres, |value| <= {MAX_COORD_M:g}); coordinates would lose "
                    "precision"
                )
        if info.point_count == 0:
            continue
        lo, hi = info.mins[k], info.maxs[k]
        for name, value in ((f"min {axis}", lo), (f"max {axis}", hi)):
            if not (np.isfinite(value) and abs(value) <= MAX_COORD_M):
                raise InputError(
                    f"{info.path}: header field '{name}' is {value}: no CRS has it (a finite "
                    f"number of metres, |value| <= {MAX_COORD_M:g})"
                )
        if lo > hi:
            raise InputError(
                f"{info.path}: header field 'min {axis}' ({lo}) is above 'max {axis}' ({hi})"
            )


def _check_point_count(path: Path, count: int, minor: int, layout: tuple[int, int] | None) -> None:
    """CorruptFileError naming the header's count field where an uncompressed file
    (``layout``: offset to point data, bytes per point) is too short for the points its
    header promises, or a LAS 1.4 header's two counts disagree. (A LAZ file's count is
    checked as it is read: its size does not tell.)"""
    field = "point_count" if minor >= 4 else "legacy_point_count"
    with open(path, "rb") as fh:
        head = fh.read(247 + 8)
    if minor >= 4 and len(head) >= 111:
        legacy = int.from_bytes(head[107:111], "little")
        if legacy not in (0, count):
            raise CorruptFileError(
                f"{path}: header field 'legacy_point_count' is {legacy}, "
                f"'point_count' is {count}: they must agree (or legacy be 0)"
            )
    if layout is not None:
        start, record = layout
        size = path.stat().st_size
        holds = max(size - start, 0) // record if record else 0
        if count > holds:
            raise CorruptFileError(
                f"{path}: header field '{field}' promises {count} points, the file holds "
                f"{holds} ({size} bytes, {record} per point from byte {start})"
            )


def point_count_field(path: Path) -> str:
    """The header field that holds the point count of ``path``: ``point_count`` (LAS 1.4)
    or ``legacy_point_count`` (LAS 1.0–1.3)."""
    with open(path, "rb") as fh:
        head = fh.read(26)
    return "point_count" if len(head) == 26 and head[25] >= 4 else "legacy_point_count"


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
    info = las_info(path)  # the header checked: scales, offsets, bounds, count
    seen = 0
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    try:
        with laspy.open(path) as reader:
            header = reader.header
            crs = info.crs
            org = np.asarray(header.offsets if origin is None else origin, dtype=np.float64)
            for points in reader.chunk_iterator(chunk_points):
                if len(points) == 0:
                    break
                seen += len(points)
                cloud = _points_to_cloud(points, header, org, crs)
                if not np.all(np.isfinite(cloud.xyz)):
                    raise InputError(
                        f"{path}: field 'X/Y/Z' has non-finite coordinates "
                        f"(header scales {[float(v) for v in header.scales]}, "
                        f"offsets {[float(v) for v in header.offsets]})"
                    )
                lo = np.minimum(lo, cloud.xyz.min(axis=0) + org)
                hi = np.maximum(hi, cloud.xyz.max(axis=0) + org)
                _check_bounds(info, lo, hi, final=False)
                yield cloud
            expected = int(header.point_count)
    except InputError:
        raise
    except Exception as exc:  # laspy/lazrs raise many types for a damaged file
        raise CorruptFileError(
            f"{path}: truncated or damaged: read {seen} of the {info.point_count} points its "
            f"header field '{point_count_field(path)}' promises ({type(exc).__name__}: {exc})"
        ) from None
    if seen != expected:
        raise CorruptFileError(
            f"{path}: truncated: header field '{point_count_field(path)}' says {expected} "
            f"points, the file holds {seen}"
        )
    if seen:
        _check_bounds(info, lo, hi, final=True)


def _check_bounds(info: LasInfo, lo: np.ndarray, hi: np.ndarray, final: bool) -> None:
    """InputError naming the header field where the points read so far (``lo``, ``hi``,
    (3,) CRS metres) lie outside the header's bounds, or, once all are read (``final``),
    where the bounds are far wider than the points. Slack: 1 m or 1 % of the box, for
    writers that round or pad the box."""
    slack = np.maximum(1.0, 0.01 * (info.maxs - info.mins))
    for k, axis in enumerate(_AXES):
        # how far the points go beyond the header's box (> 0: outside it) at each end
        for name, header, points, beyond in (
            (f"min {axis}", info.mins[k], lo[k], info.mins[k] - lo[k]),
            (f"max {axis}", info.maxs[k], hi[k], hi[k] - info.maxs[k]),
        ):
            if beyond > slack[k] or (final and -beyond > slack[k]):
                verb = "reach" if beyond > 0 else "only reach"
                raise InputError(
                    f"{info.path}: header field '{name}' is {header:.3f} but the points "
                    f"{verb} {points:.3f}: the header disagrees with its points"
                )


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
        # intensity likewise all or none: the intensity check (streetcd.detect.intensity)
        # reads it when there are no colours
        intensity=(
            np.concatenate([c.intensity for c in clouds])
            if all(c.intensity is not None for c in clouds)
            else None
        ),
        # colours only when every file has them (the appearance check needs all or none)
        rgb=(
            np.concatenate([c.rgb for c in clouds])
            if all(c.rgb is not None for c in clouds)
            else None
        ),
        crs=next(iter(crss), None),
    )
