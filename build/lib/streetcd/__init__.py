"""streetcd: what changed on a city's streets, from an older MLS point cloud and newer posed
images (Qin & Gruen 2014), with a nightly Prefect + Dask workflow around the detector.

The public face, loaded on first use so that ``import streetcd.detect`` pays for neither
the tile store (zarr) nor the workflow (Dask):

* :func:`detect_view` — one view against the reference cloud (the detector; pure);
* :class:`Config`, :func:`load_config` — every setting, from ``configs/default.yaml``;
* :class:`TileStore` — the reference cloud as a zarr tile store; :func:`ingest` fills it;
* :class:`ChangeIndex` — the change index a night writes;
* :func:`run_night` — one night, as ``streetcd run`` and the Prefect flow run it;
* :mod:`errors` — every exception streetcd raises.

docs/ARCHITECTURE.md shows the layers and where each job lives.
"""

from __future__ import annotations

import importlib

TYPE_CHECKING = False  # typing's, without importing typing (~18 ms here): mypy reads the name
if TYPE_CHECKING:
    from typing import Any

__version__ = "0.1.0"

# name -> module that defines it
_PUBLIC = {
    "detect_view": "streetcd.detect.chain",
    "DetectionResult": "streetcd.detect.chain",
    "SurfaceCache": "streetcd.detect.cache",
    "Config": "streetcd.config",
    "load_config": "streetcd.config",
    "PointCloud": "streetcd.types",
    "View": "streetcd.types",
    "PoseSet": "streetcd.types",
    "Intrinsics": "streetcd.types",
    "Pose": "streetcd.types",
    "TileStore": "streetcd.store.tiles",
    "ingest": "streetcd.store.ingest",
    "ChangeIndex": "streetcd.store.index",
    "run_night": "streetcd.run.night",
    "NightInputs": "streetcd.run.night",
}

__all__ = [*_PUBLIC, "errors", "__version__"]


def __getattr__(name: str) -> Any:
    if name == "errors":
        return importlib.import_module("streetcd.errors")
    if name in _PUBLIC:
        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'streetcd' has no attribute {name!r}")
