"""Optional PDAL reader: any format PDAL reads, optionally through a user pipeline.

Same interface as :class:`streetcd.io.readers.LaspyReader` (``info`` and ``chunks``), used by
``streetcd ingest --reader pdal [--pipeline pipeline.json]``. The pipeline file is a PDAL
pipeline (a list of stages, or ``{"pipeline": [...]}``); the source file is put in its reader
stage (the first stage when it is a ``readers.*`` stage or a file name), or prepended as a
file name so PDAL picks the reader from the extension. Later stages (``filters.*``) apply.

``pdal`` needs the PDAL C++ library (``conda install -c conda-forge pdal python-pdal``, or
``pip install streetcd[pdal]`` where the library is installed).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from streetcd.errors import CorruptFileError, InputError, MissingInputError, OptionalDependencyError
from streetcd.io.las import LasInfo, check_header, crs_string
from streetcd.types import PointCloud

INSTALL_HINT = (
    "the PDAL reader needs the 'pdal' Python package and the PDAL C++ library: "
    "pip install streetcd[pdal] (with PDAL installed, e.g. conda install -c "
    "conda-forge pdal python-pdal), or use --reader laspy"
)


def import_pdal() -> Any:
    """``import pdal``, or OptionalDependencyError with the one-line install hint."""
    try:
        import pdal
    except ImportError:
        raise OptionalDependencyError(INSTALL_HINT) from None
    return pdal


def _stages(pipeline: list[Any], path: Path) -> list[Any]:
    """The user's stages with ``path`` as the source."""
    stages = list(pipeline)
    first = stages[0] if stages else None
    if isinstance(first, str):
        return [str(path), *stages[1:]]
    if isinstance(first, dict) and str(first.get("type", "")).startswith("readers."):
        return [{**first, "filename": str(path)}, *stages[1:]]
    return [str(path), *stages]


class PdalReader:
    """Reads point files with PDAL; ``pipeline`` is a list of PDAL stages (may be empty)."""

    name = "pdal"

    def __init__(self, pipeline: list[Any] | None = None) -> None:
        import_pdal()  # fail at once, not on a worker
        self.pipeline = list(pipeline or [])

    @classmethod
    def from_file(cls, path: str | Path) -> PdalReader:
        path = Path(path)
        if not path.is_file():
            raise MissingInputError(f"PDAL pipeline file not found: {path}")
        try:
            spec = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise InputError(f"{path}: not valid JSON: {exc}") from None
        stages = spec.get("pipeline") if isinstance(spec, dict) else spec
        if not isinstance(stages, list):
            raise InputError(f"{path}: field 'pipeline' must be a list of stages")
        return cls(stages)

    def _pipeline(self, path: Path) -> Any:
        pdal = import_pdal()
        if not path.exists():
            raise MissingInputError(f"point cloud file not found: {path}")
        return pdal.Pipeline(json.dumps(_stages(self.pipeline, path)))

    def info(self, path: Path) -> LasInfo:
        """Header-level facts from PDAL's quickinfo (no points read)."""
        try:
            qi = next(iter(self._pipeline(path).quickinfo.values()))
        except (RuntimeError, StopIteration) as exc:
            raise CorruptFileError(f"{path}: PDAL cannot read it: {exc}") from None
        b = qi.get("bounds", {})
        mins = np.array([b.get("minx", 0.0), b.get("miny", 0.0), b.get("minz", 0.0)], float)
        maxs = np.array([b.get("maxx", 0.0), b.get("maxy", 0.0), b.get("maxz", 0.0)], float)
        wkt = (qi.get("srs") or {}).get("wkt") or None
        info = LasInfo(
            path,
            int(qi.get("num_points", 0)),
            crs_string(wkt) if wkt else None,
            mins,
            maxs,
            np.zeros(3),
            np.full(3, 0.001),
        )
        check_header(info)  # bounds that cannot be real fail the file, as with laspy
        return info

    def chunks(self, path: Path, chunk_points: int) -> Iterator[PointCloud]:
        """Stream PDAL's point views in chunks (CRS coordinates, float64)."""
        crs = self.info(path).crs
        try:
            for arr in self._pipeline(path).iterator(chunk_size=chunk_points):
                yield _to_cloud(arr, crs, path)
        except RuntimeError as exc:
            raise CorruptFileError(f"{path}: PDAL failed while reading: {exc}") from None


def _to_cloud(arr: np.ndarray, crs: str | None, path: Path) -> PointCloud:
    """A PDAL structured array (X, Y, Z, Classification, ...) → PointCloud, origin zeros."""
    names = set(arr.dtype.names or ())
    xyz = np.column_stack([arr["X"], arr["Y"], arr["Z"]]).astype(np.float64)
    if not np.all(np.isfinite(xyz)):
        raise InputError(f"{path}: field 'X/Y/Z' has non-finite coordinates")
    n = len(arr)
    rgb = None
    if {"Red", "Green", "Blue"} <= names:
        rgb = np.column_stack([arr["Red"], arr["Green"], arr["Blue"]]).astype(np.uint16)
    return PointCloud(
        xyz=xyz,
        origin=np.zeros(3),
        classification=(
            arr["Classification"].astype(np.uint8)
            if "Classification" in names
            else np.ones(n, np.uint8)
        ),
        intensity=arr["Intensity"].astype(np.uint16) if "Intensity" in names else None,
        rgb=rgb,
        gps_time=arr["GpsTime"].astype(np.float64) if "GpsTime" in names else None,
        crs=crs,
    )
