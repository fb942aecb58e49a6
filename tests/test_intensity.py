"""Intensity check (streetcd.detect.intensity): a cloud without colours but with LiDAR
intensity; small exact rasters, then one view end to end on test_detect's wall and board."""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import pytest
from test_detect import CAMERAS, PARAMS, make_cloud, make_view, render, with_colours

from streetcd import classes as cls
from streetcd.config import AppearanceParams
from streetcd.detect.cache import SurfaceCache
from streetcd.detect.chain import detect_view, reference_kind
from streetcd.detect.intensity import LN_PER_CODE, fill_from, intensity_change, intensity_codes
from streetcd.errors import InputError
from streetcd.io.las import load_clouds, write_las
from streetcd.types import PointCloud

H, W = 100, 100
WALL_RGB, BOARD_RGB = (150, 150, 140), (200, 40, 40)


def _rasters(board_intensity: int = 30000, wall_intensity: int = 8000):
    """A wall (building) with a board (sign) at rows 40–50, columns 40–60: the class
    raster, the intensity codes the rasteriser would lay out, and where the board is."""
    classes = np.full((H, W), cls.BUILDING, np.uint8)
    board = np.zeros((H, W), bool)
    board[40:50, 40:60] = True
    classes[board] = cls.SIGN
    codes_of = intensity_codes(np.array([wall_intensity, board_intensity, 0], np.uint16))
    assert codes_of is not None
    codes = np.full((H, W), codes_of[0, 0], np.uint8)
    codes[board] = codes_of[1, 0]
    return classes, codes, board


def _image(board_there: bool) -> np.ndarray:
    image = np.full((H, W, 3), WALL_RGB, np.uint8)
    image[:, ::9] = (135, 135, 128)  # faint mortar lines: the wall is not perfectly flat
    if board_there:
        image[40:50, 40:60] = BOARD_RGB
    return image


def test_codes_keep_intensity_ratios_and_say_none_without_intensity():
    codes = intensity_codes(np.array([1000, 2000, 4000, 65535], np.uint16))
    assert codes is not None and codes.shape == (4, 3) and codes.dtype == np.uint8
    assert np.array_equal(codes[:, 0], codes[:, 2])  # grey: the same in the three channels
    steps = np.diff(codes[:, 0].astype(float)) * LN_PER_CODE
    assert steps[:2] == pytest.approx([np.log(2.0)] * 2, abs=LN_PER_CODE)  # doubling = ln 2
    assert intensity_codes(None) is None
    assert intensity_codes(np.zeros(5, np.uint16)) is None  # LAS always has the field
    assert intensity_codes(np.full(5, 700, np.uint16)) is None  # constant: no information


def test_fill_takes_the_surroundings_value_into_a_hole():
    values = np.zeros((64, 64, 1), np.float32)
    values[:, :32], values[:, 32:] = 10.0, 30.0
    weight = np.ones((64, 64), np.float32)
    weight[20:30, 10:20] = 0.0  # a hole inside the 10 side
    filled = fill_from(values, weight)
    assert filled[20:30, 10:20].min() == pytest.approx(10.0, abs=0.5)
    hole = np.ones((64, 64), np.float32)
    hole[20:40, 24:40] = 0.0  # across the edge: between the two sides
    across = fill_from(values, hole)[30, 24:40, 0]
    assert 10.0 <= across.min() and across.max() <= 30.0 and across[-1] > across[0]


def test_a_removed_board_looks_like_the_wall_and_a_present_one_does_not():
    classes, codes, board = _rasters()
    valid = np.ones((H, W), bool)
    gone = intensity_change(_image(False), codes, valid, classes)
    assert gone[board].mean() > 0.9
    assert gone[~board].max() == 0.0  # only the inventory is checked
    there = intensity_change(_image(True), codes, valid, classes)
    assert there.max() == 0.0


def test_an_object_the_scanner_could_not_tell_from_the_wall_proves_nothing():
    classes, codes, board = _rasters(board_intensity=8000, wall_intensity=8000)
    valid = np.ones((H, W), bool)
    assert intensity_change(_image(False), codes, valid, classes).max() < 1e-3
    ungated = AppearanceParams(intensity_contrast=0.0)
    assert intensity_change(_image(False), codes, valid, classes, ungated)[board].mean() > 0.9


