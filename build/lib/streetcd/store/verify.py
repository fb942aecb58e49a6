"""Checking a whole tile store (``streetcd verify STORE``, ``streetcd ingest --recheck``).

:func:`verify_store` reads every chunk of every array the committed index names (the CRC-32C
of each is checked as it is decoded), checks that every chunk the manifest implies exists,
that each array's metadata matches its manifest, and that the index agrees with the file
records (:meth:`~streetcd.store.tiles.TileStore.check_index`). It reads, never writes, and
takes no lock: an ingest committing meanwhile may make it report the sources it replaced.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from streetcd.errors import CorruptFileError
from streetcd.store.tiles import (
    TileStore,
    _problem,
    chunk_count,
    open_field,
    read_chunk,
    read_index,
    reingest_command,
    repair_hint,
)

# progress(chunks_done, chunks_total, source file name)
VerifyProgress = Callable[[int, int, str], None]


@dataclass(frozen=True)
class Problem:
    """One thing wrong in a store; ``source`` is the LAS/LAZ file whose points it concerns
    (None for the index itself)."""

    source: str | None
    message: str

    def __str__(self) -> str:
        return self.message


@dataclass
class VerifyReport:
    """What :func:`verify_store` checked and found."""

    store: Path
    sources: int = 0
    chunks: int = 0
    points: int = 0
    failed_files: int = 0  # files recorded as failed at ingest (not damage: listed apart)
    problems: list[Problem] = field(default_factory=list)

    @property
    def damaged(self) -> set[str]:
        """Source files whose points are damaged (their re-ingest repairs them)."""
        return {p.source for p in self.problems if p.source is not None}

    @property
    def ok(self) -> bool:
        return not self.problems


def verify_store(
    path: str | Path,
    *,
    only: Iterable[str] | None = None,
    progress: VerifyProgress | None = None,
) -> VerifyReport:
    """Check the store at ``path``: every chunk of the sources its index names (or of the
    source paths in ``only``), their metadata against the manifest, the index against the
    file records. Problems are collected (one per bad array or chunk), not raised.
    MissingInputError / InputError / CorruptFileError when the root record itself cannot be
    read (nothing else can be checked then)."""
    path = Path(path).resolve()
    report = VerifyReport(path)
    read_index(path)  # a bad root record raises: nothing can be checked without it
    try:
        store = TileStore.open(path, check=False)
    except CorruptFileError as exc:  # the index generation: nothing below it can be checked
        report.problems.append(Problem(None, str(exc)))
        return report
    report.failed_files = sum(r.get("status") == "failed" for r in store.files.values())
    try:
        store.check_index()
    except CorruptFileError as exc:
        report.problems.append(
            Problem(
                None,
                f"{exc}; the tile index is damaged, rebuild the store: "
                f"{reingest_command(store.index, path)}",
            )
        )
    wanted = None if only is None else set(only)
    rows = [r for r, (p, _) in enumerate(store.sources) if wanted is None or p in wanted]
    arrays = {row: _open_fields(store, row, report) for row in rows}
    total = sum(chunk_count(a) for fields in arrays.values() for a in fields.values())
    for row in rows:
        source, key = store.sources[row]
        report.sources += 1
        report.points += int(store.files.get(source, {}).get("points", 0))
        for name, a in arrays[row].items():
            folder = path / "points" / key / name
            for c in range(chunk_count(a)):
                try:
                    read_chunk(a, folder, c)
                except CorruptFileError as exc:
                    report.problems.append(Problem(source, _line(path, source, exc)))
                report.chunks += 1
                if progress is not None:
                    progress(report.chunks, total, Path(source).name)
    return report


def _open_fields(store: TileStore, row: int, report: VerifyReport) -> dict[str, Any]:
    """{field: array} of one source, a problem recorded for each that cannot be opened."""
    source, key = store.sources[row]
    out: dict[str, Any] = {}
    try:
        manifest = store._manifest(source)
    except CorruptFileError as exc:
        report.problems.append(Problem(source, _line(store.path, source, exc)))
        return out
    for name, want in manifest.items():
        try:
            out[name] = open_field(store.path / "points" / key / name, want, source)
        except CorruptFileError as exc:
            report.problems.append(Problem(source, _line(store.path, source, exc)))
    return out


def _line(store: Path, source: str, exc: CorruptFileError) -> str:
    return f"points of {source}, {_problem(exc)}; {repair_hint(source, store)}"
