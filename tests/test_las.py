"""LAS/LAZ I/O: georeferenced round trips and chunked reading (streetcd.io.las)."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from streetcd.errors import CorruptFileError, InputError, MissingInputError
from streetcd.io.las import iter_las_chunks, las_info, read_las, write_las

ORIGIN = np.array([512_345.0, 5_401_234.0, 250.0])  # UTM-sized: 10⁵–10⁶ m


def _points(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    return {
        "xyz": rng.uniform([0, 0, 0], [80, 40, 20], (n, 3)),
        "classification": rng.integers(1, 70, n).astype(np.uint8),
        "intensity": rng.integers(0, 65535, n).astype(np.uint16),
        "rgb": rng.integers(0, 65535, (n, 3)).astype(np.uint16),
        "gps_time": np.sort(rng.uniform(3e8, 3e8 + 100, n)),
    }


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_georeferenced_coordinates_survive_write_read_within_1mm(tmp_path, suffix):
    rng = np.random.default_rng(1)
    p = _points(rng, 5000)
    path = write_las(
        tmp_path / f"a{suffix}", p["xyz"], p["classification"], origin=ORIGIN, crs="EPSG:32632"
    )
    cloud = read_las(path, origin=ORIGIN)
    assert np.abs(cloud.xyz - p["xyz"]).max() <= 0.0005 + 1e-9  # 1 mm scale: ≤ half a unit
    # The same points in CRS coordinates (origin zeros) agree as well.
    absolute = read_las(path, origin=np.zeros(3))
    assert np.abs(absolute.xyz - (p["xyz"] + ORIGIN)).max() <= 0.0005 + 1e-9
    assert cloud.crs == "EPSG:32632"


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_chunked_reading_equals_whole_file_reading(tmp_path, suffix):
    rng = np.random.default_rng(2)
    p = _points(rng, 5500)
    path = write_las(
        tmp_path / f"a{suffix}",
        p["xyz"],
        p["classification"],
        origin=ORIGIN,
        intensity=p["intensity"],
        rgb=p["rgb"],
        gps_time=p["gps_time"],
        crs="EPSG:32632",
    )
    whole = read_las(path, origin=ORIGIN)
    chunks = list(iter_las_chunks(path, chunk_points=1000, origin=ORIGIN))
    assert [len(c) for c in chunks] == [1000] * 5 + [500]
    for name in ("xyz", "classification", "intensity", "rgb", "gps_time"):
        joined = np.concatenate([getattr(c, name) for c in chunks])
        np.testing.assert_array_equal(joined, getattr(whole, name), err_msg=name)
    assert all(c.crs == "EPSG:32632" and np.array_equal(c.origin, ORIGIN) for c in chunks)


def test_las_info_reads_the_header_only(tmp_path):
    rng = np.random.default_rng(3)
    p = _points(rng, 300)
    path = write_las(
        tmp_path / "a.laz", p["xyz"], p["classification"], origin=ORIGIN, crs="EPSG:25832"
    )
    info = las_info(path)
    assert info.point_count == 300 and info.crs == "EPSG:25832"
    np.testing.assert_allclose(info.mins, p["xyz"].min(axis=0) + ORIGIN, atol=0.001)
    np.testing.assert_allclose(info.maxs, p["xyz"].max(axis=0) + ORIGIN, atol=0.001)


def test_truncated_laz_names_the_file(tmp_path):
    rng = np.random.default_rng(4)
    p = _points(rng, 20000)
    path = write_las(tmp_path / "cut.laz", p["xyz"], p["classification"], origin=ORIGIN)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CorruptFileError, match="cut.laz"):
        for _ in iter_las_chunks(path, chunk_points=2000):
            pass


def test_nan_header_offset_names_the_file_and_field(tmp_path):
    rng = np.random.default_rng(5)
    p = _points(rng, 100)
    path = write_las(tmp_path / "nan.las", p["xyz"], p["classification"], origin=ORIGIN)
    data = bytearray(path.read_bytes())
    data[155:163] = struct.pack("<d", float("nan"))  # LAS header: X offset at byte 155
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"nan\.las: header field 'x offset' is nan"):
        list(iter_las_chunks(path))
    with pytest.raises(InputError, match=r"nan\.las: header field 'x offset' is nan"):
        read_las(path)


def test_missing_and_zero_byte_files_name_the_file(tmp_path):
    with pytest.raises(MissingInputError, match="nope.laz"):
        list(iter_las_chunks(tmp_path / "nope.laz"))
    empty = tmp_path / "zero.laz"
    empty.write_bytes(b"")
    with pytest.raises(CorruptFileError, match="zero.laz"):
        las_info(empty)
    with pytest.raises(CorruptFileError, match="zero.laz"):
        list(iter_las_chunks(empty))
