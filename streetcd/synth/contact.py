"""A contact sheet of a generated folder: images beside their change masks, as one PNG."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from streetcd.errors import MissingInputError


def _read(path: Path, flags: int) -> np.ndarray:
    img = cv2.imread(str(path), flags)
    if img is None:
        raise MissingInputError(f"cannot read image {path}")
    return img


def contact_sheet(
    scene_dir: str | Path, out_png: str | Path, n_views: int = 4, tile_width: int = 480
) -> Path:
    """Write a grid of ``n_views`` images (those with the most changed pixels first, then
    unchanged ones), each beside its overlay: red = change, yellow = don't-care."""
    scene_dir = Path(scene_dir)
    manifest = json.loads((scene_dir / "manifest.json").read_text(encoding="utf-8"))
    views = manifest["views"]
    # greedily pick images that show changes not shown yet, then one without changes
    chosen: list[dict] = []
    shown: set[int] = set()
    while len(chosen) < n_views - 1:
        best = max(
            views,
            key=lambda v: (
                len(set(v["changed_instances"]) - shown),
                sum(v["changed_pixels"].values()),
            ),
        )
        if not set(best["changed_instances"]) - shown:
            break
        chosen.append(best)
        shown |= set(best["changed_instances"])
    chosen += [v for v in views if not v["changed_instances"]][: n_views - len(chosen)]
    chosen += [v for v in views if v not in chosen][: n_views - len(chosen)]
    chosen.sort(key=lambda v: v["name"])
    rows = []
    for v in chosen:
        img = _read(scene_dir / v["image"], cv2.IMREAD_COLOR)
        mask = _read(scene_dir / v["mask"], cv2.IMREAD_GRAYSCALE) > 0
        dc = _read(scene_dir / v["dontcare"], cv2.IMREAD_GRAYSCALE) > 0
        over = img.copy()
        over[mask] = (0.45 * over[mask] + 0.55 * np.array([40, 40, 255])).astype(np.uint8)
        over[dc] = (0.5 * over[dc] + 0.5 * np.array([0, 220, 255])).astype(np.uint8)
        scale = tile_width / img.shape[1]
        size = (tile_width, int(round(img.shape[0] * scale)))
        a = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        b = cv2.resize(over, size, interpolation=cv2.INTER_AREA)
        label = f"{v['name']}  changes: {v['changed_instances'] or 'none'}"
        cv2.putText(
            b, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA
        )
        rows.append(np.hstack([a, np.full((size[1], 4, 3), 255, np.uint8), b]))
        rows.append(np.full((4, rows[-1].shape[1], 3), 255, np.uint8))
    sheet = np.vstack(rows[:-1])
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out_png), sheet, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return out_png
