"""Reading street images: pixels (decoded straight to RGB) and capture times (EXIF).

Errors name the file: a missing image is MissingInputError, an image that cannot be decoded
(or a JPEG cut short) CorruptFileError, an image whose size disagrees with its pose InputError.
"""

from __future__ import annotations

import logging
from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np

from streetcd.errors import CorruptFileError, InputError, MissingInputError
from streetcd.types import View

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
EXIF_IFD = 0x8769
DATE_TIME_ORIGINAL = 36867  # EXIF "YYYY:MM:DD HH:MM:SS", the camera's clock
OFFSET_TIME_ORIGINAL = 36881  # EXIF 2.31 "+HH:MM", that clock's offset from UTC


def list_images(folder: str | Path) -> dict[str, Path]:
    """{file name: path} of the images directly in ``folder``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise MissingInputError(f"images folder not found: {folder}")
    return {
        p.name: p
        for p in sorted(folder.iterdir())
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    }


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as (H, W, 3) uint8 RGB.

    MissingInputError if it does not exist, CorruptFileError naming the file if it cannot be
    decoded or a JPEG is truncated (libjpeg would return the top half and a grey rest).
    """
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(f"image not found: {path}")
    return decode_rgb(path, np.fromfile(path, dtype=np.uint8))


def read_rgb(path: Path, view: View) -> np.ndarray:
    """(H, W, 3) uint8 RGB image of ``view``, read-only: nothing can change it, so the
    worker's image cache may share it among the views of a batch and a
    :class:`~streetcd.detect.cache.SurfaceCache` may keep its checksum while it lives.
    InputError naming the file when its size is not the one the pose states."""
    rgb = decode_rgb(path, np.fromfile(path, dtype=np.uint8))
    h, w = rgb.shape[:2]
    i = view.intrinsics
    if (w, h) != (i.width, i.height):
        raise InputError(
            f"{path}: image is {w}x{h} but the pose of {view.name!r} says {i.width}x{i.height}"
        )
    rgb.flags.writeable = False
    return rgb


def decode_rgb(path: Path, data: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB image from the bytes ``data`` of the file ``path``;
    CorruptFileError naming the file if they cannot be decoded or a JPEG is truncated
    (libjpeg would return the top half and a grey rest; OpenCV 5 refuses it, earlier
    releases did not)."""
    if path.suffix.lower() in (".jpg", ".jpeg") and b"\xff\xd9" not in data[-64:].tobytes():
        raise CorruptFileError(f"{path}: truncated JPEG (no end-of-image marker)")
    # decoded straight to RGB: the same pixels as BGR then cvtColor, without the copy
    rgb = cv2.imdecode(data, cv2.IMREAD_COLOR_RGB) if data.size else None
    if rgb is None:
        raise CorruptFileError(f"{path}: cannot be decoded as an image ({data.size} bytes)")
    return rgb


def capture_time(path: Path) -> str | None:
    """When the image at ``path`` was taken, as an index timestamp (UTC), or None.

    From EXIF ``DateTimeOriginal``, shifted by ``OffsetTimeOriginal`` where given; without
    an offset the camera clock is taken as UTC (survey cameras run on GPS/UTC time). Pose
    files give only a number of seconds whose epoch (GPS week, GPS, Unix) they do not
    state, so they are not used. Reads the header only; never fails (None instead).
    """
    # PIL here, not at the top: a worker imports this module for its pixels, and PIL's
    # import is paid in the worker's warm-up thread instead (streetcd.run.worker).
    from PIL import Image

    try:
        with Image.open(path) as image:
            exif = image.getexif().get_ifd(EXIF_IFD)
        text = str(exif.get(DATE_TIME_ORIGINAL, "")).strip().rstrip("\x00")
        if not text:
            return None
        when = datetime.strptime(text, "%Y:%m:%d %H:%M:%S")
        offset = str(exif.get(OFFSET_TIME_ORIGINAL, "")).strip().rstrip("\x00")
        if offset:
            when = datetime.fromisoformat(when.isoformat() + offset)
        else:
            when = when.replace(tzinfo=UTC)
    except (OSError, ValueError, SyntaxError) as exc:  # no EXIF, or a malformed date
        log.debug("%s: no capture time: %s", path, exc)
        return None
    return when.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
