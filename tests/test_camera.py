"""Camera model: projection round trips and convention converters."""

import pickle

import numpy as np
import pytest

from streetcd.errors import InputError
from streetcd.geometry.camera import (
    backproject,
    backproject_depth_map,
    distort,
    in_image,
    look_at,
    opk_to_rotation,
    project,
    quaternion_to_rotation,
    rotation_to_opk,
    rotation_to_quaternion,
    undistort,
)
from streetcd.types import Intrinsics, Pose

INTR = Intrinsics(1920, 1080, 1400.0, 1402.0, 959.5, 539.5, (-0.08, 0.02, 0.001, -0.0005, 0.003))
UTM = np.array([372_000.0, 143_000.0, 12.0])


def _points_in_view(rng, pose, n=2000):
    uv = rng.uniform([0, 0], [1919, 1079], size=(n, 2))
    depth = rng.uniform(2.0, 60.0, size=n)
    return uv, depth


def test_project_backproject_identity_with_distortion():
    rng = np.random.default_rng(1)
    pose = look_at([3.0, -5.0, 1.6], [10.0, 12.0, 3.0])
    uv, depth = _points_in_view(rng, pose)
    pts = backproject(uv, depth, INTR, pose)
    uv2, depth2 = project(pts, INTR, pose)
    np.testing.assert_allclose(uv2, uv, atol=1e-7)
    np.testing.assert_allclose(depth2, depth, rtol=1e-12)


def test_georeferenced_pose_shifted_to_local_projects_the_same():
    rng = np.random.default_rng(2)
    pose_crs = look_at(UTM, UTM + [10.0, 15.0, 1.0])
    pts_crs = UTM + rng.uniform([-5, 5, -2], [25, 40, 8], size=(500, 3))
    uv_crs, d_crs = project(pts_crs, INTR, pose_crs)
    local = pose_crs.shifted(UTM)
    uv_loc, d_loc = project(pts_crs - UTM, INTR, local)
    ok = np.isfinite(uv_crs[:, 0])
    np.testing.assert_allclose(uv_loc[ok], uv_crs[ok], atol=1e-6)
    np.testing.assert_allclose(d_loc, d_crs, atol=1e-9)


def test_look_at_centres_the_target_and_keeps_up_up():
    pose = look_at([0.0, 0.0, 1.5], [0.0, 20.0, 1.5])
    uv, depth = project(np.array([[0.0, 20.0, 1.5], [0.0, 20.0, 5.0]]), INTR, pose)
    assert depth[0] == pytest.approx(20.0)
    assert uv[0] == pytest.approx([INTR.cx, INTR.cy])
    assert uv[1, 1] < uv[0, 1]  # a higher point is higher in the image (smaller row)
    np.testing.assert_allclose(pose.center, [0.0, 0.0, 1.5], atol=1e-12)


def test_points_behind_the_camera_are_nan_and_not_in_image():
    pose = look_at([0.0, 0.0, 0.0], [0.0, 10.0, 0.0])
    uv, depth = project(np.array([[0.0, -5.0, 0.0]]), INTR, pose)
    assert depth[0] < 0 and np.isnan(uv).all()
    assert not in_image(uv, INTR).any()


def test_undistort_inverts_distort():
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-0.7, 0.7, size=(2, 1000))
    xd, yd = distort(x, y, INTR.dist)
    xu, yu = undistort(xd, yd, INTR.dist)
    np.testing.assert_allclose(xu, x, atol=1e-9)
    np.testing.assert_allclose(yu, y, atol=1e-9)


def test_depth_map_backprojection_of_a_fronto_parallel_plane():
    intr = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
    pose = look_at([0.0, 0.0, 0.0], [0.0, 10.0, 0.0])
    pts = backproject_depth_map(np.full((48, 64), 10.0), intr, pose)
    np.testing.assert_allclose(pts[..., 1], 10.0, atol=1e-12)  # all on the plane y = 10


def test_scaled_intrinsics_match_opencv_resize_pixel_centres():
    small = INTR.scaled(0.5)
    assert (small.width, small.height) == (960, 540)
    # The principal point of a centred camera stays at the centre of the smaller image.
    assert small.cx == pytest.approx((960 - 1) / 2)


@pytest.mark.parametrize(
    "q", [[1, 0, 0, 0], [0.5, 0.5, -0.5, 0.5], [0.1, 0.9, 0.3, -0.2], [0, 0, 0, 1]]
)
def test_quaternion_round_trip(q):
    q = np.asarray(q, float) / np.linalg.norm(q)
    R = quaternion_to_rotation(q)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    q2 = rotation_to_quaternion(R)
    np.testing.assert_allclose(quaternion_to_rotation(q2), R, atol=1e-12)
    assert q2[0] >= 0


@pytest.mark.parametrize("opk", [(0, 0, 0), (10, 20, 30), (-80, 5, 170), (90, -30, -120)])
def test_opk_round_trip(opk):
    R = opk_to_rotation(*opk)
    np.testing.assert_allclose(rotation_to_opk(R), opk, atol=1e-9)


def test_opk_zero_looks_straight_down():
    # Photogrammetric convention: ω = φ = κ = 0 is a nadir camera with image "up" = north.
    pose = Pose.from_center(opk_to_rotation(0, 0, 0), [0.0, 0.0, 100.0])
    np.testing.assert_allclose(pose.direction, [0, 0, -1], atol=1e-12)
    uv, _ = project(np.array([[0.0, 10.0, 0.0]]), INTR, pose)
    assert uv[0, 1] < INTR.cy  # north is up in the image


def test_bad_intrinsics_and_poses_are_rejected_with_the_field():
    with pytest.raises(InputError, match="focal"):
        Intrinsics(10, 10, -1.0, 1.0, 5.0, 5.0)
    with pytest.raises(InputError, match="finite"):
        Intrinsics(10, 10, 1.0, 1.0, float("nan"), 5.0)
    with pytest.raises(InputError, match="not a rotation"):
        Pose(np.diag([1.0, 1.0, -1.0]), np.zeros(3))


def test_a_pose_pickles_bit_for_bit_and_keeps_its_centre():
    rng = np.random.default_rng(3)
    R = look_at(np.array([1.0, 2.0, 3.0]), np.array([40.0, -7.0, 1.5])).R
    pose = Pose(R, rng.normal(size=3) * 1e5)  # georeferenced-size translation
    back = pickle.loads(pickle.dumps(pose, protocol=5))
    assert back.R.tobytes() == pose.R.tobytes() and back.t.tobytes() == pose.t.tobytes()
    assert back.R.shape == (3, 3) and back.t.shape == (3,)
    assert back.R.flags.writeable and back.t.flags.writeable  # arrays of their own
    assert back.center.tobytes() == pose.center.tobytes()
    # a transposed (non-contiguous) R goes as its values, not its memory layout
    turned = Pose.of_rotation(np.asfortranarray(R), pose.t)
    assert pickle.loads(pickle.dumps(turned)).R.tobytes() == R.tobytes()
