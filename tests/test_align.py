"""Registration of each neighbour to the view before eq. 5 (streetcd.detect.align): a textured
wall seen by two cameras 1 m apart, the neighbour's pose wrong by a yaw of a few pixels."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from streetcd.config import REFERENCE_WIDTH_PX, Config, CorrelateParams, DetectParams, TextureParams
from streetcd.detect.align import neighbour_shifts
from streetcd.detect.correlate import Neighbour, raw_change, stretch_histogram
from streetcd.detect.texture import texture_change, working_view
from streetcd.errors import InputError
from streetcd.types import Intrinsics, Pose

INTR = Intrinsics(160, 120, 150.0, 150.0, 79.5, 59.5)
WALL_Z = 10.0
PARAMS = TextureParams(scale=1.0, window_px=9)
ONE_PX = REFERENCE_WIDTH_PX / INTR.width  # a shift of one pixel of these images, in settings


def _render(texture: np.ndarray, center_x: float) -> np.ndarray:
    """(H, W, 3) uint8 of a camera at (center_x, 0, 0) looking down +z at the wall."""
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float32)
    x = center_x + (u - INTR.cx) / INTR.fx * WALL_Z
    y = (v - INTR.cy) / INTR.fy * WALL_Z
    grey = cv2.remap(texture, x * 100 + 600, y * 100 + 600, cv2.INTER_LINEAR)
    return np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, axis=2)


def _yawed(pose: Pose, angle: float) -> Pose:
    rot, _ = cv2.Rodrigues(np.array([0.0, angle, 0.0]))
    return Pose.from_center(rot @ pose.R, pose.center)


def _wall(yaw_px: float, seed: int = 5):
    """The view at the origin, a neighbour 1 m aside whose pose is wrong by a yaw that moves
    its pixels by ``yaw_px``: images, poses, and the wall's depth (H, W) float32."""
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (1200, 1200)).astype(np.float32), (0, 0), 15.0)
    texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX)  # blobs a few px wide
    view, other = _render(texture, 0.0), _render(texture, 1.0)
    pose_p = Pose(np.eye(3), np.zeros(3))
    pose_q = _yawed(Pose.from_center(np.eye(3), np.array([1.0, 0.0, 0.0])), yaw_px / INTR.fx)
    return view, other, pose_p, pose_q, np.full((INTR.height, INTR.width), WALL_Z, np.float32)


def _shifts(view, other, pose_p, pose_q, depth, max_px=12.0, min_gain=0.05):
    nbs = [(other, depth, INTR, pose_q, None)]
    working = working_view(view, depth, INTR, pose_p, nbs, PARAMS, 0.3)
    assert len(working.warps) == 1 and working.warps[0][0].shape == depth.shape
    return neighbour_shifts(working, INTR.width, None, PARAMS, max_px * ONE_PX, min_gain)


@pytest.mark.parametrize("yaw_px", [-6.0, 4.0, 7.0])
def test_the_shift_of_a_yawed_neighbour_is_found_to_a_pixel(yaw_px):
    view, other, pose_p, pose_q, depth = _wall(yaw_px)
    ((dy, dx),) = _shifts(view, other, pose_p, pose_q, depth)
    assert dy == 0 and abs(abs(dx) - abs(yaw_px)) <= 1  # a yaw moves pixels along the rows


def test_exact_poses_give_no_shift_and_so_do_shifts_at_the_search_edge_or_without_gain():
    view, other, pose_p, pose_q, depth = _wall(0.0)
    assert _shifts(view, other, pose_p, pose_q, depth) == [(0.0, 0.0)]
    view, other, pose_p, pose_q, depth = _wall(7.0)
    assert _shifts(view, other, pose_p, pose_q, depth, max_px=4.0) == [(0.0, 0.0)]  # at its edge
    assert _shifts(view, other, pose_p, pose_q, depth, min_gain=1.5) == [(0.0, 0.0)]
    flat = np.full_like(view, 128)
    assert _shifts(flat, flat, pose_p, pose_q, depth) == [(0.0, 0.0)]


def test_eq5_with_the_shift_sees_half_the_change_on_the_wall():
    view, other, pose_p, pose_q, depth = _wall(7.0)
    (shift,) = _shifts(view, other, pose_p, pose_q, depth)
    params = CorrelateParams(registration_tolerance_px=1.0 * ONE_PX)  # a 1 px envelope
    nb = Neighbour(stretch_histogram(other), depth, INTR, pose_q)
    classes = np.full(depth.shape, 6, np.uint8)
    inner = np.zeros(depth.shape, bool)
    inner[15:-15, 25:-25] = True  # the wall the neighbour sees either way
    medians = []
    for offset in ((0.0, 0.0), shift):
        nbo = dataclasses.replace(nb, offset=offset)
        change, support = raw_change(
            stretch_histogram(view), depth, classes, INTR, pose_p, [nbo], params
        )
        assert support[inner].all()
        medians.append(float(np.median(change[inner])))
    # misregistered, the wall's blobs differ along their edges; shifted back, half as much (the
    # yaw's perspective and the 1 m baseline leave the rest)
    assert medians[0] > 0.15 and medians[1] < 0.6 * medians[0]


def test_the_alignment_is_a_switch_and_off_keeps_the_older_hash():
    off = Config(DetectParams(correlate=CorrelateParams(align_shift_px=0.0)))
    other_gain = Config(DetectParams(correlate=CorrelateParams(align_min_gain=0.1)))
    assert len({Config().results_hash(), off.results_hash(), other_gain.results_hash()}) == 3
    assert (
        off.results_hash()
        == Config(
            DetectParams(correlate=CorrelateParams(align_shift_px=0.0, align_min_gain=0.3))
        ).results_hash()
    )
    with pytest.raises(InputError, match="align_shift_px"):
        CorrelateParams(align_shift_px=-1.0)


def test_the_texture_cue_on_the_alignments_warps_is_the_cue_warping_itself():
    view, other, pose_p, pose_q, depth = _wall(5.0)
    depth = depth.copy()
    depth[40:80, 60:100] = 5.0  # an old object in front of the wall
    nbs = [(other, depth, INTR, pose_q, None)]
    params = TextureParams(scale=0.5, window_px=9)
    working = working_view(view, depth, INTR, pose_p, nbs, params, 0.3)
    where = np.zeros(depth.shape, bool)
    where[30:90, 50:110] = True
    own = texture_change(view, depth, INTR, pose_p, nbs, params, 0.3, 2.0, where)
    shared = texture_change(view, depth, INTR, pose_p, nbs, params, 0.3, 2.0, where, 0.0, working)
    assert np.array_equal(own[0], shared[0]) and np.array_equal(own[1], shared[1])


def test_a_search_of_one_working_pixel_keeps_no_shift():
    view, other, pose_p, pose_q, depth = _wall(7.0)
    # 1 px at the working size: any shift found lies at the search's edge
    assert _shifts(view, other, pose_p, pose_q, depth, max_px=1.0) == [(0.0, 0.0)]
