"""The workflow without Prefect, on real components: a small synthetic city, a LocalCluster of
two worker processes, a scheduler and workers started as `dask` processes on loopback."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from streetcd.config import Config, RunParams
from streetcd.io.images import capture_time, read_rgb
from streetcd.io.outputs import tint_red
from streetcd.io.poses import read_poses
from streetcd.run.cluster import WORKER_MALLOC_ENV, dask_client
from streetcd.run.dispatch import Dispatcher
from streetcd.run.night import NightInputs, run_night
from streetcd.run.plan import plan_run
from streetcd.run.progress import progress_listener
from streetcd.run.publish import finish_run, new_summary, open_index, publish_segment, register_plan
from streetcd.run.worker import WorkerRuntime, cloud_key, detect_batch, is_flagged
from streetcd.store.index import ChangeIndex, canonical_dump

PARAMS = Config(run=RunParams(batch_size=2))


def night(client, images, poses, store, index, out, config: Config = Config()):
    """The one orchestration (the CLI's and the flow's), on the tests' own cluster."""
    inputs = NightInputs(str(images), str(poses), str(store), str(index), str(out))
    return run_night(inputs, config, client=client)


def planned(images, poses, store, index, out, config: Config = PARAMS):
    """A plan recorded in the index, for the tests that dispatch and publish it by hand."""
    open_index(str(index))
    plan = plan_run(images, poses, store, index, out, config)
    register_plan(plan)
    return plan


@pytest.fixture(scope="module")
def cluster():
    with dask_client(workers=2) as client:
        yield client


@pytest.fixture(scope="module")
def clean_run(small_city, cluster, tmp_path_factory):
    """One uninterrupted run: (summary, index path, out folder)."""
    out = tmp_path_factory.mktemp("clean")
    index = out / "change_index.sqlite"
    summary = night(
        cluster, small_city.images, small_city.poses, small_city.store, index, out, PARAMS
    )
    return summary, index, out


def test_local_workers_keep_their_memory_between_views(cluster):
    # Dask's default (MALLOC_TRIM_THRESHOLD_=65536) costs ~80 ms of page faults per 2 MP view.
    def malloc_env() -> dict[str, str | None]:
        return {k: os.environ.get(k) for k in WORKER_MALLOC_ENV}

    # the cluster's second worker can still be registering when the first test asks (seen
    # once: one environment came back)
    cluster.wait_for_workers(2, timeout=60)
    seen = cluster.run(malloc_env)
    assert len(seen) == 2
    assert all(env == WORKER_MALLOC_ENV for env in seen.values()), seen


def test_every_view_is_processed_and_only_flagged_ones_listed(small_city, clean_run):
    summary, index, out = clean_run
    n = len(read_poses(small_city.poses).views)
    assert summary.n_views == n and summary.n_done + summary.n_failed == n
    assert summary.n_failed == 0, summary.failures
    assert summary.n_flagged > 0  # the city has changes
    with ChangeIndex(index, create=False) as idx:
        counts = idx.counts()
        rows = idx.query()
        segments = idx.segments()
    assert counts["views"] == n and counts["flagged"] == summary.n_flagged == len(rows)
    assert len(segments) >= 2  # two streets never share a segment
    assert {r.segment_id for r in rows} <= {s.segment_id for s in segments}
    for r in rows:
        mask = cv2.imread(r.mask_path, cv2.IMREAD_UNCHANGED)
        assert mask.shape == (270, 480) and set(np.unique(mask)) <= {0, 255}
        assert (mask > 0).mean() == pytest.approx(r.changed_fraction, abs=1e-9)
        assert Path(r.mask_path).is_relative_to(out)
    assert not list(out.rglob("*.tmp"))


