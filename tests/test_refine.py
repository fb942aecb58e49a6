"""Pixel outlines by colour (streetcd.detect.refine) on small exact scenes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from streetcd.config import REFERENCE_WIDTH_PX, RefineParams
from streetcd.detect.refine import refine_outline

W, H = 400, 300
PARAMS = RefineParams(band_px=12 * REFERENCE_WIDTH_PX / W)  # 12 px at 400 px wide


def scene(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A textured wall with a red board (rows 100-179, columns 150-259): image and truth."""
    rng = np.random.default_rng(seed)
    image = np.empty((H, W, 3), np.uint8)
    image[:] = (150, 140, 120)
    image = np.clip(image + rng.normal(0, 6, image.shape), 0, 255).astype(np.uint8)
    truth = np.zeros((H, W), bool)
    truth[100:180, 150:260] = True
    image[truth] = np.clip(
        np.array([200, 40, 40]) + rng.normal(0, 6, (int(truth.sum()), 3)), 0, 255
    ).astype(np.uint8)
    return image, truth


def blocky(truth: np.ndarray, cell: int = 24) -> np.ndarray:
    """What a superpixel cut gives: the truth on a grid of ``cell`` px, cells at least half
    covered in, so the outline is off by up to half a cell (the band of PARAMS)."""
    h, w = truth.shape
    small = cv2.resize(truth.astype(np.float32), (w // cell, h // cell), cv2.INTER_AREA) >= 0.5
    return cv2.resize(small.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_a_blocky_outline_snaps_to_the_object():
    image, truth = scene()
    cut = blocky(truth)
    assert iou(cut, truth) < 0.9
    refined = refine_outline(image, cut, W, PARAMS)
    assert iou(refined, truth) > 0.97


def test_an_outline_inside_the_object_grows_onto_it_within_the_band():
    image, truth = scene()
    cut = np.zeros_like(truth)
    cut[108:172, 158:252] = True  # 8 px inside the board on every side
    refined = refine_outline(image, cut, W, PARAMS)
    assert iou(refined, truth) > 0.97


def test_the_outline_moves_at_most_the_band():
    image, truth = scene()
    cut = np.zeros_like(truth)
    cut[60:150, 110:300] = True  # the board and 40 px of wall around it, bar the bottom
    refined = refine_outline(image, cut, W, PARAMS)
    reach = cv2.distanceTransform((~cut).astype(np.uint8), cv2.DIST_L2, 5)
    assert reach[refined].max() <= 12 + 1  # it may grow no farther than the band
    inward = cv2.distanceTransform(cut.astype(np.uint8), cv2.DIST_L2, 5)
    assert refined[inward > 13].all()  # nor give up what lies deeper than the band
    assert (refined & ~truth).sum() < (cut & ~truth).sum()  # but sheds wall within it


def test_the_core_of_a_region_stays_and_other_regions_are_not_taken_away():
    image, truth = scene()
    cut = np.zeros_like(truth)
    cut[30:90, 20:100] = True  # a region on plain wall: not an object by colour
    cut[100:180, 150:260] = truth[100:180, 150:260]
    refined = refine_outline(image, cut, W, PARAMS)
    core = cv2.erode(cut[:, :130].astype(np.uint8), np.ones((25, 25), np.uint8)) > 0
    assert refined[:, :130][core].all()  # what the cut decided stays decided
    assert refined[truth].all()


def test_off_or_empty_gives_the_mask_back_unchanged():
    image, truth = scene()
    cut = blocky(truth)
    off = refine_outline(image, cut, W, RefineParams(enabled=False))
    assert np.array_equal(off, cut) and off is not cut
    empty = refine_outline(image, np.zeros_like(cut), W, PARAMS)
    assert not empty.any()


@pytest.mark.parametrize("bad", [dict(band_px=0.5), dict(iterations=0)])
def test_bad_parameters_are_refused(bad):
    from streetcd.errors import InputError

    with pytest.raises(InputError):
        RefineParams(**bad)


def test_a_wide_band_runs_scaled_down_and_still_snaps():
    # band 24 px > WORK_BAND_PX: GrabCut runs at half size, the band is kept at full size
    image, truth = scene()
    cut = blocky(truth, cell=48)
    wide = RefineParams(band_px=24 * REFERENCE_WIDTH_PX / W)
    refined = refine_outline(image, cut, W, wide)
    assert iou(cut, truth) < 0.9 and iou(refined, truth) > 0.95
    reach = cv2.distanceTransform((~cut).astype(np.uint8), cv2.DIST_L2, 5)
    assert reach[refined].max() <= 24 + 1


def test_the_same_input_gives_the_same_outline_every_time():
    # GrabCut's k-means++ draws from OpenCV's RNG: reruns and resumed runs must agree
    image, truth = scene(seed=3)
    cut = blocky(truth)
    first = refine_outline(image, cut, W, PARAMS)
    cv2.randu(np.empty((64, 64), np.uint8), 0, 255)  # move the RNG on
    assert all(np.array_equal(first, refine_outline(image, cut, W, PARAMS)) for _ in range(5))
