"""One view from files, outside the nightly run: what ``streetcd detect`` does."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from streetcd.config import DetectParams
from streetcd.detect.chain import DetectionResult, detect_view
from streetcd.errors import CorruptFileError, CRSMismatchError, MissingInputError
from streetcd.geometry.neighbours import select_neighbours
from streetcd.io.images import read_image
from streetcd.types import PointCloud, PoseSet, View

_DEFAULTS = DetectParams()


def detect_files(
    view_name: str,
    poses: PoseSet,
    image_dir: str | Path,
    cloud: PointCloud,
    params: DetectParams = _DEFAULTS,
    neighbour_names: Sequence[str] | None = None,
) -> tuple[DetectionResult, View, np.ndarray]:
    """Detect changes in the view ``view_name`` of ``poses`` with images from ``image_dir``.

    Without ``neighbour_names`` the overlapping views are chosen by
    :func:`streetcd.geometry.neighbours.select_neighbours`. Returns the result, the view and its
    image. Errors name the view and the cause (missing pose, unreadable image, no points).
    """
    view = poses.get(view_name)
    if poses.crs and cloud.crs and poses.crs != cloud.crs:
        raise CRSMismatchError(f"poses {poses.source} are in {poses.crs}, the cloud in {cloud.crs}")
    if neighbour_names is None:
        nb_views = select_neighbours(
            view,
            poses.views,
            n=params.correlate.n_neighbours,
            min_parallax_px=params.correlate.min_parallax_px,
        )
    else:
        nb_views = [poses.get(n) for n in neighbour_names]

    def image_of(v: View) -> np.ndarray:
        try:
            return read_image(Path(image_dir) / v.name)
        except (CorruptFileError, MissingInputError) as exc:
            raise type(exc)(f"view {v.name!r}: {exc}") from None

    image = image_of(view)
    neighbours = [(image_of(v), v) for v in nb_views]
    return detect_view(image, view, neighbours, cloud, params), view, image
