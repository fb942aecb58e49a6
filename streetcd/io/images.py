"""Reading street images: sizes (from the header), pixels (decoded straight to RGB) and
capture times (EXIF).

Errors name the file: a missing image is MissingInputError, an image that cannot be decoded
(or a JPEG cut short) CorruptFileError, an image whose size disagrees with its pose, or whose
header states more pixels than the limit (a decompression bomb: a 19 KB JPEG may claim
30000x30000, 2.7 GB once decoded), InputError. The pixel limit is checked from the header,
before anything is decoded. A file is read as what its first bytes say it is, whatever its
name: a PNG named ``.jpg`` is read as a PNG.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import os
import struct
import warnings
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np

from streetcd.errors import CorruptFileError, InputError, MissingInputError
from streetcd.types import View

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
EXIF_IFD = 0x8769
DEFAULT_MAX_PIXELS = 100_000_000  # run.max_image_pixels: 100 MP, 25x a 4000x1000 frame
DATE_TIME_ORIGINAL = 36867  # EXIF "YYYY:MM:DD HH:MM:SS", the camera's clock
OFFSET_TIME_ORIGINAL = 36881  # EXIF 2.31 "+HH:MM", that clock's offset from UTC


def list_images(folder: str | Path) -> dict[str, Path]:
    """{file name: path} of the images directly in ``folder``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise MissingInputError(f"images folder not found: {folder}")
    # scandir's entries know their type from the directory itself: no stat per image (a
    # city's folder holds tens of thousands)
    with os.scandir(folder) as entries:
        names = [
            e.name
            for e in entries
            if os.path.splitext(e.name)[1].lower() in IMAGE_SUFFIXES and _is_file(e)
        ]
    return {name: folder / name for name in sorted(names)}


def _is_file(entry: os.DirEntry[str]) -> bool:
    """``entry.is_file()`` as ``Path.is_file`` answers it: False, not an error, for a
    dangling link or a loop of links (those are not images of the folder)."""
    try:
        return entry.is_file()
    except OSError as exc:
        if exc.errno in (errno.ENOENT, errno.ENOTDIR, errno.EBADF, errno.ELOOP):
            return False
        raise


def read_image(path: str | Path, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Read an image file as (H, W, 3) uint8 RGB.

    MissingInputError if it does not exist, CorruptFileError naming the file if it cannot be
    decoded or a JPEG is truncated (libjpeg would return the top half and a grey rest),
    InputError if its header states more than ``max_pixels`` pixels (:func:`check_pixels`).
    """
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(f"image not found: {path}")
    data = np.fromfile(path, dtype=np.uint8)
    check_pixels(path, header_of(path, data[:HEADER_BYTES].tobytes()), max_pixels)
    return decode_rgb(path, data)


def read_rgb(path: Path, view: View, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """(H, W, 3) uint8 RGB image of ``view``, read-only: nothing can change it, so the
    worker's image cache may share it among the views of a batch and a
    :class:`~streetcd.detect.cache.SurfaceCache` may keep its checksum while it lives.

    The header is read first: InputError naming the file when it states more than
    ``max_pixels`` pixels (nothing is decoded then), or when the image's size is not the
    pose's and not the same camera at another resolution (:func:`fits_camera`; the caller
    then uses :func:`fit_view`)."""
    data = np.fromfile(path, dtype=np.uint8)
    header = header_of(path, data[:HEADER_BYTES].tobytes())
    check_pixels(path, header, max_pixels)
    i = view.intrinsics
    if not fits_camera(header.width, header.height, i.width, i.height):
        raise InputError(
            f"{path}: image is {header.width}x{header.height} but the pose of {view.name!r} "
            f"says {i.width}x{i.height} (another aspect ratio: not the same camera rescaled)"
        )
    rgb = decode_rgb(path, data)
    rgb.flags.writeable = False
    return rgb


def decode_rgb(path: Path, data: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB image from the bytes ``data`` of the file ``path``;
    CorruptFileError naming the file if they cannot be decoded or a JPEG is truncated
    (libjpeg would return the top half and a grey rest; OpenCV 5 refuses it, earlier
    releases did not)."""
    # by content, not by name: a PNG named .jpg is a PNG, and cv2 decodes it as one
    if data[:2].tobytes() == JPEG_MAGIC and b"\xff\xd9" not in data[-64:].tobytes():
        raise CorruptFileError(f"{path}: truncated JPEG (no end-of-image marker)")
    # decoded straight to RGB: the same pixels as BGR then cvtColor, without the copy
    rgb = cv2.imdecode(data, cv2.IMREAD_COLOR_RGB) if data.size else None
    if rgb is None:
        raise CorruptFileError(f"{path}: cannot be decoded as an image ({data.size} bytes)")
    return rgb


@dataclass(frozen=True)
class ImageHeader:
    """What an image file's header says: its ``format`` (``"JPEG"``, ``"PNG"``, or PIL's
    name for others) and its size in pixels."""

    format: str
    width: int
    height: int

    @property
    def pixels(self) -> int:
        return self.width * self.height


