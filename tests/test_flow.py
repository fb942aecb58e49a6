"""The Prefect flow end to end on a small synthetic city (LocalCluster, 2 worker processes),
a run killed with SIGKILL and resumed, and the infra files."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from streetcd.io.poses import read_poses
from streetcd.store.index import ChangeIndex, canonical_dump

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def flow_run(small_city, prefect_api_url, tmp_path_factory):
    """The nightly flow once, ingesting the city's archive into a new store:
    (state, index path, out folder)."""
    from streetcd_flows.nightly import nightly

    out = tmp_path_factory.mktemp("flow")
    index = out / "change_index.sqlite"
    state = nightly(
        images=str(small_city.images),
        poses=str(small_city.poses),
        store=str(out / "store.zarr"),
        index=str(index),
        out=str(out),
        archive=str(small_city.manifest.parent / "cloud"),
        workers=2,
        batch_size=2,
        return_state=True,
    )
    return state, index, out


def test_the_flow_ingests_detects_and_publishes(small_city, flow_run):
    state, index, _ = flow_run
    assert state.is_completed(), state.message
    summary = state.result()
    n = len(read_poses(small_city.poses).views)
    assert summary["n_views"] == n and summary["n_done"] == n and summary["n_failed"] == 0
    with ChangeIndex(index, create=False) as idx:
        assert idx.counts()["views"] == n
        assert idx.counts()["flagged"] == summary["n_flagged"] > 0
        n_segments = idx.counts()["segments"]
        run = idx.conn.execute("SELECT status, n_done FROM runs").fetchone()
    assert tuple(run) == ("finished", n)
    assert summary["detect_s"] > 0 and summary["wall_s"] > 0
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId
    from prefect.client.schemas.sorting import TaskRunSort

    with get_client(sync_client=True) as client:
        runs = client.read_task_runs(
            flow_run_filter=FlowRunFilter(
                id=FlowRunFilterId(any_=[state.state_details.flow_run_id])
            ),
            sort=TaskRunSort.EXPECTED_START_TIME_ASC,
            limit=200,
        )
    names = sorted(r.name for r in runs)
    per_segment = [r for r in runs if r.name.startswith("publish-segment ")]
    # Prefect sees the ingest, the plan and one task run per segment: never one per image.
    assert len(runs) == 2 + n_segments, names
    assert len(per_segment) == n_segments < n


def test_cli_rerun_on_the_same_inputs_detects_nothing(small_city, flow_run):
    from click.testing import CliRunner

    from streetcd.cli.run import run

    _, index, out = flow_run
    before = canonical_dump(index)
    n = len(read_poses(small_city.poses).views)
    result = CliRunner().invoke(
        run,
        [
            "--images",
            str(small_city.images),
            "--poses",
            str(small_city.poses),
            "--store",
            str(out / "store.zarr"),
            "--archive",
            str(small_city.manifest.parent / "cloud"),
            "--index",
            str(index),
            "--out",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    assert f"{n} views, {n} already in the index, 0 detected" in result.output
    assert canonical_dump(index) == before
    with ChangeIndex(index, create=False) as idx:
        statuses = [r[0] for r in idx.conn.execute("SELECT status FROM runs ORDER BY started_at")]
    assert statuses == ["finished", "finished"]


def _views_published(index: Path) -> int:
    try:
        with sqlite3.connect(f"file:{index}?mode=ro", uri=True, timeout=5) as con:
            return con.execute("SELECT count(*) FROM views").fetchone()[0]
    except sqlite3.OperationalError:  # not created yet
        return 0


def test_a_run_killed_mid_way_resumes_to_the_same_index(
    small_city, flow_run, prefect_api_url, tmp_path
):
    index, out = tmp_path / "change_index.sqlite", tmp_path / "out"
    n = len(read_poses(small_city.poses).views)
    cmd = [
        sys.executable,
        "-m",
        "streetcd.cli.main",
        "run",
        "--images",
        str(small_city.images),
        "--poses",
        str(small_city.poses),
        "--store",
        str(small_city.store),
        "--index",
        str(index),
        "--out",
        str(out),
        "--workers",
        "2",
        "--batch-size",
        "2",
    ]
    env = {**os.environ, "PREFECT_API_URL": prefect_api_url, "PREFECT_HOME": str(tmp_path / "ph")}
    log = tmp_path / "run1.log"
    with open(log, "wb") as fh:
        proc = subprocess.Popen(
            cmd, stdout=fh, stderr=subprocess.STDOUT, env=env, start_new_session=True
        )
    try:
        deadline = time.monotonic() + 240
        while _views_published(index) < 2 and proc.poll() is None:
            assert time.monotonic() < deadline, log.read_text()[-3000:]
            time.sleep(0.1)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)  # the CLI, its Dask workers, everything
        proc.wait(timeout=30)
    published = _views_published(index)
    assert proc.returncode == -signal.SIGKILL, log.read_text()[-3000:]
    assert 2 <= published < n, f"killed after {published} of {n} views"

    again = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    assert f"{published} already in the index" in again.stdout
    assert canonical_dump(index) == canonical_dump(flow_run[1])


def test_infra_files_parse_and_agree():
    compose = yaml.safe_load((ROOT / "infra" / "docker-compose.yml").read_text())
    assert {"prefect-server", "dask-scheduler", "dask-worker", "flow-worker"} <= set(
        compose["services"]
    )
    for name in ("dask-scheduler", "dask-worker", "flow-worker"):
        service = compose["services"][name]
        assert "data:/data" in service["volumes"]
        assert service["environment"]["STREETCD_SCHEDULER"] == "tcp://dask-scheduler:8786"

    deploy = yaml.safe_load((ROOT / "infra" / "prefect.yaml").read_text())
    (nightly,) = deploy["deployments"]
    path, func = nightly["entrypoint"].split(":")
    assert (ROOT / path).exists() and f"def {func}(" in (ROOT / path).read_text()
    from streetcd_flows.nightly import nightly as flow

    params = set(flow.parameters.properties)
    assert set(nightly["parameters"]) <= params
    assert {"images", "poses", "store", "index", "out"} <= set(nightly["parameters"])
    (schedule,) = nightly["schedules"]
    assert len(schedule["cron"].split()) == 5

    import dask

    from streetcd.run.cluster import QUIET_DASK, WORKER_MALLOC_ENV

    dask_yaml = yaml.safe_load((ROOT / "infra" / "dask.yaml").read_text())
    assert dask_yaml["distributed"]["nanny"]["pre-spawn-environ"] == WORKER_MALLOC_ENV
    for key, value in QUIET_DASK.items():
        assert dask.config.get(key, config=dask_yaml) == value, key
    assert "COPY infra/dask.yaml /etc/dask/" in (ROOT / "infra" / "Dockerfile").read_text()

    values = yaml.safe_load((ROOT / "infra" / "helm" / "dask-values.yaml").read_text())
    assert values["worker"]["replicas"] >= 1 and values["worker"]["threads_per_worker"] == 1
    mounts = values["worker"]["mounts"]
    assert mounts["volumeMounts"][0]["name"] == mounts["volumes"][0]["name"]


@pytest.mark.slow  # makes its own city (~20 s) and runs the whole flow
def test_demo_runs_the_whole_workflow_and_lists_what_changed(prefect_api_url, tmp_path):
    from click.testing import CliRunner

    from streetcd.cli.run import demo

    out = CliRunner().invoke(
        demo,
        ["--out", str(tmp_path), "--streets", "2", "--images-per-street", "3", "--size", "320x180"],
    )
    assert out.exit_code == 0, out.output
    index = tmp_path / "change_index.sqlite"
    with ChangeIndex(index, create=False) as idx:
        counts = idx.counts()
        rows = idx.query()
    assert counts["views"] == 6 and counts["failed"] == 0
    assert f"flagged views: {len(rows)}" in out.output
    assert all(r.view in out.output for r in rows)


def test_cli_run_on_an_index_in_use_fails_at_once_naming_the_holder(
    small_city, prefect_api_url, tmp_path
):
    from click.testing import CliRunner

    from streetcd.cli.run import run
    from streetcd.store.locks import run_lock

    index = tmp_path / "change_index.sqlite"
    args = ["--images", str(small_city.images), "--poses", str(small_city.poses)]
    args += ["--store", str(small_city.store), "--index", str(index), "--out", str(tmp_path)]
    with run_lock(index, "last night's run"):
        result = CliRunner().invoke(run, args)
    assert result.exit_code == 1, result.output
    assert f"change index {index} is in use by another run (last night's run, process" in (
        result.output
    )
    assert f"{os.getpid()} on" in result.output and "Nothing was changed" in result.output
    assert not index.exists()
