"""Pose readers/writers: round trips of georeferenced poses and errors that name the field."""

from pathlib import Path

import numpy as np
import pytest

from streetcd.errors import InputError, MissingInputError
from streetcd.geometry.camera import look_at
from streetcd.io.poses import (
    read_colmap_binary,
    read_colmap_text,
    read_opk_csv,
    read_poses,
    write_colmap_binary,
    write_colmap_text,
    write_opk_csv,
)
from streetcd.types import Intrinsics, View

CRS = "EPSG:32648"


def _views(n=5):
    rng = np.random.default_rng(7)
    intr = [
        Intrinsics(1920, 1080, 1400.0, 1400.0, 959.5, 539.5),
        Intrinsics(4000, 3000, 2900.0, 2901.0, 1999.5, 1499.5, (-0.05, 0.01, 1e-4, -2e-4, 0.0)),
    ]
    views = []
    for i in range(n):
        # 10^5–10^6 m coordinates, as a georeferenced archive has them.
        c = np.array(
            [372_000.0 + 4.5 * i, 143_000.0 + rng.uniform(-1, 1), 1.6 + rng.uniform(0, 0.1)]
        )
        pose = look_at(c, c + [rng.uniform(-5, 5), 15.0, rng.uniform(0, 3)])
        views.append(View(f"IMG_{i:04d}.jpg", intr[i % 2], pose, None, float(i)))
    return views


def _assert_same(a, b, tol_m=1e-3):
    assert [v.name for v in a] == [v.name for v in b]
    for va, vb in zip(a, b, strict=True):
        assert va.intrinsics == vb.intrinsics
        assert np.abs(va.center - vb.center).max() < tol_m
        np.testing.assert_allclose(va.pose.R, vb.pose.R, atol=1e-12)


def test_colmap_text_round_trip_keeps_georeferenced_centres(tmp_path):
    views = _views()
    write_colmap_text(tmp_path, views, crs=CRS)
    ps = read_colmap_text(tmp_path / "images.txt", image_dir=tmp_path / "images")
    _assert_same(views, ps.views, tol_m=1e-6)
    assert ps.crs == CRS
    assert ps.views[0].image == tmp_path / "images" / "IMG_0000.jpg"


def test_colmap_binary_round_trip(tmp_path):
    views = _views()
    write_colmap_binary(tmp_path, views)
    _assert_same(views, read_colmap_binary(tmp_path).views, tol_m=1e-6)


def test_opk_csv_round_trip(tmp_path):
    views = _views()
    path = write_opk_csv(tmp_path / "poses.csv", views, CRS)
    ps = read_poses(path)
    _assert_same(views, ps.views, tol_m=1e-6)
    assert ps.crs == CRS and [v.time for v in ps.views] == [0.0, 1.0, 2.0, 3.0, 4.0]


def test_colmap_principal_point_is_shifted_by_half_a_pixel(tmp_path):
    write_colmap_text(tmp_path, _views(1))
    line = [
        ln for ln in (tmp_path / "cameras.txt").read_text().splitlines() if not ln.startswith("#")
    ][0]
    assert line.split()[1] == "PINHOLE"
    assert float(line.split()[6]) == pytest.approx(960.0)  # COLMAP cx = OpenCV cx + 0.5


def test_read_poses_dispatches_on_folder_and_suffix(tmp_path):
    write_colmap_text(tmp_path / "txt", _views(2))
    write_colmap_binary(tmp_path / "bin", _views(2))
    assert len(read_poses(tmp_path / "txt")) == 2
    assert len(read_poses(tmp_path / "bin")) == 2
    assert len(read_poses(tmp_path / "txt" / "images.txt")) == 2
    with pytest.raises(MissingInputError, match="no images.txt"):
        read_poses(tmp_path)


def test_nan_in_opk_csv_names_file_line_and_field(tmp_path):
    path = write_opk_csv(tmp_path / "poses.csv", _views(3), CRS)
    lines = path.read_text().splitlines()
    fields = lines[3].split(",")
    fields[5] = "nan"  # phi of the second image
    lines[3] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"poses\.csv:4: field 'phi' is not finite"):
        read_opk_csv(path)


def test_truncated_colmap_binary_is_a_clear_error(tmp_path):
    write_colmap_binary(tmp_path, _views(3))
    data = (tmp_path / "images.bin").read_bytes()
    (tmp_path / "images.bin").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="images.bin: truncated"):
        read_colmap_binary(tmp_path)


def test_colmap_unknown_camera_model_is_named(tmp_path):
    write_colmap_text(tmp_path, _views(1))
    cams = tmp_path / "cameras.txt"
    cams.write_text(cams.read_text().replace("PINHOLE", "FISHEYE_X"))
    with pytest.raises(InputError, match="cameras.txt:3: field 'MODEL' = 'FISHEYE_X'"):
        read_colmap_text(tmp_path)


def test_missing_pose_for_a_view_names_the_view(tmp_path):
    write_colmap_text(tmp_path, _views(2))
    with pytest.raises(MissingInputError, match="IMG_0099"):
        read_poses(tmp_path).get("IMG_0099")
    assert read_poses(tmp_path).get("IMG_0001").name == "IMG_0001.jpg"


def test_missing_cameras_txt(tmp_path):
    write_colmap_text(tmp_path, _views(1))
    Path(tmp_path / "cameras.txt").unlink()
    with pytest.raises(MissingInputError, match="cameras.txt"):
        read_poses(tmp_path)
