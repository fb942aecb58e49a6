"""How ingest reads a source file of the MLS archive: the reader protocol and the readers.

:class:`PointReader` is what :func:`streetcd.store.ingest.ingest` asks of a reader (a header,
then the points in chunks); :class:`LaspyReader` reads LAS/LAZ through laspy, and
:func:`get_reader` picks a reader by name (the PDAL one, :class:`streetcd.io.pdal.PdalReader`,
is imported only when asked for). :func:`find_archive_files` lists an archive's LAS/LAZ files.
"""

from __future__ import annotations

import glob
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Protocol

import numpy as np

from streetcd.errors import InputError, MissingInputError
from streetcd.io.las import LasInfo, iter_las_chunks, las_info
from streetcd.io.pdal import PdalReader
from streetcd.types import PointCloud

LAS_SUFFIXES = (".las", ".laz")


class PointReader(Protocol):
    """How ingest reads one source file: its header, then its points in chunks.

    ``chunks`` yields :class:`PointCloud` with CRS coordinates (origin zeros) in float64.
    Implementations must be picklable (they travel to worker processes).
    """

    name: str

    def info(self, path: Path) -> LasInfo: ...

    def chunks(self, path: Path, chunk_points: int) -> Iterator[PointCloud]: ...


class LaspyReader:
    """LAS/LAZ through laspy's chunked reader (lazrs backend for LAZ)."""

    name = "laspy"

    def info(self, path: Path) -> LasInfo:
        return las_info(path)

    def chunks(self, path: Path, chunk_points: int) -> Iterator[PointCloud]:
        return iter_las_chunks(path, chunk_points, origin=np.zeros(3))


def get_reader(name: str = "laspy", pipeline: str | Path | None = None) -> PointReader:
    """The reader called ``name`` ("laspy" or "pdal"); ``pipeline`` is a PDAL pipeline JSON."""
    if name == "laspy":
        if pipeline is not None:
            raise InputError(f"--pipeline {pipeline} needs --reader pdal (reader is {name!r})")
        return LaspyReader()
    if name == "pdal":
        return PdalReader.from_file(pipeline) if pipeline is not None else PdalReader()
    raise InputError(f"unknown reader {name!r}; choose 'laspy' or 'pdal'")


def find_archive_files(archive: str | Path | Sequence[str | Path]) -> list[Path]:
    """LAS/LAZ files of an archive: a directory (searched recursively), a glob pattern, a
    single file, or a list of files. Sorted absolute paths; MissingInputError if none."""
    if isinstance(archive, (list, tuple)):
        paths = [Path(p) for p in archive]
        for p in paths:
            if not p.is_file():
                raise MissingInputError(f"point cloud file not found: {p}")
    else:
        a = Path(str(archive))
        if a.is_dir():
            paths = [p for p in a.rglob("*") if p.is_file() and p.suffix.lower() in LAS_SUFFIXES]
        elif a.is_file():
            paths = [a]
        else:
            paths = [Path(p) for p in glob.glob(str(archive), recursive=True)]
            paths = [p for p in paths if p.is_file()]
    paths = sorted({p.resolve() for p in paths if not p.name.startswith(".")})
    if not paths:
        raise MissingInputError(f"no LAS/LAZ files in archive {archive}")
    return paths
