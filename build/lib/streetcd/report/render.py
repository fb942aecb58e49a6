"""The pictures of the review page, small and fast to load: a view's image with its change
outlined, and the old cloud seen from the same pose.

Images are ``(H, W, 3) uint8`` RGB, rows then columns. The outline is two-tone (a black band
under a yellow line) so it shows on any background, a red car and a yellow wall alike. The old
cloud is splatted: each point of the reference cloud that the view's frustum holds is
projected through the view's pose (:func:`streetcd.detect.zbuffer.project_cloud`, the
detector's own projection), the nearest point per pixel wins, and the small holes between
points are filled from their neighbours. Colours are the cloud's RGB where it has them, else
its intensity, else a depth shade.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from streetcd.detect.zbuffer import project_cloud
from streetcd.errors import CorruptFileError
from streetcd.geometry.camera import project
from streetcd.io.images import DEFAULT_MAX_PIXELS, check_pixels, read_header
from streetcd.types import PointCloud, View

THUMB_WIDTH_PX = 480
OUTLINE_DARK = (0, 0, 0)
OUTLINE_LIGHT = (255, 230, 0)  # RGB yellow, over the dark band
JPEG_QUALITY = 82
EMPTY_GREY = 96  # where no point of the old cloud falls


def read_thumbnail(path: str | Path, width: int = THUMB_WIDTH_PX) -> np.ndarray:
    """The image at ``path`` as ``(h, width, 3)`` uint8 RGB (aspect kept; never enlarged).

    JPEGs are decoded at a reduced scale (libjpeg's DCT scaling: 1/2, 1/4, 1/8) when the image
    is at least twice as wide as asked, which is what makes a thousand thumbnails fast.
    The header is read first: an image stating more than 100 MP is refused (InputError)
    before anything is decoded. MissingInputError / CorruptFileError name the file.
    """
    path = Path(path)
    header = read_header(path)  # no pixel decoded: a decompression bomb is refused here
    check_pixels(path, header, DEFAULT_MAX_PIXELS)
    flag = cv2.IMREAD_COLOR
    for factor, reduced in REDUCED_FLAGS:
        if header.width // factor >= width:
            flag = reduced
            break
    bgr = cv2.imdecode(np.fromfile(path, dtype=np.uint8), flag)
    if bgr is None:
        raise CorruptFileError(f"{path}: cannot decode the image")
    return _fit_width(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), width)


# OpenCV's reduced decodes, largest reduction first (libjpeg scales the DCT: no full decode)
REDUCED_FLAGS = (
    (8, cv2.IMREAD_REDUCED_COLOR_8),
    (4, cv2.IMREAD_REDUCED_COLOR_4),
    (2, cv2.IMREAD_REDUCED_COLOR_2),
)


def _fit_width(image: np.ndarray, width: int) -> np.ndarray:
    h, w = image.shape[:2]
    if w <= width:
        return np.ascontiguousarray(image)
    height = max(1, round(h * width / w))
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def outline(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image`` (h, w, 3) uint8 RGB with the outer contours of ``mask`` (any size, bool or
    0/255; resized to the image) drawn two-tone: 3 px black under 1 px yellow. A copy."""
    h, w = image.shape[:2]
    small = cv2.resize(np.asarray(mask, dtype=np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
    contours, _ = cv2.findContours(
        (small > 0).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE
    )
    out = np.ascontiguousarray(image).copy()
    cv2.drawContours(out, contours, -1, OUTLINE_DARK, 3, lineType=cv2.LINE_8)
    cv2.drawContours(out, contours, -1, OUTLINE_LIGHT, 1, lineType=cv2.LINE_8)
    return out


def read_mask(path: str | Path) -> np.ndarray | None:
    """The mask PNG at ``path`` as (H, W) uint8, or None when it is missing or unreadable."""
    data = np.fromfile(path, dtype=np.uint8) if Path(path).is_file() else None
    if data is None:
        return None
    return cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)


def splat_cloud(
    cloud: PointCloud, view: View, size: tuple[int, int], max_range_m: float = 60.0
) -> np.ndarray:
    """The old ``cloud`` seen from ``view``'s pose, as an ``(h, w, 3)`` uint8 RGB picture of
    ``size`` (w, h) pixels (the view's image scaled; grey where no point falls).

    cloud : local frame (``xyz`` metres, ``X_crs − origin``). view : pose in the CRS.
    Points beyond ``max_range_m`` are left out, as the detector leaves them out.
    """
    w, h = size
    out = np.zeros((h, w, 3), np.uint8)
    if len(cloud) == 0:
        return out + EMPTY_GREY
    # the picture's size exactly (scaled() rounds each side on its own)
    intr = replace(view.intrinsics.scaled(w / view.intrinsics.width), width=w, height=h)
    pose = view.local(cloud.origin).pose
    seen = project_cloud(cloud.xyz, cloud.classification, intr, pose, max_range_m)
    if len(seen.depth) == 0:
        return out + EMPTY_GREY
    cols = np.clip(np.floor(seen.uv[:, 0] + 0.5).astype(np.int64), 0, w - 1)
    rows = np.clip(np.floor(seen.uv[:, 1] + 0.5).astype(np.int64), 0, h - 1)
    pixel = rows * w + cols
    # nearest point per pixel: sort by (pixel, depth), keep each pixel's first
    order = np.lexsort((seen.depth, pixel))
    first = np.ones(order.size, bool)
    first[1:] = pixel[order][1:] != pixel[order][:-1]
    keep = order[first]
    colour = _point_colours(cloud, seen.index[keep], seen.depth[keep], max_range_m)
    flat = out.reshape(-1, 3)
    flat[pixel[keep]] = colour
    filled = np.zeros(h * w, np.uint8)
    filled[pixel[keep]] = 255
    out, filled = _fill_holes(out, filled.reshape(h, w))
    out[filled == 0] = EMPTY_GREY
    return out


def _point_colours(
    cloud: PointCloud, index: np.ndarray, depth: np.ndarray, max_range_m: float
) -> np.ndarray:
    """(N, 3) uint8 RGB of the points ``index``: the cloud's colour, else its intensity (a
    grey stretched to the 2nd–98th percentile), else a shade that darkens with depth."""
    if cloud.rgb is not None:
        rgb = cloud.rgb[index].astype(np.uint32)
        # LAS colours are 16-bit; some writers put 8-bit values in them
        return (rgb >> 8 if rgb.max(initial=0) > 255 else rgb).astype(np.uint8)
    if cloud.intensity is not None:
        v = cloud.intensity[index].astype(np.float64)
        lo, hi = np.percentile(v, [2, 98]) if v.size else (0.0, 1.0)
        grey = np.clip((v - lo) / max(hi - lo, 1e-9), 0, 1) * 220 + 20
    else:
        grey = 235 - 200 * np.clip(depth / max_range_m, 0, 1)
    return np.repeat(grey.astype(np.uint8)[:, None], 3, axis=1)


def _fill_holes(
    image: np.ndarray, filled: np.ndarray, passes: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Grow the splatted pixels into empty neighbours, ``passes`` times 3×3, so a sparse
    cloud reads as surfaces; pixels that had a point keep it. ``image`` is black where
    ``filled`` (uint8, 255: has a colour) is 0, so the growing (a maximum) takes colours
    from points only. Returns the image and the new ``filled``."""
    kernel = np.ones((3, 3), np.uint8)
    for _ in range(passes):
        grown = cv2.dilate(image, kernel)
        grown_mask = cv2.dilate(filled, kernel)
        fill = cv2.bitwise_and(cv2.bitwise_not(filled), grown_mask)
        cv2.copyTo(grown, fill, image)
        filled = grown_mask
    return image, filled


def project_box(bbox: list[float], view: View) -> list[float] | None:
    """Where a change's 3D box ``[xmin, ymin, zmin, xmax, ymax, zmax]`` (CRS metres) lies in
    ``view``'s image: ``[left, top, right, bottom]`` as fractions of the width and height
    (0–1, clipped), or None when a corner is behind the camera or the box misses the image."""
    lo, hi = np.asarray(bbox[:3], float), np.asarray(bbox[3:], float)
    corners = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]] for i in (0, 1)
                        for j in (0, 1) for k in (0, 1)])  # fmt: skip
    local = view.local(lo)
    uv, depth = project(corners - lo, view.intrinsics, local.pose)
    if not np.all(depth > 0) or not np.all(np.isfinite(uv)):
        return None
    w, h = view.intrinsics.width, view.intrinsics.height
    left, top = uv.min(axis=0) / (w, h)
    right, bottom = uv.max(axis=0) / (w, h)
    if right < 0 or bottom < 0 or left > 1 or top > 1:
        return None
    return [round(float(np.clip(v, 0, 1)), 4) for v in (left, top, right, bottom)]


def encode_jpeg(image: np.ndarray) -> bytes:
    """``image`` (h, w, 3) uint8 RGB as JPEG bytes."""
    ok, buf = cv2.imencode(
        ".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]
    )
    if not ok:
        raise CorruptFileError(f"cannot encode a {image.shape} image as JPEG")
    return buf.tobytes()
