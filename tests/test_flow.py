"""The Prefect flow end to end on a small synthetic city (LocalCluster, 2 worker processes),
a run killed with SIGKILL and resumed, and the infra files."""

from __future__ import annotations

import json
import os
import resource
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import psutil
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
    # Prefect sees the ingest, the input check, the plan and one task run per segment: never
    # one per image.
    assert len(runs) == 3 + n_segments, names
    assert sum(name.startswith("check-inputs-") for name in names) == 1, names
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
        # the night runs in a child of its own process group (streetcd.run.supervise), which
        # kills its group when the command dies: wait for all of them before counting
        tree = psutil.Process(proc.pid).children(recursive=True) if proc.poll() is None else []
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)  # the CLI; its night follows it
        proc.wait(timeout=30)
        _, alive = psutil.wait_procs(tree, timeout=30)
        assert not alive, f"left running after the kill: {alive}"
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
    # the installed package's flow (no pull step): tests/test_infra.py deploys and runs it
    assert nightly["entrypoint"] == "streetcd_flows.nightly.nightly"
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

    from streetcd.cli.main import query
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
    listed = CliRunner().invoke(query, ["--index", str(index), "--format", "json"])
    objects = json.loads(listed.output)["objects"]
    assert counts["views"] == 6 and counts["failed"] == 0
    # the night's summary line (printed by the supervised child), then the change objects
    assert f"6 detected, {len(rows)} flagged, 0 failed" in out.output
    assert f"change objects: {len(objects)}" in out.output
    assert all(o["id"] in out.output for o in objects)


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
    assert result.exit_code == 2, result.output  # a whole-input error: nothing ran
    assert f"change index {index} is in use by another run (last night's run, process" in (
        result.output
    )
    assert f"{os.getpid()} on" in result.output and "Nothing was changed" in result.output
    assert not index.exists()


@pytest.fixture(scope="module")
def scheduler():
    """A LocalCluster's scheduler address, for the runs below to share (a run starts its
    own cluster otherwise, 10-20 s each on a busy machine)."""
    from streetcd.run.cluster import dask_client

    with dask_client(workers=2) as client:
        yield client.scheduler.address


def _bomb_street(small_city, folder: Path) -> tuple[Path, Path, str]:
    """One street of the city with its second image replaced by a 19 KB JPEG whose header
    claims 30000x30000: (images, poses, the bomb's name)."""
    from test_exit_codes import one_street
    from test_pipeline import bomb_jpeg

    images, poses = one_street(small_city, folder)
    name = sorted(p.name for p in images.iterdir())[1]
    bomb_jpeg(images / name)
    return images, poses, name


def test_the_flow_ends_failed_when_views_fail(small_city, prefect_api_url, scheduler, tmp_path):
    from streetcd_flows.nightly import nightly

    images, poses, bomb = _bomb_street(small_city, tmp_path)
    state = nightly(
        images=str(images),
        poses=str(poses),
        store=str(small_city.store),
        index=str(tmp_path / "index.sqlite"),
        out=str(tmp_path),
        scheduler=scheduler,
        batch_size=2,
        return_state=True,
    )
    assert state.is_failed()
    summary = state.result(raise_on_failure=False)
    assert summary["exit_code"] == 3 and summary["n_failed"] == 1 and summary["n_done"] == 3
    assert summary["failures"][0][0].startswith(bomb)
    assert state.message == f"1 of 4 views failed; summary {summary['summary_path']}"
    assert json.loads(Path(summary["summary_path"]).read_text())["exit_code"] == 3

    # Allowed by max_failed, the same night (now all skipped, one still failing) completes.
    again = nightly(
        images=str(images),
        poses=str(poses),
        store=str(small_city.store),
        index=str(tmp_path / "index.sqlite"),
        out=str(tmp_path),
        scheduler=scheduler,
        max_failed=1,
        return_state=True,
    )
    assert again.is_completed(), again.message
    assert again.result()["exit_code"] == 0 and len(again.result()["still_failing"]) == 1


def test_cli_exit_codes_and_the_still_failing_line(
    small_city, prefect_api_url, scheduler, tmp_path
):
    from click.testing import CliRunner

    from streetcd.cli.run import run

    images, poses, bomb = _bomb_street(small_city, tmp_path)
    index = tmp_path / "index.sqlite"
    args = ["--images", str(images), "--poses", str(poses), "--store", str(small_city.store)]
    args += ["--index", str(index), "--out", str(tmp_path), "--scheduler", scheduler]
    first = CliRunner().invoke(run, args)
    assert first.exit_code == 3, first.output
    assert "4 views, 0 already in the index, 3 detected" in first.output
    assert f"failed {bomb}" in first.output and "JPEG header says 30000x30000" in first.output
    assert f"summary: {tmp_path / 'runs'}" in first.output
    notes = json.loads((tmp_path / "runs" / "latest.json").read_text())["notes"]
    assert f"warning: 1 view(s) will fail: {bomb}; e.g. {images / bomb}: JPEG header" in notes[-1]

    second = CliRunner().invoke(run, args)
    assert second.exit_code == 3, second.output
    assert "4 views, 4 already in the index, 0 detected, 0 flagged, 0 failed" in second.output
    with ChangeIndex(index, create=False) as idx:
        (since,) = idx.conn.execute(
            "SELECT processed_at FROM views WHERE status = 'failed'"
        ).fetchone()
    assert f"1 views still failing since {since}" in second.output
    assert CliRunner().invoke(run, [*args, "--max-failed", "25%"]).exit_code == 0
    bad = CliRunner().invoke(run, [*args, "--max-failed", "1.5"])
    assert bad.exit_code == 2 and "--max-failed" in bad.output


def test_cli_run_on_a_missing_store_fails_in_one_line_before_prefect_starts(tmp_path, small_city):
    # A fresh process, as cron runs it: the one line, code 2, and neither Prefect nor Dask
    # started (they take 6-21 s); CPU time is what the command itself costs.
    store = tmp_path / "missing.zarr"
    cmd = [sys.executable, "-m", "streetcd.cli.main", "run", "--images", str(small_city.images)]
    cmd += ["--poses", str(small_city.poses), "--store", str(store), "--out", str(tmp_path)]
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr == f"Error: tile store not found: {store}\n"
    assert done.stdout == ""
    cpu_s = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    assert cpu_s < 2.0, f"{cpu_s:.2f} s of CPU: more than Python and streetcd's imports"
    summary = json.loads((tmp_path / "runs" / "latest.json").read_text())
    assert (
        summary["exit_code"] == 2
        and summary["error"] == f"MissingInputError: tile store not found: {store}"
    )
