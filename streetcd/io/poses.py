"""Pose formats: COLMAP text and binary models, and an omega/phi/kappa CSV with a CRS.

Every reader returns a :class:`~streetcd.types.PoseSet` in our conventions (see
``streetcd.geometry.camera``). Readers raise :class:`~streetcd.errors.InputError` naming the file,
the line and the field on malformed input.

COLMAP
    ``cameras.txt`` + ``images.txt`` (or ``.bin``). Poses are world→camera quaternion and
    translation. COLMAP puts the centre of the top-left pixel at (0.5, 0.5); we shift the
    principal point by −0.5 on reading and +0.5 on writing. A comment line
    ``# CRS: EPSG:XXXX`` in ``images.txt`` states the world frame (COLMAP ignores comments).

OPK CSV
    One row per image: ``name,x,y,z,omega,phi,kappa`` (metres in the CRS, degrees, the
    photogrammetric convention of :func:`streetcd.geometry.camera.opk_to_rotation`), then the
    intrinsics ``width,height,fx,fy,cx,cy,k1,k2,p1,p2,k3`` (pixels, OpenCV convention), and an
    optional ``time`` (seconds). The first line is ``# crs=EPSG:XXXX``.
"""

from __future__ import annotations

import csv
import math
import struct
from collections.abc import Iterable
from pathlib import Path

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


def _finite(value: str, path: Path, line: int, field: str) -> float:
    try:
        x = float(value)
    except ValueError:
        raise InputError(f"{path}:{line}: field {field!r} is not a number: {value!r}") from None
    if not math.isfinite(x):
        raise InputError(f"{path}:{line}: field {field!r} is not finite: {value!r}")
    return x


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


# --- COLMAP text ------------------------------------------------------------------------


def _data_lines(path: Path) -> Iterable[tuple[int, str]]:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise MissingInputError(f"pose file not found: {path}") from None
    except UnicodeDecodeError as exc:
        raise CorruptFileError(f"{path}: not a text file ({exc.reason})") from None
    for number, line in enumerate(text.splitlines(), start=1):
        if line.strip() and not line.lstrip().startswith("#"):
            yield number, line


def _crs_comment(path: Path) -> str | None:
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            if not line.startswith("#"):
                break
            body = line[1:].strip()
            if body.lower().startswith("crs:") or body.lower().startswith("crs="):
                return body[4:].strip()
    return None


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
        width = int(_finite(parts[2], path, number, "WIDTH"))
        height = int(_finite(parts[3], path, number, "HEIGHT"))
        try:
            cameras[int(parts[0])] = _intrinsics_from_colmap(model, width, height, values)
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
    views: list[View] = []
    lines = list(_data_lines(images_txt))
    # images.txt alternates a pose line and a (possibly empty) 2D-points line; empty lines
    # were dropped, so recognise pose lines by their 10 fields ending in a name.
    for number, line in lines:
        parts = line.split()
        if len(parts) != 10:
            continue  # a POINTS2D line
        try:
            views.append(_colmap_line(parts, images_txt, number, cameras, image_dir, len(views)))
        except InputError as exc:
            if bad_rows is None:
                raise
            bad_rows.append((parts[9], str(exc)))
    if not views and not bad_rows:
        raise InputError(f"{images_txt}: no image poses found")
    return PoseSet(tuple(views), _crs_comment(images_txt), images_txt)


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
    camera_id = int(_finite(parts[8], images_txt, number, "CAMERA_ID"))
    if camera_id not in cameras:
        raise InputError(
            f"{images_txt}:{number}: field 'CAMERA_ID' = {camera_id} is not in {cameras_txt}"
        )
    name = parts[9]
    if np.linalg.norm(q_t[:4]) < 1e-12:
        raise InputError(f"{images_txt}:{number}: field 'QW..QZ' of {name} is a zero quaternion")
    pose = Pose(quaternion_to_rotation(np.array(q_t[:4])), np.array(q_t[4:]))
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


