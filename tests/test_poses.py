"""Pose readers/writers: round trips of georeferenced poses and errors that name the field."""

import codecs
from dataclasses import replace
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
    sniff_format,
    write_colmap_binary,
    write_colmap_cameras_text,
    write_colmap_text,
    write_metashape_opk,
    write_opensfm,
    write_opk_csv,
    write_pix4d_opk,
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


# --- BOM, CRLF, optional columns ------------------------------------------------------------


def test_bom_and_crlf_are_read_in_every_text_format(tmp_path):
    views = _views(3)
    files = {
        "csv": write_opk_csv(tmp_path / "csv" / "poses.csv", views, CRS),
        "colmap": write_colmap_text(tmp_path / "colmap", views, crs=CRS),
    }
    (tmp_path / "pix4d").mkdir()
    write_colmap_cameras_text(tmp_path / "pix4d" / "cameras.txt", {views[0].intrinsics: 1})
    files["pix4d"] = write_pix4d_opk(tmp_path / "pix4d" / "p_external.txt", views)
    (tmp_path / "ms").mkdir()
    write_colmap_cameras_text(tmp_path / "ms" / "cameras.txt", {views[0].intrinsics: 1})
    files["metashape"] = write_metashape_opk(tmp_path / "ms" / "opk.txt", views, CRS)
    files["opensfm"] = write_opensfm(tmp_path / "reconstruction.json", views)
    for kind, path in files.items():
        clean = read_poses(path)
        # a spreadsheet's save: a BOM, CRLF line ends, and the cameras.txt beside it too
        for p in {path, path.with_name("cameras.txt")}:
            if p.exists():
                p.write_bytes(codecs.BOM_UTF8 + p.read_bytes().replace(b"\n", b"\r\n"))
        again = read_poses(path)
        assert [v.name for v in again.views] == [v.name for v in clean.views], kind
        assert again.crs == clean.crs, kind
        for a, b in zip(again.views, clean.views, strict=True):
            np.testing.assert_array_equal(a.pose.R, b.pose.R)
            assert a.intrinsics == b.intrinsics


def test_opk_csv_distortion_and_time_columns_are_optional(tmp_path):
    path = tmp_path / "poses.csv"
    path.write_text(
        "# crs=EPSG:32648\n"
        "Name;X;Y;Z;Omega;Phi;Kappa;Width;Height;fx;fy;cx;cy\n"  # a spreadsheet's ; and case
        "IMG_1.jpg;372000.5;143000.25;1.6;90;0;0;1920;1080;1400;1400;959.5;539.5\n"
    )
    (v,) = read_poses(path).views
    assert v.intrinsics.dist == (0.0, 0.0, 0.0, 0.0, 0.0) and v.time == 0.0
    np.testing.assert_allclose(v.center, [372000.5, 143000.25, 1.6])


# --- readers checked against known projections ----------------------------------------------


def _pixel(view, point):
    from streetcd.geometry.camera import project

    uv, depth = project(np.array([point], dtype=float), view.intrinsics, view.pose)
    assert depth[0] > 0, "the point must be in front of the camera"
    return uv[0]


