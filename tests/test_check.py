"""``streetcd check`` (:func:`streetcd.run.check.check_inputs`) on the small synthetic city and
on its broken copies: one line naming the file and field for a whole-input error, warnings
for views that will fail alone, notes for what the run adapts to."""

from __future__ import annotations

import re
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import pytest

from streetcd.errors import CRSMismatchError, IndexBusyError, InputError, MissingInputError
from streetcd.run.check import check_inputs
from streetcd.store.index import ChangeIndex
from streetcd.store.locks import run_lock


def edit_poses(src: Path, dst: Path, edit) -> Path:
    """A copy of the OPK CSV ``src`` with ``edit(fields)`` applied to each data row (a list of
    fields; return None to drop the row) and its comment lines kept."""
    lines = []
    for line in src.read_text().splitlines():
        if line.startswith("#") or line.startswith("name,"):
            lines.append(line)
            continue
        fields = edit(line.split(","))
        if fields is not None:
            lines.append(",".join(fields))
    dst.write_text("\n".join(lines) + "\n")
    return dst


def copy_images(small_city, dst: Path) -> Path:
    shutil.copytree(small_city.images, dst)
    return dst


def test_good_inputs_pass_with_their_class_codes_noted(small_city, tmp_path):
    report = check_inputs(
        small_city.images, small_city.poses, small_city.store, tmp_path / "index.sqlite"
    )
    names = {p.name for p in small_city.images.iterdir()}
    assert report.image_names == report.pose_names == names
    assert report.crs == "EPSG:32648" and report.warnings == ()
    (classes,) = report.notes
    assert classes.startswith("class codes near the views") and "building 6" in classes
    assert report.seconds < 2.0


def test_a_missing_store_an_empty_pose_file_and_a_busy_index_are_one_line(small_city, tmp_path):
    with pytest.raises(MissingInputError, match=f"^tile store not found: {tmp_path / 'no.zarr'}$"):
        check_inputs(small_city.images, small_city.poses, tmp_path / "no.zarr")
    empty = tmp_path / "poses.csv"
    empty.write_text("")
    with pytest.raises(InputError, match=f"^{empty}: .*header") as err:
        check_inputs(small_city.images, empty, small_city.store)
    assert "\n" not in str(err.value)
    header_only = edit_poses(small_city.poses, tmp_path / "header.csv", lambda f: None)
    with pytest.raises(InputError, match=f"^{header_only}: no (image rows|usable pose)"):
        check_inputs(small_city.images, header_only, small_city.store)
    index = tmp_path / "index.sqlite"
    with run_lock(index, "last night's run"):
        with pytest.raises(IndexBusyError, match="in use by another run \\(last night's run"):
            check_inputs(small_city.images, small_city.poses, small_city.store, index)
    empty_folder = tmp_path / "empty"
    empty_folder.mkdir()
    with pytest.raises(InputError, match=f"^{empty_folder}: no images"):
        check_inputs(empty_folder, small_city.poses, small_city.store)


def test_poses_in_a_local_frame_are_nowhere_near_the_store(small_city, tmp_path):
    # The first bad night: the same trajectory, without its UTM offset and CRS.
    rows = [
        line.split(",")
        for line in small_city.poses.read_text().splitlines()
        if not line.startswith(("#", "name,"))
    ]
    x0, y0 = float(rows[0][1]), float(rows[0][2])

    def local(fields):
        fields[1] = str(float(fields[1]) - x0)
        fields[2] = str(float(fields[2]) - y0)
        return fields

    poses = edit_poses(small_city.poses, tmp_path / "local.csv", local)
    poses.write_text("\n".join(x for x in poses.read_text().splitlines() if "crs" not in x))
    with pytest.raises(InputError) as err:
        check_inputs(small_city.images, poses, small_city.store)
    message = str(err.value)
    assert message.startswith(f"{poses}: no camera centre lies within 60 m (detect.max_range_m)")
    # both extents, so that the reader sees the offset: the store lies at UTM eastings
    assert re.search(
        r"\(cameras x 0\.\.\d+, y 0\.\.\d+; store x 37\d{4}\.\.37\d{4}, y 14\d{4}", message
    )
    assert "poses in another frame or CRS?" in message and "\n" not in message


