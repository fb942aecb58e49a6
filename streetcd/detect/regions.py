"""The changed regions of a mask: 8-connected components, each scored and located in 3D;
before them, the mask cut where an old vehicle's changed pixels meet others' (:func:`cut_apart`).

Note: the depth raster is the *old* surface. For an added object the region's 3D position is
the surface behind it (the wall, the ground), for a removed one the object itself; either
way it locates the change on the street to within the object's depth.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from streetcd.detect.boxes import mask_box
from streetcd.detect.roles import in_roles
from streetcd.geometry.camera import backproject
from streetcd.types import Intrinsics, Pose

BBOX_PERCENTILES = (2.0, 98.0)  # region extent: drop the few edge pixels that hit background
_REGION_SAMPLES = 20_000  # pixels back-projected per region (evenly spread) for its 3D extent


@dataclass(frozen=True)
class Region:
    """One changed region (an 8-connected component of the mask).

    label : id in :attr:`DetectionResult.region_labels` (1, 2, …).
    pixels : number of pixels. score : mean node energy over them, in [0, 1].
    centroid, bbox_min, bbox_max : (3,) float64 metres, local frame (add ``origin`` for the
    CRS); mean and 2nd/98th percentiles of the region's pixels (up to 20 000, evenly
    spread) back-projected through the depth raster; NaN when none has a surface.
    dominant_class : most frequent class code of the old cloud under the region (0 = none).
    foot_class : the most frequent class of the old cloud in a band of image rows just below
    the region (:data:`FOOT_BAND`), column by column: what the changed thing stands on or
    in front of, e.g. the road under the flagged cabin of a car parked since the scan,
    whose body hides the road (0 = none).
    depth_fraction : how far the change stands in front of the old surface, as a fraction of
    the camera depth of the surface behind it (:mod:`streetcd.detect.locate`): the change
    itself is at ``C + depth_fraction · (centroid − C)`` for the camera centre ``C``; NaN
    when not measured or the old surface explains the region as well.
    """

    label: int
    pixels: int
    score: float
    centroid: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    dominant_class: int
    foot_class: int = 0
    depth_fraction: float = float("nan")


FOOT_BAND = 0.03  # the band below a region that foot_class looks at, in image heights


def _foot_class(rows: np.ndarray, cols: np.ndarray, classes: np.ndarray) -> int:
    """Most frequent non-zero class in the FOOT_BAND rows below each column's lowest pixel
    of a region (rows, cols (K,) int); 0 when there is none."""
    h = classes.shape[0]
    ucols, inv = np.unique(cols, return_inverse=True)
    bottom = np.full(ucols.size, -1, dtype=np.int64)
    np.maximum.at(bottom, inv, rows)
    band = max(1, int(round(FOOT_BAND * h)))
    rr = bottom[:, None] + np.arange(1, band + 1)[None, :]
    cc = np.broadcast_to(ucols[:, None], rr.shape)
    inside = rr < h
    under = classes[rr[inside], cc[inside]]
    under = under[under > 0]
    return int(np.bincount(under).argmax()) if under.size else 0


def changed_regions(
    mask: np.ndarray,
    energy: np.ndarray,
    depth: np.ndarray,
    classes: np.ndarray,
    intrinsics: Intrinsics,
    pose: Pose,
) -> tuple[np.ndarray, list[Region]]:
    """8-connected components of ``mask`` (H, W) bool as :class:`Region` s.

    energy (H, W) float32 node energy, depth (H, W) float32 metres, classes (H, W) uint8,
    pose in the local frame. Returns the (H, W) int32 label image (0 = none) and the regions.
    """
    if not mask.any():  # most views: skip labelling and scanning a blank image
        return np.zeros(mask.shape, np.int32), []
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8, ltype=cv2.CV_32S)
    regions: list[Region] = []
    for k, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None:
            continue
        rows, cols = np.nonzero(labels[box] == k)
        rows, cols = rows + box[0].start, cols + box[1].start
        z = depth[rows, cols]
        has = np.isfinite(z)
        if has.any():
            pick = np.flatnonzero(has)[:: max(1, int(has.sum()) // _REGION_SAMPLES)]
            pts = backproject(
                np.column_stack([cols[pick], rows[pick]]).astype(np.float64),
                z[pick].astype(np.float64),
                intrinsics,
                pose,
            )
            centroid = pts.mean(axis=0)
            lo, hi = np.percentile(pts, BBOX_PERCENTILES, axis=0)
            dominant = int(np.bincount(classes[rows[has], cols[has]], minlength=256).argmax())
            foot_class = _foot_class(rows, cols, classes)
        else:
            centroid = lo = hi = np.full(3, np.nan)
            dominant = foot_class = 0
        regions.append(
            Region(
                label=k,
                pixels=int(rows.size),
                score=float(energy[rows, cols].mean()),
                centroid=centroid,
                bbox_min=lo,
                bbox_max=hi,
                dominant_class=dominant,
                foot_class=foot_class,
            )
        )
    return labels, regions


def cut_apart(mask: np.ndarray, classes: np.ndarray, codes: Sequence[int]) -> np.ndarray:
    """``mask`` (H, W) bool cut where its pixels on an old surface of the roles ``codes``
    (``classes`` (H, W) uint8; ``refine.apart_classes``: an old car, a passer-by) meet its
    pixels on another old surface, so that the two are 8-connected regions apart
    (:func:`changed_regions`): the former's pixels that touch the latter's are left out (a
    line one pixel wide). Why: a car gone or a passer-by beside a new pole is then a change
    object of its own, kept out as a transient, not part of the pole's (issue 17). A pixel
    without an old surface (class 0) is on the side of the nearest pixel with one in its
    8-connected component (a gone car's windows, the sky around a new pole). Returns
    ``mask`` itself when there is nothing to cut, else a new mask."""
    if not codes:
        return mask
    apart = mask & in_roles(classes, codes)
    if not apart.any():
        return mask
    box = mask_box(mask) or np.s_[:, :]  # never None: the apart pixels are the mask's
    side = _sides(mask[box], apart[box], classes[box] > 0)
    touching = cv2.dilate((side == 2).view(np.uint8), np.ones((3, 3), np.uint8)).view(bool)
    out = mask.copy()
    out[box] &= ~(touching & (side == 1))
    return out


def _sides(mask: np.ndarray, apart: np.ndarray, surfaced: np.ndarray) -> np.ndarray:
    """(h, w) uint8: 1 where :func:`cut_apart` puts a pixel of ``mask`` on the vehicle's
    side, 2 on the other side, 0 outside the mask. A pixel with an old surface is on its
    own side; one without takes the side of the nearest pixel with one in its 8-connected
    component of ``mask``, or the other side when the component has none."""
    side = np.where(mask & surfaced, np.where(apart, 1, 2), 0).astype(np.uint8)
    bare = mask & (side == 0)
    if bare.any() and side.any():
        _, component = cv2.connectedComponents(
            mask.view(np.uint8), connectivity=8, ltype=cv2.CV_32S
        )
        _, nearest = cv2.distanceTransformWithLabels(
            (side == 0).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5, labelType=cv2.DIST_LABEL_PIXEL
        )
        # DIST_LABEL_PIXEL numbers the pixels with a side 1, 2, ... in scan order
        has = side > 0
        side_of = np.concatenate([[0], side[has]]).astype(np.uint8)
        component_of = np.concatenate([[0], component[has]])
        near = nearest[bare]
        side[bare] = np.where(component_of[near] == component[bare], side_of[near], 2)
    side[bare & (side == 0)] = 2
    return side
