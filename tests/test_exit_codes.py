"""The night's verdict on the issue's bad nights (streetcd.run.night, streetcd.run.summary):
the one orchestration on a real LocalCluster, on one street of the small city (4 views).

- a 19 KB JPEG whose header claims 30000x30000 fails its view alone (it used to lose its
  batch while the capture date was read), the night exits 3, and it stays counted on the
  next nights ("still failing since") until it is fixed;
- images smaller than the cameras say are the same cameras at another resolution: detected
  with rescaled intrinsics (they all used to fail); a PNG named .jpg is read;
- poses in a local frame stop the night before anything runs (exit code 2).
"""

from __future__ import annotations

import gc
import json
import shutil
import time
from pathlib import Path

import cv2
import pytest
from test_pipeline import bomb_jpeg

from streetcd.config import Config, RunParams
from streetcd.errors import InputError
from streetcd.run.cluster import dask_client
from streetcd.run.night import NightInputs, PlainTracker, run_night
from streetcd.run.summary import EXIT_INPUT, EXIT_OK, EXIT_VIEWS_FAILED, allowed_failures
from streetcd.store.index import ChangeIndex

CONFIG = Config(run=RunParams(batch_size=2))


@pytest.fixture(scope="module")
def cluster():
    with dask_client(workers=2) as client:
        yield client


def one_street(small_city, folder: Path) -> tuple[Path, Path]:
    """The first street of the city (images and poses) copied under ``folder``."""
    images = folder / "images"
    images.mkdir(parents=True)
    for p in small_city.images.glob("S0_*"):
        shutil.copy(p, images / p.name)
    lines = small_city.poses.read_text().splitlines()
    poses = folder / "poses.csv"
    poses.write_text("\n".join(x for x in lines if not x.startswith("S1_")) + "\n")
    return images, poses


def night(client, small_city, images, poses, out: Path, config: Config = CONFIG, **kw):
    inputs = NightInputs(
        str(images), str(poses), str(small_city.store), str(out / "index.sqlite"), str(out)
    )
    return run_night(inputs, config, client=client, **kw)


def latest(out: Path) -> dict:
    return json.loads((out / "runs" / "latest.json").read_text())


def test_max_failed_is_a_count_or_a_fraction():
    assert allowed_failures(0, 24) == 0
    assert allowed_failures(3, 24) == 3
    assert allowed_failures(0.1, 24) == pytest.approx(2.4)
    with pytest.raises(InputError, match="run.max_failed = 1.5 must be a fraction"):
        RunParams(max_failed=1.5)


def test_a_bomb_fails_its_view_alone_and_stays_failing_until_fixed(small_city, cluster, tmp_path):
    images, poses = one_street(small_city, tmp_path)
    names = sorted(p.name for p in images.iterdir())
    bomb = names[1]
    original = (images / bomb).read_bytes()
    bomb_jpeg(images / bomb)

    first = night(cluster, small_city, images, poses, tmp_path)
    assert first.exit_code == EXIT_VIEWS_FAILED
    assert (first.n_views, first.n_done, first.n_failed, first.n_lost) == (4, 3, 1, 0)
    ((view, error),) = first.failures
    assert view.startswith(bomb)
    assert error.startswith(f"InputError: {images.resolve() / bomb}: JPEG header says 30000x30000")
    with ChangeIndex(tmp_path / "index.sqlite", create=False) as idx:
        assert idx.conn.execute("SELECT status FROM runs").fetchone()[0] == "finished"
        failed_at = idx.conn.execute(
            "SELECT processed_at FROM views WHERE status = 'failed'"
        ).fetchone()[0]
    s = latest(tmp_path)
    assert s["exit_code"] == 3 and s["status"] == "views failed"
    assert s["views"] == {
        "planned": 4,
        "already_done": 0,
        "detected": 3,
        "flagged": first.n_flagged,
        "failed": 1,
        "lost": 0,
        "still_failing": 0,
    }
    assert s["failed"] == [{"view": view, "error": error}]
    assert (
        s["summary_path"] == first.summary_path == str(tmp_path / "runs" / f"{first.run_id}.json")
    )
    assert json.loads(Path(first.summary_path).read_text()) == s

    # The next night on the same inputs detects nothing, and says the view still fails.
    second = night(cluster, small_city, images, poses, tmp_path)
    assert (second.n_done, second.n_failed, second.n_skipped) == (0, 0, 4)
    assert second.still_failing == [(view, error, failed_at)]
    assert second.exit_code == EXIT_VIEWS_FAILED
    s = latest(tmp_path)
    assert s["views"]["already_done"] == 3 and s["views"]["still_failing"] == 1
    assert s["still_failing_since"] == failed_at
    assert s["still_failing"] == [{"view": view, "error": error, "since": failed_at}]

    # One failure allowed: the same night is good.
    tolerant = Config(run=RunParams(batch_size=2, max_failed=1))
    assert night(cluster, small_city, images, poses, tmp_path, tolerant).exit_code == EXIT_OK
    assert latest(tmp_path)["allowed_failures"] == 1

    # Fixed (the real image back): detected, and nothing is failing any more.
    (images / bomb).write_bytes(original)
    fixed = night(cluster, small_city, images, poses, tmp_path)
    assert fixed.n_failed == 0 and fixed.still_failing == [] and fixed.exit_code == EXIT_OK
    assert fixed.n_done >= 1