def test_crs_of_poses_store_and_index_must_agree(small_city, tmp_path):
    other = tmp_path / "utm49.csv"
    other.write_text(small_city.poses.read_text().replace("EPSG:32648", "EPSG:32649"))
    with pytest.raises(CRSMismatchError, match=f"^crs: poses {other} is in EPSG:32649, tile store"):
        check_inputs(small_city.images, other, small_city.store)
    index = tmp_path / "index.sqlite"
    with ChangeIndex(index) as idx:
        idx.set_crs("EPSG:32650")
    with pytest.raises(
        CRSMismatchError, match=f"in EPSG:32648, change index {index} in EPSG:32650"
    ):
        check_inputs(small_city.images, small_city.poses, small_city.store, index)


def test_images_and_poses_without_their_other_half_are_warned_about(small_city, tmp_path):
    images = copy_images(small_city, tmp_path / "images")
    names = sorted(p.name for p in images.iterdir())
    (images / names[0]).unlink()  # a pose without its image
    poses = edit_poses(
        small_city.poses, tmp_path / "p.csv", lambda f: None if f[0] == names[1] else f
    )
    report = check_inputs(images, poses, small_city.store)
    assert report.warnings == (
        f"1 image(s) have no pose in {poses} and will fail: {names[1]}",
        f"1 pose(s) have no image in {images} and will fail: {names[0]}",
    )
    other = tmp_path / "others"
    other.mkdir()
    shutil.copy(images / names[2], other / "unrelated.jpg")
    with pytest.raises(InputError, match=f"^{poses}: none of its 7 view names is an image in"):
        check_inputs(other, poses, small_city.store)


def test_image_sizes_against_the_cameras(small_city, tmp_path):
    images = copy_images(small_city, tmp_path / "images")
    names = sorted(p.name for p in images.iterdir())
    # the second bad night: every image smaller than the cameras say (480x270)
    for name in names:
        image = cv2.imread(str(images / name))
        cv2.imwrite(str(images / name), cv2.resize(image, (240, 135)))
    report = check_inputs(images, small_city.poses, small_city.store)
    assert report.warnings == ()
    assert report.notes[0] == (
        f"8 image(s) are 240x135 where their camera says 480x270 (e.g. {names[0]}): the same "
        "camera at 0.5x, intrinsics rescaled"
    )
    # another aspect ratio is not the same camera: that view will fail
    image = cv2.imread(str(images / names[3]))
    cv2.imwrite(str(images / names[3]), cv2.resize(image, (240, 240)))
    report = check_inputs(images, small_city.poses, small_city.store)
    (warning,) = report.warnings
    assert warning.startswith(f"1 view(s) will fail: {names[3]}; e.g. {images / names[3]}: ")
    assert "image is 240x240 but its camera says 480x270" in warning
    # when no view can succeed, nothing runs
    for name in names:
        image = cv2.imread(str(images / name))
        cv2.imwrite(str(images / name), cv2.resize(image, (300, 300)))
    with pytest.raises(InputError, match="but its camera says 480x270 .*every one of the 8 images"):
        check_inputs(images, small_city.poses, small_city.store)


def test_a_decompression_bomb_is_warned_about_from_its_header(small_city, tmp_path):
    from test_pipeline import bomb_jpeg

    images = copy_images(small_city, tmp_path / "images")
    name = sorted(p.name for p in images.iterdir())[2]
    bomb_jpeg(images / name)
    t0 = time.perf_counter()
    report = check_inputs(images, small_city.poses, small_city.store)
    assert time.perf_counter() - t0 < 2.0  # the header only: no 2.7 GB decode
    (warning,) = report.warnings
    assert warning.startswith(f"1 view(s) will fail: {name}; e.g. {images / name}: JPEG header")
    assert "30000x30000 (900.0 MP), over the limit of 100.0 MP" in warning


def test_cli_check_exit_codes_and_one_line_errors(small_city, tmp_path):
    from click.testing import CliRunner

    from streetcd.cli.check import check

    args = ["--images", str(small_city.images), "--poses", str(small_city.poses)]
    ok = CliRunner().invoke(check, [*args, "--store", str(small_city.store)])
    assert ok.exit_code == 0, ok.output
    assert "ok: 8 images, 8 poses, CRS EPSG:32648; 0 warning(s)" in ok.output
    bad = CliRunner().invoke(check, [*args, "--store", str(tmp_path / "no.zarr")])
    assert bad.exit_code == 2
    assert bad.output == f"Error: tile store not found: {tmp_path / 'no.zarr'}\n"


