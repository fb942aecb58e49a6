"""What a detection leaves on disk: the mask PNG, the overlay JPEG and the JSON summary.

One writer for ``streetcd detect`` and the nightly run, so both draw a change the same way.
Every file is written atomically (a temporary name in the same folder, then a rename), so a
reader never sees half a file, and a run killed mid-write leaves only a stray ``.tmp``.
"""

from __future__ import annotations

import json
import math
import os
import threading
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from streetcd.detect.chain import DetectionResult
from streetcd.errors import InputError
from streetcd.types import View

OUTLINE_BGR = (0, 255, 255)  # yellow: the outline of a change, over the red tint


def atomic_write(path: Path, data: bytes) -> None:
    """Write under a temporary name unique to this process and thread in the same folder,
    then rename over ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
    os.replace(tmp, path)


def encode(ext: str, array: np.ndarray) -> bytes:
    """``array`` encoded by OpenCV as ``ext`` (".png", ".jpg"); InputError if it cannot be."""
    ok, buf = cv2.imencode(ext, array)
    if not ok:
        raise InputError(f"cannot encode a {array.shape} array as {ext}")
    return buf.tobytes()


def mask_png(mask: np.ndarray) -> bytes:
    """(H, W) bool mask as a 0/255 8-bit PNG."""
    return encode(".png", mask.astype(np.uint8) * 255)


def overlay_bgr(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 BGR (for OpenCV's encoder): the RGB ``image`` with the pixels of
    ``mask`` (H, W) bool tinted half-way to red (:func:`tint_red`) and the changed regions
    outlined in :data:`OUTLINE_BGR`, ``max(1, W / 800)`` px wide."""
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)  # a copy, tinted in place
    pick = np.ascontiguousarray(mask, dtype=bool).view(np.uint8)
    x, y, w, h = cv2.boundingRect(pick)
    if not (w and h):
        return bgr
    tint_red(bgr, mask, channel=2)
    contours, _ = cv2.findContours(
        np.ascontiguousarray(pick[y : y + h, x : x + w]),
        cv2.RETR_EXTERNAL,
        cv2.CHAIN_APPROX_SIMPLE,
        offset=(x, y),
    )
    cv2.drawContours(bgr, contours, -1, OUTLINE_BGR, max(1, image.shape[1] // 800))
    return bgr


def tint_red(image: np.ndarray, mask: np.ndarray, channel: int = 0) -> np.ndarray:
    """Blend ``image`` (H, W, 3) uint8 C-contiguous, in place, half-way to pure red where
    ``mask`` (H, W) bool is set: ``⌊(v + 255) / 2⌋`` in the red ``channel`` (0 for RGB, 2 for BGR),
    ``⌊v / 2⌋`` in the others (``0.5 v + 0.5 red``, truncated). A lookup table and a masked
    copy in OpenCV, which lets the detector have the GIL meanwhile."""
    pick = np.ascontiguousarray(mask, dtype=bool).view(np.uint8)
    # Only the box around the mask: changes are a few per cent of a view, and the lookup
    # over the whole image was half of the overlay's cost (docs/BENCHMARKS.md).
    x, y, w, h = cv2.boundingRect(pick)
    if w and h:
        box = image[y : y + h, x : x + w]
        cv2.copyTo(cv2.LUT(box, _half_red_lut(channel)), pick[y : y + h, x : x + w], box)
    return image


@lru_cache(maxsize=3)
def _half_red_lut(channel: int) -> np.ndarray:
    """(256, 1, 3) uint8 table of :func:`tint_red` for red in ``channel``."""
    v = np.arange(256, dtype=np.uint16)
    lut = np.stack([v >> 1] * 3, axis=-1)
    lut[:, channel] = (v + 255) >> 1
    return lut.astype(np.uint8).reshape(256, 1, 3)


def write_mask(path: Path, mask: np.ndarray) -> None:
    """:func:`mask_png` of ``mask``, written atomically to ``path``."""
    atomic_write(path, mask_png(mask))


def write_overlay(path: Path, image: np.ndarray, mask: np.ndarray) -> None:
    """:func:`overlay_bgr` of ``image`` and ``mask`` as a JPEG, written atomically."""
    atomic_write(path, encode(".jpg", overlay_bgr(image, mask)))


def summary(result: DetectionResult, view: View) -> dict[str, Any]:
    """The JSON summary of one view: score, changed fraction, regions in CRS metres, timings."""

    def crs(local: np.ndarray) -> list[float | None]:
        return [
            None if not math.isfinite(v) else round(float(v), 3)
            for v in np.asarray(local) + result.origin
        ]

    return {
        "view": view.name,
        "score": round(result.score, 4),
        "changed_fraction": round(result.changed_fraction, 6),
        "neighbours": list(result.neighbours),
        # False when the cloud has no colours or the check is switched off
        "appearance_check": result.appearance is not None,
        "origin": [float(v) for v in result.origin],
        "regions": [
            {
                "label": r.label,
                "pixels": r.pixels,
                "score": round(r.score, 4),
                "centroid": crs(r.centroid),
                "bbox_min": crs(r.bbox_min),
                "bbox_max": crs(r.bbox_max),
                "dominant_class": r.dominant_class,
            }
            for r in result.regions
        ],
        "timings_s": {k: round(v, 4) for k, v in result.timings.items()},
    }


def write_outputs(
    result: DetectionResult, view: View, image: np.ndarray, out_dir: str | Path
) -> dict[str, Path]:
    """Write ``<stem>.mask.png`` (uint8 0/255), ``<stem>.overlay.jpg`` and ``<stem>.json``
    into ``out_dir``, each atomically. Returns the paths by kind."""
    out = Path(out_dir)
    paths = {
        "mask": out / f"{view.stem}.mask.png",
        "overlay": out / f"{view.stem}.overlay.jpg",
        "summary": out / f"{view.stem}.json",
    }
    write_mask(paths["mask"], result.mask)
    write_overlay(paths["overlay"], image, result.mask)
    atomic_write(paths["summary"], json.dumps(summary(result, view), indent=2).encode())
    return paths