def write_colmap_text(folder: str | Path, views: Iterable[View], crs: str | None = None) -> Path:
    """Write ``cameras.txt``, ``images.txt`` and an empty ``points3D.txt`` into ``folder``.

    One camera per distinct intrinsics. Values are written with 17 significant digits, so
    georeferenced coordinates survive the round trip exactly. Returns the images.txt path.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    camera_ids: dict[Intrinsics, int] = {}
    image_lines = []
    for image_id, view in enumerate(views, start=1):
        cid = camera_ids.setdefault(view.intrinsics, len(camera_ids) + 1)
        q = rotation_to_quaternion(view.pose.R)
        values = " ".join(f"{x:.17g}" for x in (*q, *view.pose.t))
        image_lines.append(f"{image_id} {values} {cid} {view.name}\n\n")
    cam_lines = []
    for intr, cid in camera_ids.items():
        model, params = _colmap_camera_params(intr)
        cam_lines.append(
            f"{cid} {model} {intr.width} {intr.height} "
            + " ".join(f"{p:.17g}" for p in params)
            + "\n"
        )
    (folder / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "".join(cam_lines)
    )
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


def _unpack(fmt: str, data: bytes, offset: int, path: Path) -> tuple[tuple, int]:
    size = struct.calcsize(fmt)
    if offset + size > len(data):
        raise CorruptFileError(f"{path}: truncated at byte {offset} (needs {size} more bytes)")
    return struct.unpack_from(fmt, data, offset), offset + size


def read_colmap_binary(path: str | Path, image_dir: str | Path | None = None) -> PoseSet:
    """Read ``cameras.bin`` + ``images.bin`` (``path`` is images.bin or its folder)."""
    path = Path(path)
    images_bin = path / "images.bin" if path.is_dir() else path
    cameras_bin = images_bin.with_name("cameras.bin")
    for p in (images_bin, cameras_bin):
        if not p.exists():
            raise MissingInputError(f"COLMAP binary model file not found: {p}")
    data = cameras_bin.read_bytes()
    (count,), off = _unpack("<Q", data, 0, cameras_bin)
    cameras: dict[int, Intrinsics] = {}
    for _ in range(count):
        (cid, mid, width, height), off = _unpack("<iiQQ", data, off, cameras_bin)
        if mid not in _COLMAP_BY_ID:
            raise InputError(f"{cameras_bin}: field 'model_id' = {mid} is not supported")
        model, names = _COLMAP_BY_ID[mid]
        params, off = _unpack(f"<{len(names)}d", data, off, cameras_bin)
        cameras[cid] = _intrinsics_from_colmap(
            model, width, height, dict(zip(names, params, strict=True))
        )
    data = images_bin.read_bytes()
    (count,), off = _unpack("<Q", data, 0, images_bin)
    views: list[View] = []
    for _ in range(count):
        (_iid, *q_t, cid), off = _unpack("<i7di", data, off, images_bin)
        end = data.find(b"\x00", off)
        if end < 0:
            raise CorruptFileError(f"{images_bin}: truncated image name at byte {off}")
        name = data[off:end].decode("utf-8")
        off = end + 1
        (n_points,), off = _unpack("<Q", data, off, images_bin)
        off += 24 * n_points
        if cid not in cameras:
            raise InputError(
                f"{images_bin}: image {name}: field 'camera_id' = {cid} not in {cameras_bin}"
            )
        pose = Pose(quaternion_to_rotation(np.array(q_t[:4])), np.array(q_t[4:]))
        image = Path(image_dir) / name if image_dir is not None else None
        views.append(View(name, cameras[cid], pose, image, float(len(views))))
    return PoseSet(tuple(views), None, images_bin)


def write_colmap_binary(folder: str | Path, views: Iterable[View]) -> Path:
    """Write ``cameras.bin`` and ``images.bin`` (no 2D points). Returns the images.bin path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    views = list(views)
    camera_ids: dict[Intrinsics, int] = {}
    for v in views:
        camera_ids.setdefault(v.intrinsics, len(camera_ids) + 1)
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
    if not path.exists():
        raise MissingInputError(f"pose file not found: {path}")
    crs = None
    with open(path, encoding="utf-8", newline="") as fh:
        lines = fh.read().splitlines()
    body = []
    for line in lines:
        if line.startswith("#"):
            text = line[1:].strip()
            if text.lower().startswith(("crs=", "crs:")):
                crs = text[4:].strip()
        elif line.strip():
            body.append(line)
    reader = csv.DictReader(body)
    missing = [f for f in OPK_FIELDS[:-1] if f not in (reader.fieldnames or [])]
    if missing:
        raise InputError(f"{path}: header lacks field(s) {', '.join(missing)}")
    views: list[View] = []
    for number, row in enumerate(reader, start=2 + sum(1 for x in lines if x.startswith("#"))):
        name = (row.get("name") or "").strip()
        try:
            views.append(_opk_row(row, name, path, number, image_dir, len(views)))
        except InputError as exc:
            if bad_rows is None:
                raise
            bad_rows.append((name or f"{path.name}:{number}", str(exc)))
    if not views and not bad_rows:
        raise InputError(f"{path}: no image rows")
    return PoseSet(tuple(views), crs, path)


def _opk_row(
    row: dict[str, str | None],
    name: str,
    path: Path,
    number: int,
    image_dir: str | Path | None,
    order: int,
) -> View:
    """One OPK CSV row as a View; InputError naming the file, line and field."""
    if not name:
        raise InputError(f"{path}:{number}: field 'name' is empty")
    num = {f: _finite(row[f] or "", path, number, f) for f in OPK_FIELDS[1:-1]}
    time = row.get("time")
    R = opk_to_rotation(num["omega"], num["phi"], num["kappa"])
    try:
        intr = Intrinsics(
            int(num["width"]),
            int(num["height"]),
            num["fx"],
            num["fy"],
            num["cx"],
            num["cy"],
            (num["k1"], num["k2"], num["p1"], num["p2"], num["k3"]),
        )
    except InputError as exc:
        raise InputError(f"{path}:{number}: {exc}") from None
    center = np.array([num["x"], num["y"], num["z"]])
    image = Path(image_dir) / name if image_dir is not None else None
    t = _finite(time, path, number, "time") if time else float(order)
    return View(name, intr, Pose.from_center(R, center), image, t)


def read_poses(
    path: str | Path,
    image_dir: str | Path | None = None,
    *,
    bad_rows: list[tuple[str, str]] | None = None,
) -> PoseSet:
    """Read any supported pose file, chosen by name: a COLMAP ``images.txt`` / ``images.bin``
    (or the folder with either), or an OPK ``.csv``.

    bad_rows : when given, malformed rows of a text format are appended to it as
    ``(name, error)`` and reading goes on (a binary model is read whole or not at all)."""
    path = Path(path)
    if path.is_dir():
        if (path / "images.txt").exists():
            return read_colmap_text(path, image_dir, bad_rows=bad_rows)
        if (path / "images.bin").exists():
            return read_colmap_binary(path, image_dir)
        raise MissingInputError(f"{path}: no images.txt or images.bin in this folder")
    if path.suffix.lower() == ".csv":
        return read_opk_csv(path, image_dir, bad_rows=bad_rows)
    if path.suffix.lower() == ".bin":
        return read_colmap_binary(path, image_dir)
    if path.suffix.lower() == ".txt":
        return read_colmap_text(path, image_dir, bad_rows=bad_rows)
    raise InputError(f"{path}: unknown pose format (expected images.txt, images.bin or .csv)")
