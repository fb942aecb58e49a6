"""A `View`: one image with its camera and pose, the unit of work of the detector."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from streetcd.camera import Intrinsics, Pose


@dataclass(frozen=True)
class View:
    """One posed image.

    ``pose`` is world→camera in the frame of the pose file (usually the CRS, so its centre
    has georeferenced-size coordinates); call :meth:`local` before projecting local points.
    ``image`` is the image path when known. ``time`` is the acquisition time in seconds
    (GPS or Unix) when the pose file gives one, else the view's order in the file.
    """

    name: str
    intrinsics: Intrinsics
    pose: Pose
    image: Path | None = None
    time: float | None = None

    @property
    def stem(self) -> str:
        return Path(self.name).stem

    @property
    def center(self) -> np.ndarray:
        return self.pose.center

    def local(self, origin: np.ndarray) -> View:
        """The same view in the frame ``X - origin`` (origin (3,) float64, world metres)."""
        return replace(self, pose=self.pose.shifted(origin))


@dataclass(frozen=True)
class PoseSet:
    """Views read from one pose file, with the CRS the file states (``"EPSG:32648"``) or None."""

    views: tuple[View, ...]
    crs: str | None = None
    source: Path | None = None

    def __len__(self) -> int:
        return len(self.views)

    def by_name(self) -> dict[str, View]:
        return {v.name: v for v in self.views}

    def get(self, name: str) -> View:
        """The view called ``name`` (its file name or stem); MissingInputError if absent."""
        from streetcd.errors import MissingInputError

        for v in self.views:
            if v.name == name or v.stem == name:
                return v
        where = f" in {self.source}" if self.source else ""
        raise MissingInputError(f"no pose for view {name!r}{where} ({len(self.views)} views)")