def test_registration_bands_are_opened_away():
    """The board still stands, shifted 2 px by a pose error: the strip where the image shows
    the wall on the board's old pixels is narrower than the opening and goes."""
    classes, codes, _ = _rasters()
    shifted = np.full((H, W, 3), WALL_RGB, np.uint8)
    shifted[40:50, 42:62] = BOARD_RGB
    valid = np.ones((H, W), bool)
    assert intensity_change(shifted, codes, valid, classes).max() > 0.5  # the 2 px strip
    assert intensity_change(shifted, codes, valid, classes, registration_px=2).max() == 0.0


def test_no_surface_or_no_inventory_gives_zero():
    classes, codes, _ = _rasters()
    image = _image(False)
    assert not intensity_change(image, codes, np.zeros((H, W), bool), classes).any()
    off = AppearanceParams(classes=())
    assert not intensity_change(image, codes, np.ones((H, W), bool), classes, off).any()


def test_settings_are_checked():
    with pytest.raises(InputError, match="intensity_same_rgb"):
        AppearanceParams(intensity_same_rgb=40.0, intensity_differ_rgb=30.0)
    with pytest.raises(InputError, match="intensity_contrast"):
        AppearanceParams(intensity_contrast=-1.0)


def _with_intensity(cloud: PointCloud) -> PointCloud:
    """The cloud as a scanner without a camera records it: the board bright, the rest dim."""
    bright = cloud.classification == cls.SIGN
    intensity = np.where(bright, 40000, 9000).astype(np.uint16)
    return PointCloud(cloud.xyz, cloud.origin, cloud.classification, intensity=intensity)


def _detect(images, cloud, params=PARAMS, surfaces=None):
    nbs = [(images[n], make_view(n)) for n in ("a.png", "b.png", "c.png")]
    return detect_view(images["p.png"], make_view("p.png"), nbs, cloud, params, surfaces=surfaces)


def test_a_board_removed_from_a_plain_wall_is_seen_through_the_intensity(caplog):
    """test_detect's board, gone from a plain wall, in a cloud without colours: eq. 5 cannot
    see it; the intensity check can, and only runs when the cloud has no colours."""
    plain = {name: render(x, board=False, plain=True)[0] for name, x in CAMERAS.items()}
    was_board = render(0.0)[1]
    cloud = _with_intensity(make_cloud(board=True))
    off = replace(PARAMS, appearance=replace(PARAMS.appearance, intensity=False))
    assert reference_kind(cloud, PARAMS) == "intensity" and reference_kind(cloud, off) is None
    cache = SurfaceCache()  # one cache for both settings: the key must tell them apart
    without = _detect(plain, cloud, off, surfaces=cache)
    assert without.appearance is None
    assert without.mask[was_board].mean() < 0.1
    with caplog.at_level(logging.INFO, logger="streetcd.detect.chain"):
        result = _detect(plain, cloud, surfaces=cache)
    assert result.appearance is not None
    assert result.mask[was_board].mean() > 0.75
    assert result.mask[~was_board].mean() < 0.01
    assert any("intensity check" in r.getMessage() for r in caplog.records)
    # with colours the reference-colour check runs instead, whatever the intensity says
    coloured = with_colours(cloud)
    coloured = PointCloud(
        coloured.xyz, coloured.origin, coloured.classification, cloud.intensity, coloured.rgb
    )
    assert reference_kind(coloured, PARAMS) == "colour"


def test_load_clouds_keeps_intensity_only_when_every_file_has_it(tmp_path):
    xyz = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]) + 500000.0
    codes = np.array([2, 6], np.uint8)
    a = write_las(tmp_path / "a.las", xyz, codes, intensity=np.array([10, 20], np.uint16))
    b = write_las(tmp_path / "b.las", xyz + 1.0, codes, intensity=np.array([30, 40], np.uint16))
    cloud = load_clouds([a, b])
    assert cloud.intensity is not None
    assert cloud.intensity.tolist() == [10, 20, 30, 40]


def test_results_hash_holds_the_intensity_settings_only_when_the_check_is_on():
    from streetcd.config import Config

    def with_appearance(**changes):
        c = Config()
        return replace(
            c, detect=replace(c.detect, appearance=replace(c.detect.appearance, **changes))
        )

    on = with_appearance().results_hash()
    assert with_appearance(intensity_contrast=0.5).results_hash() != on
    off = with_appearance(intensity=False).results_hash()
    assert off != on
    assert with_appearance(intensity=False, intensity_contrast=0.5).results_hash() == off