def test_a_rerun_detects_nothing_and_changes_nothing(small_city, cluster, clean_run):
    _, index, out = clean_run
    before = canonical_dump(index)
    again = night(
        cluster, small_city.images, small_city.poses, small_city.store, index, out, PARAMS
    )
    assert again.n_done == 0 and again.n_skipped == again.n_views
    assert canonical_dump(index) == before
    other = Config(run=RunParams(batch_size=2, min_changed_fraction=0.5))
    plan = plan_run(small_city.images, small_city.poses, small_city.store, index, out, other)
    assert plan.n_todo == plan.n_views  # other parameters: everything is due again


def test_a_view_is_flagged_by_its_largest_region_not_by_scattered_specks():
    params = RunParams(min_region_fraction=0.002)
    n = 1920 * 1080  # 0.2 % = 4147.2 px
    specks = [300] * 40  # 12,000 px changed, none of it one object
    assert not is_flagged(sum(specks) / n, specks, n, params)
    assert not is_flagged(4147 / n, [4147], n, params)
    assert is_flagged(4148 / n, [4148], n, params)
    assert is_flagged(0.01, [4148, *specks], n, params)
    assert not is_flagged(0.0, [], n, params)
    # min_region_fraction 0: any changed pixel flags the view (the old rule)
    assert is_flagged(1 / n, [1], n, RunParams(min_region_fraction=0.0))
    # both rules hold: more than min_changed_fraction changed as well
    strict = RunParams(min_changed_fraction=0.01, min_region_fraction=0.002)
    assert not is_flagged(5000 / n, [5000], n, strict)


def test_a_regions_score_weighs_its_size_when_the_rule_says_so():
    n = 1920 * 1080
    weighed = RunParams(min_region_fraction=0.001, region_score_power=1.0)  # 2073.6 px
    # a small, sure region counts; a larger, doubtful one does not
    assert is_flagged(2200 / n, [2200], n, weighed, [0.95])
    assert not is_flagged(3000 / n, [3000], n, weighed, [0.5])
    assert is_flagged(0.01, [3000, 2200], n, weighed, [0.5, 0.95])
    # without scores, or with power 0, pixels alone decide (the rule before)
    assert is_flagged(3000 / n, [3000], n, weighed)
    pixels_alone = RunParams(min_region_fraction=0.001, region_score_power=0.0)
    assert is_flagged(3000 / n, [3000], n, pixels_alone, [0.5])
    with pytest.raises(ValueError, match="2 region scores for 1 regions"):
        is_flagged(3000 / n, [3000], n, weighed, [0.5, 0.9])
    from streetcd.errors import InputError

    with pytest.raises(InputError, match="run.region_score_power"):
        RunParams(region_score_power=-1.0)