HEADER_BYTES = 1 << 16  # a JPEG's frame header follows its EXIF, which is at most 64 KB
JPEG_MAGIC = b"\xff\xd8"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (they carry the size): C0-CF but DHT, JPG and DAC
_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def read_header(path: str | Path) -> ImageHeader:
    """The header of the image at ``path``, read without decoding any pixel (the first
    64 KB at most). MissingInputError if there is no such file, CorruptFileError naming it
    if its header cannot be read."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(HEADER_BYTES)
    except FileNotFoundError:
        raise MissingInputError(f"image not found: {path}") from None
    return header_of(path, head)


def header_of(path: Path, head: bytes) -> ImageHeader:
    """:func:`read_header` from the file's first bytes ``head`` (JPEG and PNG parsed here;
    other formats through PIL, which reads the header only)."""
    if head.startswith(JPEG_MAGIC):
        size = _jpeg_size(head)
        if size is None:
            raise CorruptFileError(f"{path}: JPEG without a frame header in its first 64 KB")
        return ImageHeader("JPEG", *size)
    if head.startswith(PNG_MAGIC) and len(head) >= 24 and head[12:16] == b"IHDR":
        width, height = struct.unpack(">II", head[16:24])
        return ImageHeader("PNG", width, height)
    return _pil_header(path)


def _jpeg_size(head: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's start-of-frame segment, None if ``head`` has none."""
    k = 2
    while k + 9 <= len(head):
        if head[k] != 0xFF:
            return None
        marker = head[k + 1]
        if marker == 0xFF:  # fill byte before a marker
            k += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
            k += 2
            continue
        (length,) = struct.unpack(">H", head[k + 2 : k + 4])
        if marker in _SOF:
            height, width = struct.unpack(">HH", head[k + 5 : k + 9])
            return width, height
        k += 2 + length
    return None


def _pil_header(path: Path) -> ImageHeader:
    """The header of a format other than JPEG and PNG (TIFF) through PIL."""
    from PIL import Image

    with warnings.catch_warnings():
        # our limit is check_pixels'; PIL's warning is about its own
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        try:
            with Image.open(path) as image:
                return ImageHeader(str(image.format), *image.size)
        except Image.DecompressionBombError as exc:  # PIL's own hard limit, 2x 89 MP
            raise InputError(f"{path}: {exc}; refused before decoding") from None
        except (OSError, SyntaxError, ValueError) as exc:
            why = str(exc).replace(f" {str(path)!r}", "").replace(str(path), "the file")
            raise CorruptFileError(f"{path}: cannot be decoded as an image ({why})") from None


def check_pixels(path: Path, header: ImageHeader, max_pixels: int) -> None:
    """InputError naming the file when its header states more than ``max_pixels`` pixels
    (``run.max_image_pixels``): such an image is refused before it is decoded."""
    if header.pixels > max_pixels:
        raise InputError(
            f"{path}: {header.format} header says {header.width}x{header.height} "
            f"({header.pixels / 1e6:.1f} MP), over the limit of {max_pixels / 1e6:.1f} MP "
            "(run.max_image_pixels); refused before decoding"
        )


def fits_camera(width: int, height: int, cam_width: int, cam_height: int) -> bool:
    """Whether an image ``width`` x ``height`` is the camera's ``cam_width`` x
    ``cam_height`` frame, or the same frame at another resolution (one scale factor, each
    side rounded to whole pixels)."""
    if (width, height) == (cam_width, cam_height):
        return True
    factor = width / cam_width
    return round(cam_height * factor) == height


def fit_view(view: View, width: int, height: int) -> View:
    """``view`` with its intrinsics rescaled to an image ``width`` x ``height`` of the same
    camera (:func:`fits_camera`); ``view`` itself when the sizes agree."""
    i = view.intrinsics
    if (width, height) == (i.width, i.height):
        return view
    scaled = i.scaled(width / i.width)
    # the rounding of the scaled sides may differ from the file's by one pixel
    return dataclasses.replace(
        view, intrinsics=dataclasses.replace(scaled, width=width, height=height)
    )


def capture_time(path: Path) -> str | None:
    """When the image at ``path`` was taken, as an index timestamp (UTC), or None.

    From EXIF ``DateTimeOriginal``, shifted by ``OffsetTimeOriginal`` where given; without
    an offset the camera clock is taken as UTC (survey cameras run on GPS/UTC time). Pose
    files give only a number of seconds whose epoch (GPS week, GPS, Unix) they do not
    state, so they are not used. Reads the header only; never fails (None instead, also
    for a header PIL refuses as a decompression bomb: the pixels are refused by
    :func:`check_pixels`, not here).
    """
    # PIL here, not at the top: a worker imports this module for its pixels, and PIL's
    # import is paid in the worker's warm-up thread instead (streetcd.run.worker).
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
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
    except Exception as exc:  # no EXIF, a malformed date, a header PIL refuses: all unknown
        log.debug("%s: no capture time: %s", path, exc)
        return None
    return when.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
