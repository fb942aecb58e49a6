"""Pose formats: COLMAP text and binary models, our omega/phi/kappa CSV, the OPK exports of
Pix4D and Agisoft Metashape, and OpenSfM's ``reconstruction.json``.

Every reader returns a :class:`~streetcd.types.PoseSet` in our conventions (see
``streetcd.geometry.camera``). Readers raise :class:`~streetcd.errors.InputError` (or a
subclass) naming the file, the line and the field on malformed input, and nothing else: any
bytes give poses or one such error (``tests/test_bad_inputs.py`` fuzzes them). Text files
are UTF-8; a byte-order mark (as spreadsheets write) and CRLF line ends are accepted.

Image names must name a file inside the images folder: a name that is empty, absolute, has a
drive letter, climbs out with ``..``, or holds a NUL or control character is refused for that
view (:func:`image_name_problem`); with ``bad_rows`` the reading goes on.

COLMAP
    ``cameras.txt`` + ``images.txt`` (or ``.bin``). Poses are world→camera quaternion and
    translation. COLMAP puts the centre of the top-left pixel at (0.5, 0.5); we shift the
    principal point by −0.5 on reading and +0.5 on writing. A comment line
    ``# CRS: EPSG:XXXX`` in ``images.txt`` states the world frame (COLMAP ignores comments).

OPK CSV
    One row per image: ``name,x,y,z,omega,phi,kappa`` (metres in the CRS, degrees, the
    photogrammetric convention of :func:`streetcd.geometry.camera.opk_to_rotation`), then the
    intrinsics ``width,height,fx,fy,cx,cy`` (pixels, OpenCV convention), the optional
    distortion ``k1,k2,p1,p2,k3`` (zero when absent) and an optional ``time`` (seconds). The
    first line may be ``# crs=EPSG:XXXX``. Header names are matched without regard to case;
    the delimiter is ``,``, ``;`` or a tab, whichever the header uses.

Pix4D OPK export (``*_calibrated_external_camera_parameters.txt``)
    A header ``imageName X Y Z Omega Phi Kappa``, then one whitespace-separated row per image:
    camera centre (CRS metres) and omega/phi/kappa in degrees, the same photogrammetric
    convention as our OPK CSV. It holds no intrinsics: they come from a COLMAP
    ``cameras.txt`` with one camera beside it (:func:`read_sidecar_camera`).

Metashape OPK export ("Export Cameras", Omega Phi Kappa ``.txt``)
    Optional ``# CoordinateSystem: … (EPSG::XXXX)`` line, a header
    ``#Label X/East Y/North Z/Altitude Omega Phi Kappa r11 … r33`` (the ``r`` columns optional),
    tab-separated rows. Same angle convention; ``r11 … r33`` must be the rotation of those
    angles (either way round), else the row is refused. Intrinsics as for Pix4D.

OpenSfM ``reconstruction.json``
    A list of reconstructions, each with ``cameras`` (``projection_type`` perspective,
    simple_radial, radial or brown; ``focal`` or ``focal_x``/``focal_y`` and ``c_x``/``c_y``
    normalised by the larger image side, principal point relative to the image centre) and
    ``shots`` (``rotation``: world→camera angle-axis in radians, ``translation``, ``camera``,
    optional ``capture_time``). OpenSfM's camera axes are OpenCV's. Poses stay in the
    reconstruction's frame (``crs`` None).

:func:`read_poses` picks the reader from the file's content (a Metashape ``.txt`` is not a
COLMAP ``images.txt``), then from its name.
"""

from __future__ import annotations

import codecs
import csv
import json
import math
import os
import re
import stat
import struct
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import numpy as np

from streetcd.errors import CorruptFileError, InputError, MissingInputError
from streetcd.geometry.camera import (
    opk_to_rotation,
    quaternion_to_rotation,
    rotation_to_opk,
    rotation_to_quaternion,
)
from streetcd.types import Intrinsics, Pose, PoseSet, View

