"""Shared fixtures: one Prefect test server per session, one small synthetic city."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def prefect_api_url():
    """A temporary Prefect server for the whole session (it takes ~20 s to start); yields its
    API URL so that subprocesses can use it too. Only tests that run flows ask for it."""
    from prefect.settings import PREFECT_API_URL
    from prefect.testing.utilities import prefect_test_harness

    # No telemetry: the test server would try to reach the internet and log an error.
    mp = pytest.MonkeyPatch()
    mp.setenv("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    try:
        with prefect_test_harness(server_startup_timeout=120):
            yield PREFECT_API_URL.value()
    finally:
        mp.undo()


@dataclass(frozen=True)
class City:
    root: Path
    manifest: Path
    images: Path
    poses: Path
    store: Path


@pytest.fixture(scope="session")
def small_city(tmp_path_factory) -> City:
    """A synthetic city of 2 short streets × 4 small images (the first with changes), its
    cloud ingested into a tile store. About 20 s to make."""
    from streetcd.store.ingest import ingest
    from streetcd.synth import generate_city

    root = tmp_path_factory.mktemp("city")
    manifest = Path(
        generate_city(
            root / "city", seed=5, n_streets=2, images_per_street=4, size=(480, 270), length_m=30.0
        )
    )
    result = ingest(manifest.parent / "cloud", root / "store.zarr")
    assert result.ok, result.failed
    return City(
        root,
        manifest,
        manifest.parent / "images",
        manifest.parent / "poses" / "poses_opk.csv",
        root / "store.zarr",
    )