def test_read_rgb_refuses_a_cut_jpeg_and_a_wrong_size_naming_the_file(tmp_path):
    from streetcd.errors import CorruptFileError, InputError
    from streetcd.types import Intrinsics, Pose, View

    rgb = np.random.default_rng(3).integers(0, 256, (60, 80, 3), dtype=np.uint8)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    view = View("v.jpg", Intrinsics(80, 60, 70.0, 70.0, 40.0, 30.0), Pose(np.eye(3), np.zeros(3)))
    good, cut = tmp_path / "v.jpg", tmp_path / "cut.jpg"
    good.write_bytes(buf.tobytes())
    cut.write_bytes(buf.tobytes()[: len(buf) * 2 // 3])  # scan data left, no end marker
    image = read_rgb(good, view)
    want = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert np.array_equal(image, want) and not image.flags.writeable
    with pytest.raises(CorruptFileError, match=f"{cut}: truncated JPEG"):
        read_rgb(cut, view)
    other = View("v.jpg", Intrinsics(40, 40, 35.0, 35.0, 20.0, 20.0), view.pose)
    with pytest.raises(InputError, match="image is 80x60 but the pose of 'v.jpg' says 40x40"):
        read_rgb(good, other)
    # the same camera at half the resolution: read, for the caller to rescale the intrinsics
    small = View("v.jpg", Intrinsics(40, 30, 35.0, 35.0, 20.0, 15.0), view.pose)
    assert np.array_equal(read_rgb(good, small), want)


def test_the_overlay_tint_is_half_way_to_red_exactly():
    rng = np.random.default_rng(7)
    image = rng.integers(0, 256, (37, 53, 3), dtype=np.uint8)
    image[0, :3] = [[0, 0, 0], [255, 255, 255], [1, 254, 127]]  # both ends, odd and even
    mask = rng.random((37, 53)) < 0.3
    mask[0, :3] = True
    want = image.copy()  # the overlay's definition: 0.5 v + 0.5 red, truncated
    want[mask] = (0.5 * want[mask] + 0.5 * np.array([255, 0, 0])).astype(np.uint8)
    got = tint_red(image.copy(), mask)
    assert np.array_equal(got, want)
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    tint_red(bgr, mask, channel=2)
    assert np.array_equal(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), want)
    assert np.array_equal(tint_red(image.copy(), np.zeros_like(mask)), image)
    inner = np.zeros_like(mask)  # a mask away from the borders: only its box is tinted
    inner[5:12, 10:31] = mask[5:12, 10:31]
    want = image.copy()
    want[inner] = (0.5 * want[inner] + 0.5 * np.array([255, 0, 0])).astype(np.uint8)
    assert np.array_equal(tint_red(image.copy(), inner), want)


def test_a_worker_without_a_share_takes_views_from_the_back_and_the_index_is_the_same(
    small_city, cluster, clean_run, tmp_path
):
    """All of the run is one worker's share, in single-view batches: the other worker takes
    views from the back of that queue, each with a crop of its own; every view runs once,
    the owner runs its batches in plan order, and the index equals a clean run's."""
    from distributed import get_task_stream

    index = tmp_path / "change_index.sqlite"
    plan = planned(
        small_city.images,
        small_city.poses,
        small_city.store,
        index,
        tmp_path,
        Config(run=RunParams(batch_size=1)),
    )
    owner, other = sorted(cluster.nthreads())
    dispatcher = Dispatcher(cluster, plan, detect_batch, shares={owner: plan.batches}, tail_views=0)
    with get_task_stream(cluster) as stream:
        dispatcher.start()
        summary = new_summary(plan)
        for s in plan.segments_todo:
            summary.merge(publish_segment(plan, dispatcher.finished(s)))
    finish_run(plan, summary)
    order = {b.key: k for k, b in enumerate(plan.batches)}
    ran: dict[str, list[int]] = {owner: [], other: []}
    for t in sorted(stream.data, key=lambda t: t["startstops"][0]["start"]):
        ran[t["worker"]].append(order[t["key"].removesuffix(f"-{plan.run_id}")])
    assert sorted(ran[owner] + ran[other]) == list(range(len(plan.batches)))
    assert ran[owner] == sorted(ran[owner])
    assert ran[other], "the worker without a share took nothing"
    assert summary.n_done == plan.n_views and summary.n_failed == 0
    assert canonical_dump(index) == canonical_dump(clean_run[1])


def test_a_run_started_before_any_worker_is_done_by_the_workers_that_join(
    small_city, clean_run, tmp_path
):
    """No worker when the run starts: the dispatcher hands Dask one batch without a place,
    and the worker that joins runs it and then the whole queue."""
    from distributed import Client, LocalCluster

    index = tmp_path / "change_index.sqlite"
    with (
        LocalCluster(n_workers=0, threads_per_worker=1, dashboard_address=":0") as local,
        Client(local, set_as_default=False) as client,
    ):
        plan = planned(small_city.images, small_city.poses, small_city.store, index, tmp_path)
        dispatcher = Dispatcher(client, plan, detect_batch).start()
        assert dispatcher.running == {None: 1} and not client.nthreads()
        local.scale(1)
        summary = new_summary(plan)
        for s in plan.segments_todo:
            summary.merge(publish_segment(plan, dispatcher.finished(s)))
        finish_run(plan, summary)
    assert summary.n_done == plan.n_views and summary.n_failed == 0
    assert canonical_dump(index) == canonical_dump(clean_run[1])


def test_working_ahead_changes_no_result(small_city, tmp_path):
    """Detecting every batch with the next one prepared ahead (its first images and EXIF in
    the I/O thread) and the next segment's crop started from the segment's first batch on
    (in the crop thread) gives the same records and the same mask and overlay files as
    detecting each batch on its own."""
    from dataclasses import replace

    runs = []
    for ahead in (False, True):
        out = tmp_path / f"ahead-{ahead}"
        plan = plan_run(
            small_city.images, small_city.poses, small_city.store, out / "index.sqlite", out, PARAMS
        )
        assert len(plan.segments_todo) >= 2
        runtime = WorkerRuntime()  # a fresh worker's
        records = []
        for k, b in enumerate(plan.batches):
            nxt = plan.batches[k + 1] if ahead and k + 1 < len(plan.batches) else None
            later = [c for c in plan.batches[k:] if c.segment_id != b.segment_id]
            next_segment = later[0] if ahead and later else None
            records += runtime.detect_batch(b, nxt, next_segment)
            if next_segment is not None:
                entry, mine = runtime.clouds.claim(cloud_key(next_segment))
                # started ahead by this batch (done or not: a short batch can finish before
                # the crop thread does, and nothing waits for it until that segment's turn)
                assert not mine
                entry.result(timeout=120)
        runtime.close()
        timeless = [
            replace(
                r,
                detect_s=None,
                total_s=None,
                cpu_s=None,
                mask_path=r.mask_path and str(Path(r.mask_path).relative_to(out)),
                overlay_path=r.overlay_path and str(Path(r.overlay_path).relative_to(out)),
            )
            for r in records
        ]
        files = {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
        runs.append((timeless, {k: v for k, v in files.items() if k.suffix != ".sqlite"}))
    assert runs[0][0] == runs[1][0]
    assert any(r.flagged for r in runs[0][0]) and runs[0][1] == runs[1][1]


def test_a_mask_that_cannot_be_written_fails_its_view_and_is_not_listed(small_city, tmp_path):
    plan = plan_run(
        small_city.images,
        small_city.poses,
        small_city.store,
        tmp_path / "index.sqlite",
        tmp_path,
        PARAMS,
    )
    (tmp_path / "masks").write_text("a file where the masks folder goes")
    runtime = WorkerRuntime()
    records = [r for b in plan.batches for r in runtime.detect_batch(b)]
    runtime.close()
    failed = [r for r in records if r.status == "failed"]
    assert failed, "the city has changes: some view must have had a mask to write"
    for r in failed:
        assert "cannot write the mask" in (r.error or "")
        assert not r.flagged and r.mask_path is None and r.overlay_path is None
    assert not any(r.flagged for r in records)


def test_bad_inputs_are_recorded_and_the_rest_goes_on(small_city, cluster, tmp_path):
    images = tmp_path / "images"
    shutil.copytree(small_city.images, images)
    names = sorted(p.name for p in images.iterdir())
    corrupt, lifted, unposed, malformed, twice = names[1:6]
    (images / corrupt).write_bytes((images / corrupt).read_bytes()[:200])  # truncated JPEG
    lines, malformed_line = [], 0
    for line in small_city.poses.read_text().splitlines():
        fields = line.split(",")
        if fields[0] == lifted:  # a bad pose: 1 km up in the air, it sees no reference point
            fields[3] = str(float(fields[3]) + 1000.0)
        if fields[0] == malformed:  # a row that cannot be read: it fails this view only
            fields[5], malformed_line = "north-ish", len(lines) + 1
        if fields[0] == twice:  # two poses for one image: which one is meant?
            lines.append(",".join(fields))
        if fields[0] != unposed:
            lines.append(",".join(fields))
    poses = tmp_path / "poses.csv"
    poses.write_text("\n".join(lines) + "\n")
    index = tmp_path / "change_index.sqlite"
    summary = night(cluster, images, poses, small_city.store, index, tmp_path, PARAMS)
    errors = {key.rsplit("#", 1)[0]: e for key, e in summary.failures}  # keys: name#hash
    assert set(errors) == {corrupt, lifted, unposed, malformed, twice}
    assert corrupt in errors[corrupt] and "CorruptFileError" in errors[corrupt]
    assert lifted in errors[lifted] and "EmptyViewError" in errors[lifted]
    assert f"no pose for image {unposed}" in errors[unposed]
    assert errors[malformed] == (
        f"InputError: {poses}:{malformed_line}: field 'phi' is not a number: 'north-ish'"
    )
    assert str(poses) in errors[twice] and f"{twice!r} has 2 poses" in errors[twice]
    assert summary.n_done == len(names) - 5
    with ChangeIndex(index, create=False) as idx:
        assert {key.rsplit("#", 1)[0]: e for key, e in idx.failures()} == errors
        assert idx.conn.execute("SELECT status FROM runs").fetchone()[0] == "finished"
    again = plan_run(images, poses, small_city.store, index, tmp_path, PARAMS)
    assert again.n_todo == 0 and again.n_skipped == len(names)  # failures are not retried

    # Fixing the row makes that view, and only it, due again.
    poses.write_text(poses.read_text().replace("north-ish", "0.0"))
    fixed = plan_run(images, poses, small_city.store, index, tmp_path, PARAMS)
    assert [t.view.name for b in fixed.batches for t in b.tasks] == [malformed]


def test_a_run_on_a_locked_index_fails_fast_and_changes_nothing(small_city, cluster, tmp_path):
    from streetcd.errors import IndexBusyError
    from streetcd.store.locks import run_lock

    index = tmp_path / "change_index.sqlite"
    with run_lock(index, "a run that is still going"):
        t0 = time.perf_counter()
        with pytest.raises(IndexBusyError, match="a run that is still going, process"):
            night(cluster, small_city.images, small_city.poses, small_city.store, index, tmp_path)
        assert time.perf_counter() - t0 < 5
    assert not index.exists()


def test_the_capture_time_comes_from_exif_in_utc(tmp_path):
    from PIL import Image

    image = Image.new("RGB", (8, 8))
    exif = Image.Exif()
    sub = exif.get_ifd(0x8769)
    sub[36867] = "2026:11:21 23:30:00"  # DateTimeOriginal
    sub[36881] = "+02:00"  # OffsetTimeOriginal
    image.save(tmp_path / "zoned.jpg", exif=exif)
    del sub[36881]
    image.save(tmp_path / "utc.jpg", exif=exif)
    image.save(tmp_path / "none.jpg")
    (tmp_path / "junk.jpg").write_bytes(b"not a jpeg")
    assert capture_time(tmp_path / "zoned.jpg") == "2026-11-21T21:30:00Z"
    assert capture_time(tmp_path / "utc.jpg") == "2026-11-21T23:30:00Z"
    assert capture_time(tmp_path / "none.jpg") is None
    assert capture_time(tmp_path / "junk.jpg") is None


def _start(cmd: list[str], log: Path) -> subprocess.Popen:
    with open(log, "wb") as fh:  # the child keeps its own copy of the descriptor
        return subprocess.Popen(
            cmd, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True
        )  # own process group: kill it whole


def _kill(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)


def _wait_for(check, what: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            raise TimeoutError(f"waited {timeout_s} s for {what}")
        time.sleep(0.2)


def test_losing_a_worker_mid_run_gives_the_same_index(small_city, clean_run, tmp_path):
    from distributed import Client

    dask = str(Path(sys.executable).with_name("dask"))  # the `dask` command of this venv
    sched_file = tmp_path / "scheduler.json"
    procs = [
        _start(
            [
                dask,
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--no-dashboard",
                "--scheduler-file",
                str(sched_file),
            ],
            tmp_path / "scheduler.log",
        )
    ]
    try:
        _wait_for(sched_file.exists, "the scheduler file", 60)
        for k in range(2):
            procs.append(
                _start(
                    [
                        dask,
                        "worker",
                        "--scheduler-file",
                        str(sched_file),
                        "--nthreads",
                        "1",
                        "--host",
                        "127.0.0.1",
                        "--no-dashboard",
                        "--name",
                        f"w{k}",
                    ],
                    tmp_path / f"worker{k}.log",
                )
            )
        with Client(scheduler_file=str(sched_file), set_as_default=False) as client:
            client.wait_for_workers(2, timeout=90)
            victim = procs[2]
            killed = []

            def kill_after_first_batch(event, payload):
                if event == "batch" and not killed:
                    _kill(victim)
                    killed.append(time.monotonic())

            index = tmp_path / "change_index.sqlite"
            with progress_listener(kill_after_first_batch):
                summary = night(
                    client,
                    small_city.images,
                    small_city.poses,
                    small_city.store,
                    index,
                    tmp_path,
                    PARAMS,
                )
            assert killed, "the run ended before a batch was published"
            assert len(client.scheduler_info(n_workers=-1)["workers"]) == 1
    finally:
        for p in reversed(procs):
            _kill(p)
    assert summary.n_failed == 0, summary.failures
    assert canonical_dump(index) == canonical_dump(clean_run[1])


def test_new_mls_data_redoes_only_the_views_it_can_reach(small_city, clean_run, tmp_path):
    from streetcd.io.las import write_las
    from streetcd.store.ingest import ingest
    from streetcd.store.tiles import TileStore

    store = tmp_path / "store.zarr"
    shutil.copytree(small_city.store, store)
    index = tmp_path / "change_index.sqlite"
    shutil.copy(clean_run[1], index)  # closed cleanly, so the WAL is checkpointed into it
    views = read_poses(small_city.poses).views
    near = sorted(v.name for v in views if v.name.startswith("S1_"))
    center = np.mean([v.center for v in views if v.name in near], axis=0)
    rng = np.random.default_rng(2)
    new = tmp_path / "archive"
    new.mkdir()
    write_las(
        new / "extra.laz",
        center + rng.uniform(-1, 1, (500, 3)) + [0.0, 6.0, 0.0],
        np.full(500, 67, np.uint8),
        crs=TileStore.open(small_city.store).crs,
    )
    assert ingest(new, store).ok
    plan = plan_run(small_city.images, small_city.poses, store, index, tmp_path, PARAMS)
    todo = sorted(t.view.name for b in plan.batches for t in b.tasks)
    assert todo == near and plan.n_skipped == len(views) - len(near)


def bomb_jpeg(path: Path, side: int = 30000, kb: int = 19) -> Path:
    """A real JPEG of about ``kb`` KB (noise) whose frame header is rewritten to claim
    ``side`` x ``side`` pixels: what the issue's bad night had (OpenCV would allocate
    ``3 * side**2`` bytes to decode it)."""
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)
    for quality in range(95, 5, -5):
        ok, buf = cv2.imencode(".jpg", rgb, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if len(buf) <= kb * 1024:
            break
    data = bytearray(buf.tobytes())
    sof = data.find(b"\xff\xc0")
    data[sof + 5 : sof + 9] = side.to_bytes(2, "big") * 2
    path.write_bytes(bytes(data))
    return path


def test_a_decompression_bomb_is_refused_from_its_header_before_decoding(tmp_path):
    from PIL import Image

    from streetcd.errors import InputError
    from streetcd.io.images import read_header, read_image
    from streetcd.types import Intrinsics, Pose, View

    bomb = bomb_jpeg(tmp_path / "bomb.jpg")
    assert 10_000 < bomb.stat().st_size <= 19 * 1024
    header = read_header(bomb)
    assert (header.format, header.width, header.height) == ("JPEG", 30000, 30000)
    view = View(
        "bomb.jpg", Intrinsics(30000, 30000, 2e4, 2e4, 15e3, 15e3), Pose(np.eye(3), np.zeros(3))
    )
    want = f"{bomb}: JPEG header says 30000x30000 (900.0 MP), over the limit of 100.0 MP"
    with pytest.raises(InputError, match=want.replace("(", r"\(").replace(")", r"\)")):
        read_rgb(bomb, view)
    with pytest.raises(InputError, match="over the limit of 0.0 MP"):
        read_image(bomb, max_pixels=100)
    # PIL refuses it too (DecompressionBombError) while reading the EXIF: no capture time,
    # no exception (it used to escape and lose the view's whole batch)
    with pytest.raises(Image.DecompressionBombError):
        Image.open(bomb)
    assert capture_time(bomb) is None


def test_an_image_is_read_as_what_its_bytes_are_not_by_its_name(tmp_path):
    from streetcd.io.images import read_header, read_image

    rgb = np.random.default_rng(2).integers(0, 256, (30, 40, 3), dtype=np.uint8)
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    named_jpg = tmp_path / "really_a_png.jpg"
    named_jpg.write_bytes(png.tobytes())  # was: "truncated JPEG (no end-of-image marker)"
    assert read_header(named_jpg).format == "PNG"
    assert np.array_equal(read_image(named_jpg), rgb)  # PNG is lossless
    cv2.imwrite(str(tmp_path / "t.tif"), rgb)
    assert (read_header(tmp_path / "t.tif").width, read_header(tmp_path / "t.tif").height) == (
        40,
        30,
    )


def test_a_view_at_another_resolution_gets_its_intrinsics_rescaled():
    from streetcd.io.images import fit_view, fits_camera
    from streetcd.types import Intrinsics, Pose, View

    view = View(
        "v.jpg", Intrinsics(1920, 1080, 1500.0, 1500.0, 959.5, 539.5), Pose(np.eye(3), np.zeros(3))
    )
    half = fit_view(view, 960, 540)
    i = half.intrinsics
    assert (i.width, i.height, i.fx, i.fy, i.cx, i.cy) == (960, 540, 750.0, 750.0, 479.5, 269.5)
    assert half.pose is view.pose and fit_view(view, 1920, 1080) is view
    assert fits_camera(960, 540, 1920, 1080) and fits_camera(1366, 768, 2732, 1536)
    assert not fits_camera(960, 720, 1920, 1080)


def test_objects_built_as_segments_end_are_those_of_a_rebuild_after_the_night(
    small_city, clean_run, tmp_path
):
    """The run builds a segment's change objects as soon as the segments whose views can
    change them are published (ObjectBuilder): the index holds what rebuilding every
    segment after the night gives, and each segment waits for every segment with a done
    view within reach of its box (regions lie within the detector's range of their camera,
    and a segment links the regions within HALO_M of its own)."""
    from streetcd.run.publish import _waiting_for
    from streetcd.store.objects import ground_classes, influence_m, list_objects, rebuild_objects

    _, index, _ = clean_run
    copy = tmp_path / "copy.sqlite"
    with ChangeIndex(index, create=False) as idx:
        idx.conn.execute("VACUUM INTO ?", (str(copy),))
        views = idx.conn.execute("SELECT segment_id, center_x, center_y FROM views").fetchall()
    during = list_objects(index, sort="id")
    with ChangeIndex(copy, create=False) as idx:
        segments = [s.segment_id for s in idx.segments()]
        rebuild_objects(idx, segments, ground_classes(small_city.store))
    assert during and list_objects(copy, sort="id") == during
    plan = planned(
        small_city.images, small_city.poses, small_city.store, tmp_path / "i.sqlite", tmp_path
    )
    reach = influence_m(60.0)
    assert reach == 2 * 60.0 + 20.0
    waiting = _waiting_for(plan, reach + 1.0)
    assert set(waiting) == {s.id for s in plan.segments}
    with ChangeIndex(tmp_path / "i.sqlite", create=False) as idx:
        boxes = {s.segment_id: s for s in idx.segments()}
    for seg, deps in waiting.items():
        (x0, y0, x1, y1), r = boxes[seg].bbox, reach
        near = {
            v["segment_id"]
            for v in views
            if x0 - r <= v["center_x"] <= x1 + r and y0 - r <= v["center_y"] <= y1 + r
        }
        assert seg in deps and near <= deps, seg