# COLMAP camera models we read: name -> (model id, parameter names)
_COLMAP_MODELS: dict[str, tuple[int, tuple[str, ...]]] = {
    "SIMPLE_PINHOLE": (0, ("f", "cx", "cy")),
    "PINHOLE": (1, ("fx", "fy", "cx", "cy")),
    "SIMPLE_RADIAL": (2, ("f", "cx", "cy", "k1")),
    "RADIAL": (3, ("f", "cx", "cy", "k1", "k2")),
    "OPENCV": (4, ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    "FULL_OPENCV": (6, ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
}
_COLMAP_BY_ID = {mid: (name, params) for name, (mid, params) in _COLMAP_MODELS.items()}

OPK_FIELDS = (
    "name", "x", "y", "z", "omega", "phi", "kappa",
    "width", "height", "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "time",
)  # fmt: skip
OPK_REQUIRED = OPK_FIELDS[:13]  # distortion and time may be left out
_DISTORTION = ("k1", "k2", "p1", "p2", "k3")
PIX4D_HEADER = ("imagename", "x", "y", "z", "omega", "phi", "kappa")
_METASHAPE_R = tuple(f"r{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3))

# A pose line longer than this is not a pose line (COLMAP's POINTS2D lines hold ~30 bytes a
# point: 64 MiB is two million points in one image); reading stops before memory runs out.
MAX_LINE_BYTES = 64 << 20
MAX_JSON_BYTES = 512 << 20  # OpenSfM's file is read whole; a city's is tens of MB
_MAX_NAME_BYTES = 4096  # an image name in images.bin (PATH_MAX)
_DRIVE = re.compile(r"^[A-Za-z]:")


# --- values and names -------------------------------------------------------------------


def _finite(value: Any, path: Path, line: int | str, field: str) -> float:
    """``value`` as a finite float; InputError naming ``path:line`` and ``field`` if not."""
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise InputError(f"{path}:{line}: field {field!r} is not a number: {value!r}")
    try:
        x = float(value)
    except (ValueError, OverflowError):
        raise InputError(f"{path}:{line}: field {field!r} is not a number: {value!r}") from None
    if not math.isfinite(x):
        raise InputError(f"{path}:{line}: field {field!r} is not finite: {value!r}")
    return x


def _whole(value: Any, path: Path, line: int | str, field: str) -> int:
    """``value`` as an int (``"1920"`` or ``1920.0``); InputError if it has a fraction."""
    x = _finite(value, path, line, field)
    if not x.is_integer() or abs(x) >= 2**63:
        raise InputError(f"{path}:{line}: field {field!r} is not a whole number: {value!r}")
    return int(x)


def image_name_problem(name: str) -> str | None:
    """Why ``name`` cannot name an image inside the images folder, or None when it can.

    Refused: empty names, NUL and control characters, text that is not valid Unicode, absolute
    paths, drive letters and ``..`` (or ``.``) parts, with ``/`` or ``\\`` as separator. A
    relative name with folders (``cam0/IMG_1.jpg``) stays inside and is left to the caller.
    """
    if not name.strip():
        return "it is empty"
    if "\x00" in name:
        return "it holds a NUL byte"
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        return "it holds a control character"
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        return "it is not valid Unicode"
    if name.startswith(("/", "\\")):
        return "it is an absolute path"
    if _DRIVE.match(name):
        return "it starts with a drive letter"
    parts = re.split(r"[/\\]", name)
    if ".." in parts:
        return "it climbs out of the images folder ('..')"
    if "." in parts or "" in parts:
        return "it has an empty or '.' path part"
    return None


def _checked_name(name: str, path: Path, line: int | str, field: str = "name") -> str:
    why = image_name_problem(name)
    if why is not None:
        raise InputError(f"{path}:{line}: field {field!r} = {name!r} is refused: {why}")
    return name


def _intrinsics(where: str, *args: Any) -> Intrinsics:
    """Intrinsics(*args); its InputError prefixed with ``where`` (file:line or file: camera)."""
    try:
        return Intrinsics(*args)
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


def _pose(where: str, R: np.ndarray, t: np.ndarray) -> Pose:
    try:
        return Pose(R, t)
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


def _opk_pose(where: str, num: dict[str, float]) -> Pose:
    """The pose of a camera at ``num``'s x, y, z (world, metres) turned by its omega, phi,
    kappa (degrees; :func:`~streetcd.geometry.camera.opk_to_rotation`); InputError naming
    ``where`` and the centre when ``t = -R C`` is not finite (finite coordinates near 1e308
    overflow it: a fuzzed file, no survey)."""
    R = opk_to_rotation(num["omega"], num["phi"], num["kappa"])
    center = np.array([num["x"], num["y"], num["z"]])
    with np.errstate(over="ignore", invalid="ignore"):
        t = -R @ center
    if not np.isfinite(t).all():
        raise InputError(f"{where}: fields 'x, y, z' = {center.tolist()} are too large")
    # a product of three rotations of finite angles: Pose's rotation test (a third of
    # reading a city's pose file) has nothing to find
    return Pose.of_rotation(R, t)


def _intrinsics_from_colmap(model: str, width: int, height: int, p: dict[str, float]) -> Intrinsics:
    fx = p.get("fx", p.get("f"))
    fy = p.get("fy", p.get("f"))
    assert fx is not None and fy is not None
    if model == "FULL_OPENCV" and any(p[k] != 0.0 for k in ("k4", "k5", "k6")):
        raise InputError("FULL_OPENCV with rational terms k4..k6 is not supported")
    dist = (
        p.get("k1", 0.0),
        p.get("k2", 0.0),
        p.get("p1", 0.0),
        p.get("p2", 0.0),
        p.get("k3", 0.0),
    )
    return Intrinsics(width, height, fx, fy, p["cx"] - 0.5, p["cy"] - 0.5, dist)


# --- reading files ----------------------------------------------------------------------


def _open(path: Path) -> IO[bytes]:
    """``path`` opened for binary reading; MissingInputError if absent, InputError if it is
    not a regular file (a folder, or a FIFO that would block the run)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise MissingInputError(f"pose file not found: {path}") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot be read: {exc}") from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{path}: is a folder, not a pose file")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{path}: is not a regular file")
    try:
        return open(path, "rb")
    except OSError as exc:
        raise InputError(f"{path}: cannot be read: {exc.strerror}") from None


def _text_lines(path: Path) -> Iterator[tuple[int, str]]:
    """Every line of the UTF-8 text file ``path`` as (number from 1, text without its line
    end), streamed; a leading byte-order mark is dropped. CorruptFileError naming the line
    for bytes that are not UTF-8 and for a line longer than :data:`MAX_LINE_BYTES`."""
    with _open(path) as fh:
        number = 0
        while raw := fh.readline(MAX_LINE_BYTES + 1):
            number += 1
            if len(raw) > MAX_LINE_BYTES:
                raise CorruptFileError(
                    f"{path}:{number}: line longer than {MAX_LINE_BYTES >> 20} MiB; not a pose file"
                )
            if number == 1 and raw.startswith(codecs.BOM_UTF8):
                raw = raw[len(codecs.BOM_UTF8) :]
            try:
                text = raw.decode("utf-8")
            except UnicodeDecodeError as exc:
                raise CorruptFileError(
                    f"{path}:{number}: not UTF-8 text (byte {raw[exc.start]:#04x} at column "
                    f"{exc.start + 1}); save the file as UTF-8"
                ) from None
            yield number, text.rstrip("\r\n")


def _data_lines(path: Path) -> Iterable[tuple[int, str]]:
    """The lines of ``path`` that are neither empty nor ``#`` comments."""
    for number, line in _text_lines(path):
        if line.strip() and not line.lstrip().startswith("#"):
            yield number, line


def _crs_of(comment: str) -> str | None:
    """The CRS a ``# crs=…`` / ``# CRS: …`` comment states (text after ``#``), or None."""
    body = comment.strip()
    if body.lower().startswith(("crs:", "crs=")):
        return body[4:].strip() or None
    return None


def _crs_comment(path: Path) -> str | None:
    for _, line in _text_lines(path):
        if not line.startswith("#"):
            break
        crs = _crs_of(line[1:])
        if crs:
            return crs
    return None


# --- COLMAP text ------------------------------------------------------------------------


class _Rows:
    """The views a pose file gives and the rows it refuses.

    Without ``bad_rows`` the first refused row stops the reading (its InputError goes up);
    with a list, ``(name, error)`` is appended to it and the reading goes on.
    """

    def __init__(self, bad_rows: list[tuple[str, str]] | None) -> None:
        self.views: list[View] = []
        self.bad_rows = bad_rows
        self.n_bad = 0

    @contextmanager
    def row(self, name: str) -> Iterator[None]:
        """Read one row; ``name`` is its image name, or ``file:line`` where it has none."""
        try:
            yield
        except InputError as exc:
            if self.bad_rows is None:
                raise
            self.bad_rows.append((name, str(exc)))
            self.n_bad += 1

    def pose_set(self, crs: str | None, source: Path, empty: str) -> PoseSet:
        """The views read; ``empty`` is the error of a file that held no row at all (a file
        whose every row was refused gives an empty set: its rows are in ``bad_rows``)."""
        if not self.views and not self.n_bad:
            raise InputError(empty)
        return PoseSet(tuple(self.views), crs, source)


def read_colmap_cameras_text(path: Path) -> dict[int, Intrinsics]:
    cameras: dict[int, Intrinsics] = {}
    for number, line in _data_lines(path):
        parts = line.split()
        if len(parts) < 4:
            raise InputError(f"{path}:{number}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS…")
        model = parts[1]
        if model not in _COLMAP_MODELS:
            raise InputError(
                f"{path}:{number}: field 'MODEL' = {model!r} is not supported "
                f"(use one of {', '.join(_COLMAP_MODELS)})"
            )
        names = _COLMAP_MODELS[model][1]
        if len(parts) != 4 + len(names):
            raise InputError(
                f"{path}:{number}: model {model} needs {len(names)} parameters "
                f"({', '.join(names)}), got {len(parts) - 4}"
            )
        values = {n: _finite(v, path, number, n) for n, v in zip(names, parts[4:], strict=True)}
        camera_id = _whole(parts[0], path, number, "CAMERA_ID")
        width = _whole(parts[2], path, number, "WIDTH")
        height = _whole(parts[3], path, number, "HEIGHT")
        try:
            cameras[camera_id] = _intrinsics_from_colmap(model, width, height, values)
        except InputError as exc:
            raise InputError(f"{path}:{number}: {exc}") from None
    return cameras


def read_colmap_text(
    path: str | Path,
    image_dir: str | Path | None = None,
    *,
    bad_rows: list[tuple[str, str]] | None = None,
) -> PoseSet:
    """Read a COLMAP text model: ``path`` is ``images.txt`` or the folder holding it.

    ``cameras.txt`` must lie beside ``images.txt``. Image paths are resolved against
    ``image_dir`` when given. Returns views in file order; ``time`` is the file order.
    bad_rows : as :func:`read_opk_csv`, for malformed image lines.
    """
    path = Path(path)
    images_txt = path / "images.txt" if path.is_dir() else path
    cameras_txt = images_txt.with_name("cameras.txt")
    if not images_txt.exists():
        raise MissingInputError(f"COLMAP images.txt not found: {images_txt}")
    if not cameras_txt.exists():
        raise MissingInputError(f"COLMAP cameras.txt not found beside {images_txt}")
    cameras = read_colmap_cameras_text(cameras_txt)
    rows = _Rows(bad_rows)
    # images.txt alternates a pose line and a (possibly empty) 2D-points line; empty lines
    # are dropped, so recognise pose lines by their 10 fields ending in a name. Streamed:
    # with its 2D points the file of a city can be larger than memory.
    for number, line in _data_lines(images_txt):
        parts = line.split()
        if len(parts) != 10:
            continue  # a POINTS2D line
        with rows.row(parts[9]):
            rows.views.append(
                _colmap_line(parts, images_txt, number, cameras, image_dir, len(rows.views))
            )
    crs = _crs_comment(images_txt)
    return rows.pose_set(crs, images_txt, f"{images_txt}: no image poses found")


def _colmap_pose(q_t: list[float], where: str, name: str) -> Pose:
    """The pose of COLMAP's (QW, QX, QY, QZ, TX, TY, TZ); InputError naming ``where``."""
    if not all(math.isfinite(v) for v in q_t):
        raise InputError(f"{where}: field 'QW..TZ' of {name!r} is not finite: {q_t}")
    norm = math.hypot(*q_t[:4])  # scaled: no overflow (and no warning) for |q| near 1e308
    if not 1e-6 < norm < 1e150:
        raise InputError(f"{where}: field 'QW..QZ' of {name!r} is not a rotation (|q| = {norm})")
    return _pose(where, quaternion_to_rotation(np.array(q_t[:4])), np.array(q_t[4:]))


def _colmap_line(
    parts: list[str],
    images_txt: Path,
    number: int,
    cameras: dict[int, Intrinsics],
    image_dir: str | Path | None,
    order: int,
) -> View:
    """One image line of ``images.txt`` as a View; InputError naming the file, line, field."""
    cameras_txt = images_txt.with_name("cameras.txt")
    fields = ("QW", "QX", "QY", "QZ", "TX", "TY", "TZ")
    q_t = [_finite(v, images_txt, number, f) for v, f in zip(parts[1:8], fields, strict=True)]
    camera_id = _whole(parts[8], images_txt, number, "CAMERA_ID")
    if camera_id not in cameras:
        raise InputError(
            f"{images_txt}:{number}: field 'CAMERA_ID' = {camera_id} is not in {cameras_txt}"
        )
    name = _checked_name(parts[9], images_txt, number, "NAME")
    pose = _colmap_pose(q_t, f"{images_txt}:{number}", name)
    image = Path(image_dir) / name if image_dir is not None else None
    return View(name, cameras[camera_id], pose, image, float(order))


def _colmap_camera_params(intr: Intrinsics) -> tuple[str, list[float]]:
    cx, cy = intr.cx + 0.5, intr.cy + 0.5
    if not intr.has_distortion:
        return "PINHOLE", [intr.fx, intr.fy, cx, cy]
    k1, k2, p1, p2, k3 = intr.dist
    if k3 == 0.0:
        return "OPENCV", [intr.fx, intr.fy, cx, cy, k1, k2, p1, p2]
    return "FULL_OPENCV", [intr.fx, intr.fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]


def _camera_ids(views: Iterable[View]) -> dict[Intrinsics, int]:
    ids: dict[Intrinsics, int] = {}
    for v in views:
        ids.setdefault(v.intrinsics, len(ids) + 1)
    return ids


def write_colmap_cameras_text(path: str | Path, camera_ids: dict[Intrinsics, int]) -> Path:
    """Write a COLMAP ``cameras.txt`` with the cameras ``{intrinsics: id}``."""
    path = Path(path)
    lines = []
    for intr, cid in camera_ids.items():
        model, params = _colmap_camera_params(intr)
        lines.append(
            f"{cid} {model} {intr.width} {intr.height} "
            + " ".join(f"{p:.17g}" for p in params)
            + "\n"
        )
    path.write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "".join(lines)
    )
    return path


def write_colmap_text(folder: str | Path, views: Iterable[View], crs: str | None = None) -> Path:
    """Write ``cameras.txt``, ``images.txt`` and an empty ``points3D.txt`` into ``folder``.

    One camera per distinct intrinsics. Values are written with 17 significant digits, so
    georeferenced coordinates survive the round trip exactly. Returns the images.txt path.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    views = list(views)
    camera_ids = _camera_ids(views)
    image_lines = []
    for image_id, view in enumerate(views, start=1):
        q = rotation_to_quaternion(view.pose.R)
        values = " ".join(f"{x:.17g}" for x in (*q, *view.pose.t))
        image_lines.append(f"{image_id} {values} {camera_ids[view.intrinsics]} {view.name}\n\n")
    write_colmap_cameras_text(folder / "cameras.txt", camera_ids)
    header = (
        "# Image list with two lines of data per image:\n"
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
    )
    if crs:
        header += f"# CRS: {crs}\n"
    images_txt = folder / "images.txt"
    images_txt.write_text(header + "".join(image_lines))
    (folder / "points3D.txt").write_text("# 3D point list (empty: poses only)\n")
    return images_txt


# --- COLMAP binary ----------------------------------------------------------------------


class _BinaryReader:
    """Little-endian records read from an open file, which is streamed (a model with its 2D
    points can be larger than memory); CorruptFileError naming the file where it ends early."""

    def __init__(self, fh: IO[bytes], path: Path) -> None:
        self.fh, self.path = fh, path
        self.size = os.fstat(fh.fileno()).st_size

    def unpack(self, fmt: str) -> tuple:
        size = struct.calcsize(fmt)
        offset = self.fh.tell()
        data = self.fh.read(size)
        if len(data) < size:
            raise CorruptFileError(
                f"{self.path}: truncated at byte {offset} (needs {size - len(data)} more bytes)"
            )
        return struct.unpack(fmt, data)

    def skip(self, n: int) -> None:
        offset = self.fh.tell()
        if offset + n > self.size:
            raise CorruptFileError(
                f"{self.path}: truncated at byte {offset} (needs {offset + n - self.size} "
                "more bytes)"
            )
        self.fh.seek(n, os.SEEK_CUR)

    def name(self) -> str:
        """A NUL-terminated UTF-8 name of at most 4096 bytes."""
        offset = self.fh.tell()
        data = self.fh.read(_MAX_NAME_BYTES + 1)
        end = data.find(b"\x00")
        if end < 0:
            raise CorruptFileError(
                f"{self.path}: image name at byte {offset} is not terminated within "
                f"{_MAX_NAME_BYTES} bytes"
            )
        self.fh.seek(offset + end + 1)
        try:
            return data[:end].decode("utf-8")
        except UnicodeDecodeError:
            raise CorruptFileError(
                f"{self.path}: image name at byte {offset} is not UTF-8: {data[:end]!r}"
            ) from None


def _read_cameras_bin(path: Path) -> dict[int, Intrinsics]:
    cameras: dict[int, Intrinsics] = {}
    with _open(path) as fh:
        r = _BinaryReader(fh, path)
        (count,) = r.unpack("<Q")
        for _ in range(count):
            cid, mid, width, height = r.unpack("<iiQQ")
            if mid not in _COLMAP_BY_ID:
                raise InputError(f"{path}: camera {cid}: field 'model_id' = {mid} is not supported")
            model, names = _COLMAP_BY_ID[mid]
            params = r.unpack(f"<{len(names)}d")
            p = dict(zip(names, params, strict=True))
            for k, v in p.items():
                _finite(v, path, f"camera {cid}", k)
            try:
                cameras[cid] = _intrinsics_from_colmap(model, width, height, p)
            except InputError as exc:
                raise InputError(f"{path}: camera {cid}: {exc}") from None
    return cameras


def read_colmap_binary(
    path: str | Path,
    image_dir: str | Path | None = None,
    *,
    bad_rows: list[tuple[str, str]] | None = None,
) -> PoseSet:
    """Read ``cameras.bin`` + ``images.bin`` (``path`` is images.bin or its folder).

    bad_rows : as :func:`read_opk_csv`, for images whose name, camera or pose is refused;
    a file that ends early or cannot be decoded fails whole."""
    path = Path(path)
    images_bin = path / "images.bin" if path.is_dir() else path
    cameras_bin = images_bin.with_name("cameras.bin")
    for p in (images_bin, cameras_bin):
        if not p.exists():
            raise MissingInputError(f"COLMAP binary model file not found: {p}")
    cameras = _read_cameras_bin(cameras_bin)
    rows = _Rows(bad_rows)
    with _open(images_bin) as fh:
        r = _BinaryReader(fh, images_bin)
        (count,) = r.unpack("<Q")
        for k in range(count):
            (_iid, *q_t, cid) = r.unpack("<i7di")
            name = r.name()
            (n_points,) = r.unpack("<Q")
            r.skip(24 * n_points)  # (x, y, point3D id) per 2D point
            where = f"{images_bin}: image {k + 1}"
            with rows.row(name):
                _checked_name(name, images_bin, f"image {k + 1}")
                if cid not in cameras:
                    raise InputError(
                        f"{where}: field 'camera_id' = {cid} of {name!r} is not in {cameras_bin}"
                    )
                pose = _colmap_pose(list(q_t), where, name)
                image = Path(image_dir) / name if image_dir is not None else None
                rows.views.append(View(name, cameras[cid], pose, image, float(len(rows.views))))
    return rows.pose_set(None, images_bin, f"{images_bin}: no image poses found")


def write_colmap_binary(folder: str | Path, views: Iterable[View]) -> Path:
    """Write ``cameras.bin`` and ``images.bin`` (no 2D points). Returns the images.bin path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    views = list(views)
    camera_ids = _camera_ids(views)
    cam = bytearray(struct.pack("<Q", len(camera_ids)))
    for intr, cid in camera_ids.items():
        model, params = _colmap_camera_params(intr)
        cam += struct.pack("<iiQQ", cid, _COLMAP_MODELS[model][0], intr.width, intr.height)
        cam += struct.pack(f"<{len(params)}d", *params)
    (folder / "cameras.bin").write_bytes(bytes(cam))
    img = bytearray(struct.pack("<Q", len(views)))
    for iid, v in enumerate(views, start=1):
        q = rotation_to_quaternion(v.pose.R)
        img += struct.pack("<i7di", iid, *q, *v.pose.t, camera_ids[v.intrinsics])
        img += v.name.encode("utf-8") + b"\x00" + struct.pack("<Q", 0)
    (folder / "images.bin").write_bytes(bytes(img))
    return folder / "images.bin"


# --- omega / phi / kappa CSV -----------------------------------------------------------


def write_opk_csv(path: str | Path, views: Iterable[View], crs: str) -> Path:
    """Write views as an OPK CSV (see module docstring) with ``# crs=…`` on the first line."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        fh.write(f"# crs={crs}\n")
        writer = csv.writer(fh)
        writer.writerow(OPK_FIELDS)
        for v in views:
            omega, phi, kappa = rotation_to_opk(v.pose.R)
            i = v.intrinsics
            row = [
                v.name,
                *(f"{c:.17g}" for c in v.center),
                *(f"{a:.17g}" for a in (omega, phi, kappa)),
                i.width,
                i.height,
                *(f"{x:.17g}" for x in (i.fx, i.fy, i.cx, i.cy, *i.dist)),
                "" if v.time is None else f"{v.time:.17g}",
            ]
            writer.writerow(row)
    return path


def _delimiter(header: str) -> str:
    """The delimiter a CSV header uses: ``,``, ``;`` (spreadsheets in many locales) or tab."""
    return max((",", ";", "\t"), key=header.count)


def read_opk_csv(
    path: str | Path,
    image_dir: str | Path | None = None,
    *,
    bad_rows: list[tuple[str, str]] | None = None,
) -> PoseSet:
    """Read an OPK CSV written by :func:`write_opk_csv` or by hand (see module docstring).

    bad_rows : when given, a malformed row does not stop the reading: ``(name, error)`` is
    appended (name is the row's image name, or ``file:line`` where it has none).
    """
    path = Path(path)
    crs = None
    body: list[tuple[int, str]] = []
    for number, line in _text_lines(path):
        if line.startswith("#"):
            crs = crs or _crs_of(line[1:])
        elif line.strip():
            body.append((number, line))
    if not body:
        raise InputError(f"{path}: no header line (expected {', '.join(OPK_REQUIRED)}, …)")
    # each line with its end again: a quoted field may span lines, and keeps its newline
    reader = csv.reader([line + "\n" for _, line in body], delimiter=_delimiter(body[0][1]))
    try:
        header = [h.strip().lower() for h in next(reader)]
    except csv.Error as exc:
        raise InputError(f"{path}:{body[0][0]}: header is not CSV: {exc}") from None
    missing = [f for f in OPK_REQUIRED if f not in header]
    if missing:
        raise InputError(f"{path}:{body[0][0]}: header lacks field(s) {', '.join(missing)}")
    rows = _Rows(bad_rows)
    while True:
        try:
            values = next(reader)
        except StopIteration:
            break
        except csv.Error as exc:  # e.g. a field over csv's size limit
            number = body[min(reader.line_num, len(body)) - 1][0]
            raise InputError(f"{path}:{number}: not a CSV row: {exc}") from None
        number = body[reader.line_num - 1][0]
        row = dict(zip(header, values, strict=False))
        name = (row.get("name") or "").strip()
        with rows.row(name or f"{path.name}:{number}"):
            rows.views.append(_opk_row(row, name, path, number, image_dir, len(rows.views)))
    return rows.pose_set(crs, path, f"{path}: no image rows")


def _opk_row(
    row: dict[str, str],
    name: str,
    path: Path,
    number: int,
    image_dir: str | Path | None,
    order: int,
) -> View:
    """One OPK CSV row as a View; InputError naming the file, line and field."""
    if not name:
        raise InputError(f"{path}:{number}: field 'name' is empty")
    _checked_name(name, path, number)
    num = {f: _finite(row.get(f, ""), path, number, f) for f in OPK_REQUIRED[1:]}
    dist = tuple(
        _finite(row[f], path, number, f) if (row.get(f) or "").strip() else 0.0 for f in _DISTORTION
    )
    width = _whole(row["width"], path, number, "width")
    height = _whole(row["height"], path, number, "height")
    intr = _intrinsics(
        f"{path}:{number}", width, height, num["fx"], num["fy"], num["cx"], num["cy"], dist
    )
    image = Path(image_dir) / name if image_dir is not None else None
    time = (row.get("time") or "").strip()
    t = _finite(time, path, number, "time") if time else float(order)
    return View(name, intr, _opk_pose(f"{path}:{number}", num), image, t)


# --- Pix4D and Metashape OPK exports ---------------------------------------------------


def read_sidecar_camera(pose_file: Path) -> Intrinsics:
    """The one camera of the COLMAP ``cameras.txt`` beside ``pose_file``: the intrinsics of an
    OPK export that holds only exterior orientations. InputError naming it when it is missing
    or holds more than one camera (which image uses which could not be known)."""
    cameras_txt = pose_file.with_name("cameras.txt")
    if cameras_txt == pose_file or not cameras_txt.is_file():
        raise MissingInputError(
            f"{pose_file}: holds no intrinsics; put a COLMAP cameras.txt with the one camera "
            f"beside it ({cameras_txt})"
        )
    cameras = read_colmap_cameras_text(cameras_txt)
    if len(cameras) != 1:
        raise InputError(
            f"{cameras_txt}: holds {len(cameras)} cameras; the intrinsics of {pose_file.name} "
            "must be one camera"
        )
    return next(iter(cameras.values()))


def _split(line: str) -> list[str]:
    """Fields of a Pix4D/Metashape line: tab-separated when it has tabs (names may hold
    spaces), else whitespace-separated."""
    return [f.strip() for f in line.split("\t")] if "\t" in line else line.split()


def _header_tokens(line: str) -> list[str]:
    return [t.lower() for t in _split(line.lstrip("#").strip())]


def _opk_view(
    name: str,
    values: dict[str, str],
    where: str,
    intr: Intrinsics,
    image_dir: str | Path | None,
    order: int,
    path: Path,
    line: int,
) -> View:
    """A View from centre x, y, z and omega, phi, kappa (degrees) given as text."""
    _checked_name(name, path, line)
    num = {f: _finite(values.get(f, ""), path, line, f) for f in PIX4D_HEADER[1:]}
    pose = _opk_pose(where, num)
    image = Path(image_dir) / name if image_dir is not None else None
    return View(name, intr, pose, image, float(order))


def read_pix4d_opk(
    path: str | Path,
    image_dir: str | Path | None = None,
    *,
    bad_rows: list[tuple[str, str]] | None = None,
    intrinsics: Intrinsics | None = None,
) -> PoseSet:
    """Read Pix4D's ``*_calibrated_external_camera_parameters.txt`` (see module docstring).

    intrinsics : the camera of every image; by default :func:`read_sidecar_camera`.
    """
    path = Path(path)
    lines = (x for x in _text_lines(path) if x[1].strip())
    header = next(lines, None)  # with or without a leading '#'
    if header is None or tuple(_header_tokens(header[1])) != PIX4D_HEADER:
        raise InputError(f"{path}: header is not 'imageName X Y Z Omega Phi Kappa'")
    intr = intrinsics or read_sidecar_camera(path)
    rows = _Rows(bad_rows)
    for number, line in lines:
        if line.lstrip().startswith("#"):
            continue
        parts = _split(line)
        name = parts[0] if parts else ""
        with rows.row(name or f"{path.name}:{number}"):
            if len(parts) != 7:
                raise InputError(f"{path}:{number}: expected 7 fields, got {len(parts)}")
            values = dict(zip(PIX4D_HEADER[1:], parts[1:], strict=True))
            where = f"{path}:{number}"
            n = len(rows.views)
            rows.views.append(_opk_view(name, values, where, intr, image_dir, n, path, number))
    return rows.pose_set(None, path, f"{path}: no image rows")


def write_pix4d_opk(path: str | Path, views: Iterable[View]) -> Path:
    """Write views as Pix4D's external camera parameters (centres and OPK; no intrinsics)."""
    path = Path(path)
    rows = ["imageName X Y Z Omega Phi Kappa\n"]
    for v in views:
        values = (*v.center, *rotation_to_opk(v.pose.R))
        rows.append(v.name + " " + " ".join(f"{x:.12f}" for x in values) + "\n")
    path.write_text("".join(rows))
    return path


_METASHAPE_COLUMNS = {"label": "name", "photoid": "name", "x/east": "x", "y/north": "y"}


def _metashape_column(token: str) -> str:
    """Our name of a Metashape header column (``X/Easting`` → ``x``, ``Z/Altitude`` → ``z``)."""
    token = token.lower()
    if token in _METASHAPE_COLUMNS:
        return _METASHAPE_COLUMNS[token]
    head = token.split("/")[0]
    return head if head in ("x", "y", "z") else token


def _metashape_crs(comment: str) -> str | None:
    """``EPSG:XXXX`` from ``CoordinateSystem: … (EPSG::XXXX)``, else None."""
    m = re.search(r"EPSG::?(\d+)", comment)
    return f"EPSG:{m.group(1)}" if m else None


def read_metashape_opk(
    path: str | Path,
    image_dir: str | Path | None = None,
    *,
    bad_rows: list[tuple[str, str]] | None = None,
    intrinsics: Intrinsics | None = None,
) -> PoseSet:
    """Read Metashape's Omega Phi Kappa camera export (see module docstring).

    intrinsics : the camera of every image; by default :func:`read_sidecar_camera`.
    """
    path = Path(path)
    crs, columns, header_line = None, None, 0
    rows = _Rows(bad_rows)
    intr = intrinsics
    for number, line in _text_lines(path):
        if not line.strip():
            continue
        if columns is None:
            tokens = _header_tokens(line)
            if line.startswith("#") and tokens and tokens[0] in ("label", "photoid"):
                columns, header_line = [_metashape_column(t) for t in tokens], number
                missing = [c for c in ("name", *PIX4D_HEADER[1:]) if c not in columns]
                if missing:
                    raise InputError(f"{path}:{number}: header lacks {', '.join(missing)}")
                intr = intr or read_sidecar_camera(path)
            elif line.startswith("#"):
                crs = crs or _metashape_crs(line)
            else:
                raise InputError(f"{path}:{number}: no '#Label X/East …' header before the rows")
            continue
        if line.startswith("#"):
            continue
        assert intr is not None
        parts = _split(line)
        name = parts[0] if parts else ""
        with rows.row(name or f"{path.name}:{number}"):
            if len(parts) != len(columns):
                raise InputError(
                    f"{path}:{number}: expected {len(columns)} fields as in the header "
                    f"(line {header_line}), got {len(parts)}"
                )
            row = dict(zip(columns, parts, strict=True))
            view = _opk_view(
                name, row, f"{path}:{number}", intr, image_dir, len(rows.views), path, number
            )
            if all(r in row for r in _METASHAPE_R):
                _check_metashape_matrix(row, view, path, number)
            rows.views.append(view)
    if columns is None:
        raise InputError(f"{path}: no '#Label X/East Y/North Z/Altitude Omega Phi Kappa' header")
    return rows.pose_set(crs, path, f"{path}: no image rows")


def _check_metashape_matrix(row: dict[str, str], view: View, path: Path, number: int) -> None:
    """``r11 … r33`` must be the rotation of the row's angles (camera→world or its transpose):
    a row whose matrix and angles disagree cannot be trusted either way."""
    r = np.array([_finite(row[k], path, number, k) for k in _METASHAPE_R]).reshape(3, 3)
    M = (np.diag([1.0, -1.0, -1.0]) @ view.pose.R).T  # photogrammetric camera→world
    if not (np.allclose(r, M, atol=1e-4) or np.allclose(r, M.T, atol=1e-4)):
        # a rotation's entries lie in [-1, 1]: tested first, r rᵀ cannot overflow
        is_rotation = (
            bool((np.abs(r) <= 1.0 + 1e-4).all())
            and np.allclose(r @ r.T, np.eye(3), atol=1e-4)
            and np.linalg.det(r) > 0
        )
        why = "is not the rotation of omega/phi/kappa" if is_rotation else "is not a rotation"
        raise InputError(f"{path}:{number}: field 'r11..r33' {why}: {r.round(6).tolist()}")


def write_metashape_opk(path: str | Path, views: Iterable[View], crs: str | None = None) -> Path:
    """Write views as Metashape's Omega Phi Kappa export (tab-separated, with ``r11 … r33``
    = the photogrammetric camera→world matrix of the angles)."""
    path = Path(path)
    rows = []
    if crs:
        code = crs.split(":")[-1]
        rows.append(f"# CoordinateSystem: {crs} (EPSG::{code})\n")
    rows.append(
        "#Label\tX/East\tY/North\tZ/Altitude\tOmega\tPhi\tKappa\t" + "\t".join(_METASHAPE_R) + "\n"
    )
    for v in views:
        M = (np.diag([1.0, -1.0, -1.0]) @ v.pose.R).T
        values = (*v.center, *rotation_to_opk(v.pose.R), *M.ravel())
        rows.append(v.name + "\t" + "\t".join(f"{x:.12f}" for x in values) + "\n")
    path.write_text("".join(rows))
    return path


# --- OpenSfM ----------------------------------------------------------------------------


def angle_axis_to_rotation(r: np.ndarray) -> np.ndarray:
    """(3,) angle-axis vector (radians, axis × angle) → (3, 3) rotation (Rodrigues)."""
    r = np.asarray(r, dtype=np.float64)
    angle = math.hypot(*r)  # scaled: no overflow warning on a huge (hostile) vector
    if angle < 1e-12:
        return np.eye(3)
    k = r / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def rotation_to_angle_axis(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation → (3,) angle-axis vector (radians), the inverse of
    :func:`angle_axis_to_rotation` (via the unit quaternion, stable at every angle)."""
    w, x, y, z = rotation_to_quaternion(R)
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-15:
        return np.zeros(3)
    angle = 2.0 * math.atan2(s, w)
    return np.array([x, y, z]) / s * angle


def _opensfm_camera(cam: Any, where: str) -> Intrinsics:
    """Intrinsics (pixels, OpenCV) of an OpenSfM camera (focal normalised by max(w, h))."""
    if not isinstance(cam, dict):
        raise InputError(f"{where}: is not an object")
    kind = cam.get("projection_type", "perspective")
    if kind not in ("perspective", "simple_radial", "radial", "brown"):
        raise InputError(
            f"{where}: field 'projection_type' = {kind!r} is not supported "
            "(perspective, simple_radial, radial, brown)"
        )
    width = _json_whole(cam, "width", where)
    height = _json_whole(cam, "height", where)
    size = max(width, height)
    if kind == "brown":
        fx, fy = _json_num(cam, "focal_x", where), _json_num(cam, "focal_y", where)
        cx, cy = _json_num(cam, "c_x", where, 0.0), _json_num(cam, "c_y", where, 0.0)
    else:
        fx = fy = _json_num(cam, "focal", where)
        cx = cy = 0.0
    dist = tuple(_json_num(cam, k, where, 0.0) for k in _DISTORTION)
    # OpenSfM's normalised (0, 0) is the image centre: pixel (w/2 - 0.5, h/2 - 0.5) in OpenCV's
    # convention (top-left pixel centre at 0), and one unit is max(w, h) pixels.
    return _intrinsics(
        where,
        width,
        height,
        fx * size,
        fy * size,
        width / 2.0 - 0.5 + cx * size,
        height / 2.0 - 0.5 + cy * size,
        dist,
    )


def _json_num(obj: dict, key: str, where: str, default: float | None = None) -> float:
    if key not in obj and default is not None:
        return default
    return _json_finite(obj, key, where)


def _json_finite(obj: dict, key: str, where: str) -> float:
    value = obj.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{where}: field {key!r} is not a finite number: {value!r}")
    return float(value)


def _json_whole(obj: dict, key: str, where: str) -> int:
    x = _json_finite(obj, key, where)
    if not x.is_integer():
        raise InputError(f"{where}: field {key!r} is not a whole number: {x!r}")
    return int(x)


def _json_vector(obj: dict, key: str, where: str) -> np.ndarray:
    value = obj.get(key)
    if not isinstance(value, list) or len(value) != 3:
        raise InputError(f"{where}: field {key!r} is not a list of 3 numbers: {value!r}")
    return np.array([_json_finite({key: v}, key, where) for v in value])


def read_opensfm(
    path: str | Path,
    image_dir: str | Path | None = None,
    *,
    bad_rows: list[tuple[str, str]] | None = None,
) -> PoseSet:
    """Read OpenSfM's ``reconstruction.json`` (see module docstring): every shot of every
    reconstruction, in name order (the file is a JSON object per shot, without an order);
    ``time`` is the shot's ``capture_time`` when given, else that order."""
    path = Path(path)
    data = _read_json(path)
    if isinstance(data, dict):
        data = [data]
    if not isinstance(data, list) or not all(isinstance(r, dict) for r in data):
        raise InputError(f"{path}: not an OpenSfM reconstruction (a list of objects)")
    rows = _Rows(bad_rows)
    for k, rec in enumerate(data):
        cameras, shots = rec.get("cameras", {}), rec.get("shots", {})
        if not isinstance(cameras, dict) or not isinstance(shots, dict):
            raise InputError(f"{path}: reconstruction {k}: 'cameras' and 'shots' must be objects")
        for name in sorted(shots):
            with rows.row(name):
                rows.views.append(_opensfm_shot(name, shots[name], cameras, path, k, image_dir))
    views = rows.pose_set(None, path, f"{path}: no shots").views
    order = {id(v): i for i, v in enumerate(views)}
    return PoseSet(
        tuple(v if v.time is not None else _with_time(v, order[id(v)]) for v in views),
        None,
        path,
    )


def _with_time(view: View, t: float) -> View:
    return View(view.name, view.intrinsics, view.pose, view.image, float(t))


def _opensfm_shot(
    name: str,
    shot: Any,
    cameras: dict,
    path: Path,
    k: int,
    image_dir: str | Path | None,
) -> View:
    where = f"{path}: reconstruction {k}: shot {name!r}"
    _checked_name(name, path, f"reconstruction {k}", "shots")
    if not isinstance(shot, dict):
        raise InputError(f"{where}: is not an object")
    cam_id = shot.get("camera")
    if not isinstance(cam_id, str) or cam_id not in cameras:
        raise InputError(f"{where}: field 'camera' = {cam_id!r} is not in 'cameras'")
    intr = _opensfm_camera(cameras[cam_id], f"{path}: reconstruction {k}: camera {cam_id!r}")
    R = angle_axis_to_rotation(_json_vector(shot, "rotation", where))
    pose = _pose(where, R, _json_vector(shot, "translation", where))
    t = _json_finite(shot, "capture_time", where) if "capture_time" in shot else None
    image = Path(image_dir) / name if image_dir is not None else None
    return View(name, intr, pose, image, t)


def _read_json(path: Path) -> Any:
    with _open(path) as fh:
        data = fh.read(MAX_JSON_BYTES + 1)
    if len(data) > MAX_JSON_BYTES:
        raise InputError(f"{path}: larger than {MAX_JSON_BYTES >> 20} MiB; not a pose file")
    if data.startswith(codecs.BOM_UTF8):
        data = data[len(codecs.BOM_UTF8) :]
    try:
        return json.loads(data.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise CorruptFileError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    except RecursionError:
        raise CorruptFileError(f"{path}: JSON nested too deep") from None
    except ValueError as exc:  # JSONDecodeError, and numbers too long to convert
        raise CorruptFileError(f"{path}: not valid JSON: {str(exc).splitlines()[0]}") from None


def write_opensfm(path: str | Path, views: Iterable[View]) -> Path:
    """Write views as an OpenSfM ``reconstruction.json`` (one reconstruction, one camera per
    distinct intrinsics, ``brown`` model; poses world→camera as OpenSfM keeps them)."""
    path = Path(path)
    views = list(views)
    cameras, shots = {}, {}
    for intr, cid in _camera_ids(views).items():
        size = max(intr.width, intr.height)
        k1, k2, p1, p2, k3 = intr.dist
        cameras[f"camera{cid}"] = {
            "projection_type": "brown",
            "width": intr.width,
            "height": intr.height,
            "focal_x": intr.fx / size,
            "focal_y": intr.fy / size,
            "c_x": (intr.cx + 0.5 - intr.width / 2.0) / size,
            "c_y": (intr.cy + 0.5 - intr.height / 2.0) / size,
            **{"k1": k1, "k2": k2, "p1": p1, "p2": p2, "k3": k3},
        }
    ids = _camera_ids(views)
    for v in views:
        shots[v.name] = {
            "rotation": rotation_to_angle_axis(v.pose.R).tolist(),
            "translation": v.pose.t.tolist(),
            "camera": f"camera{ids[v.intrinsics]}",
            **({"capture_time": v.time} if v.time is not None else {}),
        }
    path.write_text(json.dumps([{"cameras": cameras, "shots": shots, "points": {}}], indent=1))
    return path


# --- which reader -----------------------------------------------------------------------


def sniff_format(path: Path) -> str | None:
    """The pose format of the file ``path`` judged by its first lines: ``"opensfm"``,
    ``"opk_csv"``, ``"pix4d"``, ``"metashape"`` or ``"colmap_text"``; None when its start
    says nothing (then the name decides). Never fails on the content: the reader does."""
    with _open(path) as fh:
        head = fh.read(1 << 16)
    if head.startswith(codecs.BOM_UTF8):
        head = head[len(codecs.BOM_UTF8) :]
    text = head.decode("utf-8", errors="replace")
    if text.lstrip()[:1] in ("[", "{"):
        return "opensfm"
    for line in text.splitlines():
        if not line.strip():
            continue
        tokens = _header_tokens(line)
        if tuple(tokens) == PIX4D_HEADER:
            return "pix4d"
        if line.startswith("#") and tokens[:1] in (["label"], ["photoid"]):
            return "metashape"
        if line.startswith("#"):
            if "image_id" in line.lower().replace(" ", "_"):
                return "colmap_text"
            continue
        fields = [f.strip().lower() for f in line.split(_delimiter(line))]
        if "name" in fields and "omega" in fields:
            return "opk_csv"
        return None
    return None


def read_poses(
    path: str | Path,
    image_dir: str | Path | None = None,
    *,
    bad_rows: list[tuple[str, str]] | None = None,
) -> PoseSet:
    """Read any supported pose file (see the module docstring), chosen by its content, then
    by its name: a COLMAP ``images.txt`` / ``images.bin`` (or the folder with either), an OPK
    ``.csv``, a Pix4D or Metashape OPK ``.txt``, or OpenSfM's ``reconstruction.json`` (or the
    folder with it).

    bad_rows : when given, malformed rows are appended to it as ``(name, error)`` and reading
    goes on (a file that cannot be decoded, or ends early, fails whole)."""
    path = Path(path)
    if path.is_dir():
        if (path / "images.txt").exists():
            return read_colmap_text(path, image_dir, bad_rows=bad_rows)
        if (path / "images.bin").exists():
            return read_colmap_binary(path, image_dir, bad_rows=bad_rows)
        if (path / "reconstruction.json").exists():
            return read_opensfm(path / "reconstruction.json", image_dir, bad_rows=bad_rows)
        raise MissingInputError(
            f"{path}: no images.txt, images.bin or reconstruction.json in this folder"
        )
    suffix = path.suffix.lower()
    kind = None if suffix == ".bin" else sniff_format(path)
    if kind == "opensfm" or suffix == ".json":
        return read_opensfm(path, image_dir, bad_rows=bad_rows)
    if kind == "pix4d":
        return read_pix4d_opk(path, image_dir, bad_rows=bad_rows)
    if kind == "metashape":
        return read_metashape_opk(path, image_dir, bad_rows=bad_rows)
    if kind == "opk_csv" or suffix == ".csv":
        return read_opk_csv(path, image_dir, bad_rows=bad_rows)
    if suffix == ".bin":
        return read_colmap_binary(path, image_dir, bad_rows=bad_rows)
    if kind == "colmap_text" or suffix == ".txt":
        return read_colmap_text(path, image_dir, bad_rows=bad_rows)
    raise InputError(
        f"{path}: unknown pose format (expected a COLMAP model, an OPK .csv, a Pix4D or "
        "Metashape OPK .txt, or OpenSfM's reconstruction.json)"
    )