def _one_camera(folder, width=1000, height=800, f=500.0):
    """A COLMAP cameras.txt beside an OPK export: PINHOLE, principal point at the centre."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cameras.txt").write_text(f"1 PINHOLE {width} {height} {f} {f} 500 400\n")
    return 499.5, 399.5  # OpenCV's cx, cy: COLMAP's minus half a pixel


@pytest.mark.parametrize(
    "opk, point, expected",
    [
        # ω = φ = κ = 0 looks straight down, image x east, image up north
        ((0, 0, 0), (101.0, 200.0, 40.0), (50.0, 0.0)),
        ((0, 0, 0), (100.0, 201.0, 40.0), (0.0, -50.0)),
        # κ = 90°: the image x axis turns to the north
        ((0, 0, 90), (100.0, 201.0, 40.0), (50.0, 0.0)),
        # ω = 90°: a street camera looking north, up is up
        ((90, 0, 0), (100.0, 210.0, 51.0), (0.0, -50.0)),
        ((90, 0, 0), (101.0, 210.0, 50.0), (50.0, 0.0)),
    ],
)
def test_pix4d_export_projects_a_known_point_where_expected(tmp_path, opk, point, expected):
    cx, cy = _one_camera(tmp_path)
    path = tmp_path / "proj_calibrated_external_camera_parameters.txt"
    path.write_text(
        "imageName X Y Z Omega Phi Kappa\n"
        f"IMG_0001.JPG 100.000000 200.000000 50.000000 {opk[0]} {opk[1]} {opk[2]}\n"
    )
    (view,) = read_poses(path).views
    np.testing.assert_allclose(_pixel(view, point), (cx + expected[0], cy + expected[1]), atol=1e-6)


def test_metashape_export_is_not_taken_for_colmap_and_projects_as_expected(tmp_path):
    cx, cy = _one_camera(tmp_path)
    path = tmp_path / "cameras_opk.txt"
    # Metashape's layout: the coordinate system, a #Label header, tab-separated rows with
    # the photogrammetric camera→world matrix of the angles (here ω = 90°: Rx(90°)).
    path.write_text(
        "# CoordinateSystem: WGS 84 / UTM zone 48N (EPSG::32648)\n"
        "#Label\tX/East\tY/North\tZ/Altitude\tOmega\tPhi\tKappa\t"
        "r11\tr12\tr13\tr21\tr22\tr23\tr31\tr32\tr33\n"
        "IMG 0001.JPG\t100\t200\t50\t90\t0\t0\t1\t0\t0\t0\t0\t-1\t0\t1\t0\n"
    )
    ps = read_poses(path)
    (view,) = ps.views
    assert ps.crs == "EPSG:32648" and view.name == "IMG 0001.JPG"  # names may hold spaces
    np.testing.assert_allclose(_pixel(view, (100.0, 210.0, 51.0)), (cx, cy - 50.0), atol=1e-6)


def test_metashape_matrix_that_disagrees_with_the_angles_is_refused(tmp_path):
    _one_camera(tmp_path)
    path = tmp_path / "opk.txt"
    path.write_text(
        "#Label\tX/East\tY/North\tZ/Altitude\tOmega\tPhi\tKappa\t"
        "r11\tr12\tr13\tr21\tr22\tr23\tr31\tr32\tr33\n"
        "A.jpg\t100\t200\t50\t90\t0\t0\t2\t0\t0\t0\t0\t-1\t0\t1\t0\n"
    )
    with pytest.raises(InputError, match=r"opk\.txt:2: field 'r11..r33' is not a rotation"):
        read_poses(path)


def test_opensfm_reconstruction_projects_a_known_point_where_expected(tmp_path):
    path = tmp_path / "reconstruction.json"
    # OpenSfM: world→camera angle-axis, OpenCV camera axes, focal / max(w, h), principal
    # point offset / max(w, h) from the image centre.
    path.write_text(
        '[{"cameras": {"v2 cam 640 480 brown 0.5": {"projection_type": "brown", "width": 640,'
        ' "height": 480, "focal_x": 0.5, "focal_y": 0.5, "c_x": 0.01, "c_y": 0.0, "k1": 0.0,'
        ' "k2": 0.0, "p1": 0.0, "p2": 0.0, "k3": 0.0},'
        ' "v2 other 640 480 perspective 0.5": {"projection_type": "perspective",'
        ' "width": 640, "height": 480, "focal": 0.5, "k1": 0.0, "k2": 0.0}},'
        ' "shots": {"b.jpg": {"rotation": [1.5707963267948966, 0.0, 0.0],'
        ' "translation": [0.0, 0.0, 5.0], "camera": "v2 other 640 480 perspective 0.5"},'
        ' "a.jpg": {"rotation": [0.0, 0.0, 0.0], "translation": [0.0, 0.0, 0.0],'
        ' "camera": "v2 cam 640 480 brown 0.5", "capture_time": 12.5}}, "points": {}}]'
    )
    ps = read_poses(tmp_path)  # the folder holding it
    a, b = ps.views
    assert (a.name, b.name) == ("a.jpg", "b.jpg") and a.time == 12.5
    # a: at the origin looking along +z; f = 0.5 * 640 = 320 px, cx = 319.5 + 0.01 * 640
    np.testing.assert_allclose(_pixel(a, (1.0, 0.0, 10.0)), (319.5 + 6.4 + 32.0, 239.5))
    # b: rotated 90° about x (camera z = world +y), centre -Rᵀt = (0, -5, 0)
    np.testing.assert_allclose(b.center, [0.0, -5.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(_pixel(b, (0.0, 10.0, -1.5)), (319.5, 239.5 + 32.0), atol=1e-9)


@pytest.mark.parametrize("writer", ["pix4d", "metashape", "opensfm"])
def test_exports_round_trip(tmp_path, writer):
    views = [replace(v, intrinsics=_views(1)[0].intrinsics) for v in _views()]  # one camera
    if writer == "opensfm":
        views = _views()  # two cameras, one with distortion
        path = write_opensfm(tmp_path / "reconstruction.json", views)
    else:
        write_colmap_cameras_text(tmp_path / "cameras.txt", {views[0].intrinsics: 1})
        write = write_pix4d_opk if writer == "pix4d" else write_metashape_opk
        path = write(tmp_path / "export.txt", views)
    got = read_poses(path).views
    for a, b in zip(views, got, strict=True):
        assert a.name == b.name and a.intrinsics == b.intrinsics
        np.testing.assert_allclose(a.center, b.center, atol=1e-6)
        np.testing.assert_allclose(a.pose.R, b.pose.R, atol=1e-9)


def test_format_is_told_by_content_not_by_the_extension(tmp_path):
    views = _views(2)
    write_colmap_cameras_text(tmp_path / "cameras.txt", {views[0].intrinsics: 1})
    one = [replace(v, intrinsics=views[0].intrinsics) for v in views]
    assert sniff_format(write_metashape_opk(tmp_path / "images.txt", one)) == "metashape"
    assert len(read_poses(tmp_path / "images.txt")) == 2  # a Metashape file named images.txt
    assert sniff_format(write_pix4d_opk(tmp_path / "p.csv", one)) == "pix4d"
    assert sniff_format(write_opensfm(tmp_path / "r.txt", views)) == "opensfm"
    assert sniff_format(write_opk_csv(tmp_path / "o.txt", views, CRS)) == "opk_csv"
    assert sniff_format(write_colmap_text(tmp_path / "c", views)) == "colmap_text"
    hashed = tmp_path / "hashed.txt"  # Pix4D's header is sometimes a '#' comment
    hashed.write_text("# " + (tmp_path / "p.csv").read_text())
    assert [v.name for v in read_poses(hashed).views] == [v.name for v in views]


# --- the workers' crop cache key ------------------------------------------------------------


def test_the_crop_cache_key_changes_with_every_input_of_the_crop():
    from streetcd.config import Config
    from streetcd.geometry.camera import opk_to_rotation
    from streetcd.run.plan import Batch, ViewTask
    from streetcd.run.worker import cloud_key
    from streetcd.types import Pose

    views = _views(3)

    def batch(vs, **kw):
        tasks = tuple(ViewTask(v, (), "s0", "h") for v in vs)
        args = dict(store="/s.zarr", store_generation=3, store_id="abc") | kw
        return Batch(
            "s0",
            0,
            tasks,
            out_dir="/o",
            config=Config(),
            params_hash="p",
            crop_views=tuple(vs),
            **args,
        )

    base = cloud_key(batch(views))
    assert cloud_key(batch(list(views))) == base  # equal inputs, equal key
    turned = replace(views[1], pose=Pose.from_center(opk_to_rotation(90, 0, 10), views[1].center))
    moved = replace(views[1], pose=Pose.from_center(views[1].pose.R, views[1].center + 0.01))
    zoomed = replace(views[1], intrinsics=replace(views[1].intrinsics, fx=1500.0))
    changed = [
        batch([views[0], turned, views[2]]),  # re-oriented, same centre (issue 19)
        batch([views[0], moved, views[2]]),
        batch([views[0], zoomed, views[2]]),
        batch(views, store_id="def"),  # another store at the same path
        batch(views, store_generation=4),
        batch(views, store="/t.zarr"),
    ]
    keys = [cloud_key(b) for b in changed]
    assert base not in keys and len(set(keys)) == len(keys)
