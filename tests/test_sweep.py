"""The nearer-depth test (streetcd.detect.sweep): a textured plate added 5 m in front of a
textured wall, seen by a view and two neighbours 1 m to each side; the old cloud is the wall
alone."""

from __future__ import annotations

import cv2
import numpy as np

from streetcd.detect.sweep import nearer_depth_change
from streetcd.types import Intrinsics, Pose

RNG = np.random.default_rng(11)
INTR = Intrinsics(160, 120, 150.0, 150.0, 79.5, 59.5)
WALL_Z, PLATE_Z, HALF = 10.0, 5.0, 0.5  # the plate: 1 m square, centred on the view's axis


def _texture(sigma: float) -> np.ndarray:
    """(2000, 2000) float32 grey levels, 100 per metre: noise blurred to ``sigma`` texels
    (0.1 m: a pixel or two at the wall), its contrast back to a standard deviation of 40."""
    t = cv2.GaussianBlur(RNG.uniform(0, 255, (2000, 2000)).astype(np.float32), (0, 0), sigma)
    return (t - t.mean()) / t.std() * 40.0 + 128.0


WALL, PLATE = _texture(10.0), _texture(10.0)


def _render(center_x: float, plate: bool) -> np.ndarray:
    """(H, W, 3) uint8 of a camera at (center_x, 0, 0) looking down +z."""
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float32)
    rx, ry = (u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy
    grey = cv2.remap(WALL, (center_x + rx * WALL_Z) * 100 + 1000, ry * WALL_Z * 100 + 1000, 1)
    if plate:
        px, py = center_x + rx * PLATE_Z, ry * PLATE_Z
        on = (np.abs(px) <= HALF) & (np.abs(py) <= HALF)
        grey[on] = cv2.remap(PLATE, px * 100 + 1000, py * 100 + 1000, 1)[on]
    return np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, axis=2)


def _pose(center_x: float) -> Pose:
    return Pose(np.eye(3), np.array([-center_x, 0.0, 0.0]))


def _nearer(plate: bool, at: tuple[float, ...] = (-1.0, 1.0), **kw) -> np.ndarray:
    """``N_p`` of the view at x = 0 with neighbours at the x of ``at``."""
    depth = np.full((INTR.height, INTR.width), WALL_Z, np.float32)
    neighbours = [(_render(x, plate), depth, INTR, _pose(x), None) for x in at]
    args = {
        "fractions": (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9),
        "margin": 0.05,
        "span": 0.15,
        "match": 0.08,
        "window_px": 3,
        "scale": 1.0,
        "max_work_px": 4000,
        "occlusion_tolerance_m": 0.3,
    }
    args.update(kw)
    return nearer_depth_change(_render(0.0, plate), depth, INTR, _pose(0.0), neighbours, **args)


def test_an_added_plate_is_explained_by_its_nearer_depth_and_the_wall_is_not():
    n = _nearer(plate=True)
    half_px = int(INTR.fx * HALF / PLATE_Z)  # 15 px: the plate covers rows 45-75, cols 65-95
    inner = np.zeros(n.shape, bool)
    inner[60 - half_px + 3 : 60 + half_px - 3, 80 - half_px + 3 : 80 + half_px - 3] = True
    around = np.zeros(n.shape, bool)  # the plate and two pixels round it
    around[60 - half_px - 2 : 60 + half_px + 2, 80 - half_px - 2 : 80 + half_px + 2] = True
    assert np.mean(n[inner] > 0.5) > 0.9  # the plate, but for a border of the window
    assert n[:, :40].max() == 0.0 and n[:, -40:].max() == 0.0  # the wall away from it
    # beside it, where one neighbour sees the plate through the wall (its ghost): a little
    assert (n[~around] > 0.5).sum() < 0.15 * (n[around] > 0.5).sum()


def test_neighbours_all_on_one_side_give_no_evidence():
    # the same plate, its neighbours both to the right (the last view of a walk): a nearer
    # depth would explain the plate, and a pose error as well, so the test says nothing
    assert _nearer(plate=True).max() > 0.5
    assert not _nearer(plate=True, at=(1.0, 2.0)).any()


def test_an_unchanged_street_gives_no_evidence():
    assert _nearer(plate=False).max() == 0.0


def test_one_neighbour_or_no_surface_gives_no_evidence():
    depth = np.full((INTR.height, INTR.width), np.nan, np.float32)
    nb = [(_render(1.0, True), depth, INTR, _pose(1.0), None)] * 2
    args = dict(fractions=(0.5,), margin=0.05, span=0.15, match=0.08, window_px=3, scale=1.0)
    none = nearer_depth_change(
        _render(0.0, True),
        depth,
        INTR,
        _pose(0.0),
        nb,
        max_work_px=4000,
        occlusion_tolerance_m=0.3,
        **args,
    )
    assert none.shape == depth.shape and not none.any()
    wall = np.full_like(depth, WALL_Z)
    alone = nearer_depth_change(
        _render(0.0, True),
        wall,
        INTR,
        _pose(0.0),
        nb[:1],
        max_work_px=4000,
        occlusion_tolerance_m=0.3,
        **args,
    )
    assert not alone.any()


def test_trying_the_nearer_depths_on_the_packed_candidates_equals_the_whole_raster():
    """The nearer depths run only where the old surface leaves more than the margin, packed
    into rows: the same values as computing every pixel (a reference written out here)."""
    from streetcd.detect import sweep
    from streetcd.detect.correlate import Neighbour, camera_rays, stretch_histogram

    depth = np.full((INTR.height, INTR.width), WALL_Z, np.float32)
    depth[:, :20] = np.nan  # no old surface there
    fractions, margin, span, match = (0.4, 0.5, 0.6), 0.05, 0.15, 0.08

    def blur(img):
        return cv2.blur(np.asarray(stretch_histogram(img), np.float32), (3, 3))

    view = blur(_render(0.0, True))
    nbs = [Neighbour(blur(_render(x, True)), depth, INTR, _pose(x)) for x in (-1.0, 1.0)]
    rays = camera_rays(INTR)
    old = sweep.worst_difference(view, nbs, depth, rays, _pose(0.0), 0.3)
    near = np.fmin.reduce(
        [sweep.worst_difference(view, nbs, depth * f, rays, _pose(0.0), 0.3) for f in fractions],
        axis=0,
    )
    with np.errstate(invalid="ignore"):
        want = np.where(
            (old - near > margin) & (near <= match), np.clip((old - near - margin) / span, 0, 1), 0
        )
    neighbours = [(_render(x, True), depth, INTR, _pose(x), None) for x in (-1.0, 1.0)]
    got = nearer_depth_change(
        _render(0.0, True),
        depth,
        INTR,
        _pose(0.0),
        neighbours,
        fractions=fractions,
        margin=margin,
        span=span,
        match=match,
        window_px=3,
        scale=1.0,
        max_work_px=4000,
        occlusion_tolerance_m=0.3,
    )
    assert (want > 0.5).sum() > 300
    np.testing.assert_array_equal(got, want.astype(np.float32))