def test_smaller_images_are_detected_with_rescaled_intrinsics(small_city, cluster, tmp_path):
    images, poses = one_street(small_city, tmp_path)
    names = sorted(p.name for p in images.iterdir())
    for name in names:  # the cameras say 480x270
        image = cv2.imread(str(images / name))
        small = cv2.resize(image, (240, 135), interpolation=cv2.INTER_AREA)
        ext = ".png" if name == names[0] else ".jpg"  # and one of them a PNG named .jpg
        ok, buf = cv2.imencode(ext, small)
        (images / name).write_bytes(buf.tobytes())

    summary = night(cluster, small_city, images, poses, tmp_path)
    assert summary.n_failed == 0, summary.failures
    assert summary.n_done == 4 and summary.exit_code == EXIT_OK
    assert any(
        n.startswith("4 image(s) are 240x135 where their camera says 480x270")
        and n.endswith("the same camera at 0.5x, intrinsics rescaled")
        for n in summary.notes
    )
    assert latest(tmp_path)["notes"] == summary.notes
    with ChangeIndex(tmp_path / "index.sqlite", create=False) as idx:
        for row in idx.query():
            assert cv2.imread(row.mask_path, cv2.IMREAD_UNCHANGED).shape == (135, 240)


def test_the_plan_is_out_of_the_cycle_collector_while_the_night_runs_only(
    small_city, cluster, tmp_path
):
    images, poses = one_street(small_city, tmp_path)
    frozen: list[int] = []

    class Watching(PlainTracker):
        def each(self, name, fn, items):  # the segments' detection and publishing
            frozen.append(gc.get_freeze_count())
            return super().each(name, fn, items)

    summary = night(cluster, small_city, images, poses, tmp_path, tracker=Watching())
    assert summary.n_done == 4
    assert frozen and frozen[0] > 1000  # the plan and the imports: not walked by full passes
    assert gc.get_freeze_count() == 0  # the process gets its collector back


def test_poses_in_a_local_frame_stop_the_night_before_it_runs(small_city, cluster, tmp_path):
    images, poses = one_street(small_city, tmp_path)
    lines = [x for x in poses.read_text().splitlines() if not x.startswith("#")]
    rows = [x.split(",") for x in lines[1:]]
    x0, y0 = float(rows[0][1]), float(rows[0][2])
    for r in rows:  # the same trajectory, without its UTM offset and CRS
        r[1], r[2] = f"{float(r[1]) - x0:.3f}", f"{float(r[2]) - y0:.3f}"
    poses.write_text("\n".join([lines[0], *(",".join(r) for r in rows)]) + "\n")
    t0 = time.perf_counter()
    with pytest.raises(InputError, match=f"^{poses}: no camera centre lies within 60 m"):
        night(cluster, small_city, images, poses, tmp_path)
    assert time.perf_counter() - t0 < 5.0
    s = latest(tmp_path)
    assert s["exit_code"] == EXIT_INPUT and s["status"] == "input error" and s["run_id"] is None
    assert s["error"].startswith(f"InputError: {poses}: no camera centre lies within 60 m")
    assert not (tmp_path / "index.sqlite").exists()