def test_streetcd_check_on_a_missing_store_answers_in_under_two_seconds(small_city, tmp_path):
    # The whole command, Python's start and imports included; its CPU time, which the
    # machine's other load does not inflate as it does the wall time.
    cmd = [sys.executable, "-m", "streetcd.cli.main", "check", "--images", str(small_city.images)]
    cmd += ["--poses", str(small_city.poses), "--store", str(tmp_path / "no.zarr")]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert done.returncode == 2, done.stderr
    assert done.stderr == f"Error: tile store not found: {tmp_path / 'no.zarr'}\n"
    assert "Traceback" not in done.stdout + done.stderr
    cpu_s = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    assert cpu_s < 2.0, f"{cpu_s:.2f} s of CPU"


def test_the_run_plans_from_what_the_check_read(small_city, tmp_path, monkeypatch):
    """The pose file is read once a night: the plan takes the check's listing (reading a
    city's pose file twice cost seconds), and reads again when given another folder's."""
    import streetcd.run.plan as plan_module

    reads = []
    real = plan_module.read_poses
    monkeypatch.setattr(
        plan_module, "read_poses", lambda *a, **k: reads.append(a[0]) or real(*a, **k)
    )
    index = tmp_path / "index.sqlite"
    report = check_inputs(small_city.images, small_city.poses, small_city.store, index)
    assert len(reads) == 1 and report.listing is not None
    out = tmp_path / "out"
    shared = plan_module.plan_run(
        small_city.images, small_city.poses, small_city.store, index, out,
        listing=report.listing,
    )  # fmt: skip
    assert len(reads) == 1
    alone = plan_module.plan_run(small_city.images, small_city.poses, small_city.store, index, out)
    assert len(reads) == 2

    def tasks(plan):
        return [
            (t.key, t.input_hash, [n.name for n in t.neighbours])
            for b in plan.batches
            for t in b.tasks
        ]

    assert tasks(shared) == tasks(alone) and len(tasks(alone)) == len(report.image_names)
    other = copy_images(small_city, tmp_path / "images")
    plan_module.plan_run(
        other, small_city.poses, small_city.store, index, out, listing=report.listing
    )
    assert len(reads) == 3  # not this folder's listing: read again


@pytest.fixture(scope="module")
def city_coded(tmp_path_factory):
    """A small street whose cloud has a city's own class codes (210 building, 201 road …),
    ingested, and the class map `streetcd synth` writes beside it."""
    from streetcd.store.ingest import ingest
    from streetcd.synth import generate_street

    root = tmp_path_factory.mktemp("coded")
    manifest = generate_street(
        root / "street", seed=3, n_images=3, size=(320, 180), length_m=30.0, kind="codes"
    )
    street = Path(manifest).parent
    assert ingest(street / "cloud", root / "store.zarr").ok
    return street, root / "store.zarr"


def test_the_class_codes_are_judged_by_the_configs_class_map(city_coded):
    from streetcd.config import load_config

    street, store = city_coded
    poses = street / "poses" / "poses_opk.csv"
    # with the street's class map: no warning, each code named by its role there
    mapped = check_inputs(
        street / "images", poses, store, config=load_config(street / "streetcd.yaml")
    )
    assert mapped.warnings == ()
    (codes,) = mapped.notes
    assert "building 210" in codes and "road 201" in codes
    # with the default (ASPRS) map the same codes are in no role: said once, by the check
    plain = check_inputs(street / "images", poses, store)
    (warning,) = plain.warnings
    assert warning.startswith("only 0.00 % of the reference points have a class the detector uses")
    assert "210:" in warning and "set detect.classes" in warning
    assert "code 210" in plain.notes[0]
    # and the reference-colour check will leave the ground out: no road told from it
    assert plain.notes[1] == (
        "the reference-colour check leaves the ground out (appearance.ground_classes): the "
        "points' roles are inferred from their geometry, which gives the road and the sidewalk"
        " one role"
    )
