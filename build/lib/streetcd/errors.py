"""Exceptions. One root (`StreetcdError`); each subclass also inherits the builtin a caller
would naturally catch, so ``except ValueError`` keeps working around streetcd calls.

Messages speak to the user: they name the file (or view), the field and the value.
"""

from __future__ import annotations


class StreetcdError(Exception):
    """Root of every error streetcd raises on purpose."""


class InputError(StreetcdError, ValueError):
    """An input file or value is malformed (bad field, NaN, wrong shape)."""


class MissingInputError(StreetcdError, FileNotFoundError):
    """An input file, pose or view that the work needs does not exist."""


class CorruptFileError(InputError):
    """A file exists but cannot be decoded (truncated LAZ, unreadable JPEG)."""


class CRSMismatchError(InputError):
    """Files that must share one coordinate reference system do not."""


class EmptyViewError(StreetcdError, RuntimeError):
    """A view sees no reference points, so nothing can be compared in it."""


class OptionalDependencyError(StreetcdError, ImportError):
    """An optional backend (e.g. PDAL) was asked for but is not installed."""


class StoreLockedError(StreetcdError, RuntimeError):
    """Another ingest holds the tile store's lock."""


class IndexBusyError(StreetcdError, RuntimeError):
    """Another run holds the change index's run lock."""
