"""The real case of ../shared/cases through the whole nightly pipeline: its LAZ ingested into
a tile store, its 18 photographs and COLMAP poses through the one orchestration on a
LocalCluster, and the change objects scored against the labelled removed objects
(`streetcd evaluate --case DIR --index INDEX`). ~15 s each on 2 cores."""

from __future__ import annotations

from pathlib import Path

import pytest

from streetcd.config import Config
from streetcd.eval.objects import score_case_index
from streetcd.run.cluster import dask_client
from streetcd.run.night import NightInputs, run_night
from streetcd.store.ingest import ingest

CASES = Path(__file__).resolve().parents[2] / "shared" / "cases"


def _night(case: Path, tmp_path: Path):
    """Ingest the case's cloud and run one night on its images; (summary, index)."""
    if not case.is_dir():
        pytest.skip(f"{case} not present (the shared annotated cases)")
    store, out = tmp_path / "store.zarr", tmp_path / "run"
    result = ingest(case / "cloud", store)
    assert result.ok, result.failed
    index = out / "change_index.sqlite"
    inputs = NightInputs(
        str(case / "images"), str(case / "sparse"), str(store), str(index), str(out)
    )
    with dask_client(workers=2) as client:
        summary = run_night(inputs, Config(), client=client)
    return summary, index


def test_the_real_cases_removed_objects_are_reported_as_change_objects(tmp_path):
    summary, index = _night(CASES / "dgp-scene02", tmp_path)
    assert (summary.n_done, summary.n_failed) == (18, 0)
    score = score_case_index(CASES / "dgp-scene02", index).as_dict()
    found = {c["type"] for c in score["changes"] if c["objects"]}
    # 2026-11-30: the pole, the sign and the board, each by one object; the bin kept out
    assert {"pole", "sign", "board"} <= found, score["changes"]
    assert score["object_precision_pct"] == 100.0
    assert score["changes_one_object"] >= 3


def test_the_real_unchanged_twin_reports_nothing(tmp_path):
    summary, index = _night(CASES / "dgp-scene02-unchanged", tmp_path)
    score = score_case_index(CASES / "dgp-scene02-unchanged", index).as_dict()
    assert score["flagged_views"] == 0 and score["objects_reported"] == 0
    assert (summary.n_done, summary.n_failed, summary.n_flagged) == (18, 0, 0)
