"""Neighbour selection by frustum overlap."""

import numpy as np
import pytest

from streetcd.geometry.camera import look_at
from streetcd.geometry.neighbours import overlap, select_neighbours
from streetcd.types import Intrinsics, Pose, View

INTR = Intrinsics(400, 300, 350.0, 350.0, 199.5, 149.5)
ORIGIN = np.array([350000.0, 5600000.0, 300.0])  # CRS-sized coordinates


def view(name: str, x: float, heading: float = 1.0, y: float = 0.0) -> View:
    """A camera at (x, y) on a street, 1.6 m high, looking along +y (heading 1) or −y."""
    local = look_at([x, y, 1.6], [x, y + 10.0 * heading, 1.6])
    return View(name, INTR, Pose.from_center(local.R, local.center + ORIGIN))


def strip(n: int = 7, spacing: float = 2.0) -> list[View]:
    return [view(f"img_{i:02d}.jpg", i * spacing) for i in range(n)]


def test_overlap_of_a_view_with_itself_is_one_and_falls_with_distance():
    views = strip()
    assert overlap(views[3], views[3]) == 1.0
    shares = [overlap(views[3], views[3 + k]) for k in (1, 2, 3)]
    assert 1.0 > shares[0] > shares[1] > shares[2] > 0.0


def test_nearest_views_are_chosen_never_the_view_itself():
    views = strip()
    chosen = select_neighbours(views[3], views, n=2)
    assert [v.name for v in chosen] == ["img_02.jpg", "img_04.jpg"]  # tie: by name
    chosen = select_neighbours(views[3], views, n=3)
    assert views[3] not in chosen and len(chosen) == 3
    assert {v.name for v in chosen[:2]} == {"img_02.jpg", "img_04.jpg"}


def test_ties_are_broken_deterministically_whatever_the_input_order():
    views = strip()
    rng = np.random.default_rng(0)
    first = [v.name for v in select_neighbours(views[3], views, n=4)]
    for _ in range(3):
        shuffled = [views[i] for i in rng.permutation(len(views))]
        assert [v.name for v in select_neighbours(views[3], shuffled, n=4)] == first


def test_views_looking_away_or_far_away_are_not_neighbours():
    p = view("p.jpg", 0.0)
    away = view("away.jpg", 1.0, heading=-1.0)
    far = view("far.jpg", 500.0)
    near = view("near.jpg", 1.5)
    assert overlap(p, away) == 0.0
    assert [v.name for v in select_neighbours(p, [away, far, near], n=3)] == ["near.jpg"]


@pytest.mark.parametrize("n", [0, 1, 5])
def test_at_most_n_are_returned(n):
    views = strip(9, 1.0)
    assert len(select_neighbours(views[4], views, n=n)) == min(n, 8)


def test_overlaps_in_one_batch_equal_overlap_pair_by_pair():
    from dataclasses import replace

    from streetcd.geometry.neighbours import overlaps

    views = strip(6, 3.0) + [view("back.jpg", 4.0, heading=-1.0), view("side.jpg", 5.0, y=8.0)]
    bent = Intrinsics(640, 360, 420.0, 430.0, 319.5, 179.5, (-0.2, 0.05, 0.001, -0.002, 0.0))
    views.append(replace(view("bent.jpg", 2.5), intrinsics=bent))  # distortion, other size
    for p in views:
        batch = overlaps(p, views)
        assert batch.tolist() == [overlap(p, q) for q in views]  # exactly, not approximately
        assert batch[views.index(p)] == 1.0
    assert overlaps(views[0], []).shape == (0,)


def test_a_camera_that_did_not_move_is_never_a_neighbour():
    """The same camera a second later at a red light overlaps best (all of it) and proves
    nothing: without parallax every depth is photo-consistent."""
    views = strip()
    stopped = view("img_03_later.jpg", 3 * 2.0)
    crept = view("img_03_crept.jpg", 3 * 2.0 + 0.05)  # 0.05 m: 0.9 px at 20 m, below 1.6 px
    p = views[3]
    assert overlap(p, stopped) == 1.0 and overlap(p, crept) > overlap(p, views[2])
    chosen = [v.name for v in select_neighbours(p, [*views, stopped, crept], n=3)]
    assert "img_03_later.jpg" not in chosen
    assert chosen[:2] == ["img_02.jpg", "img_04.jpg"]  # full parallax ranks first
    # overlap alone (the paper's choice) takes the camera that did not move first
    paper = select_neighbours(p, [*views, stopped, crept], n=3, min_parallax_px=0.0)
    assert paper[0].name == "img_03_later.jpg"


def test_neighbours_of_many_views_at_once_equal_one_view_at_a_time():
    """The planner's batched choice (blocks of views, candidate lists of unequal length
    padded) is the per-view choice, distortion and other image sizes included."""
    from dataclasses import replace

    from streetcd.geometry.neighbours import select_neighbours_many

    views = strip(9, 1.5) + [view("back.jpg", 4.0, heading=-1.0), view("far.jpg", 400.0)]
    bent = Intrinsics(640, 360, 420.0, 430.0, 319.5, 179.5, (-0.2, 0.05, 0.001, -0.002, 0.0))
    views.append(replace(view("bent.jpg", 2.5), intrinsics=bent))
    rng = np.random.default_rng(1)
    candidates = [[views[j] for j in rng.permutation(len(views))[: k % 7]] for k in range(12)]
    candidates[0] = views  # itself among them
    for n in (1, 3):
        one_by_one = [select_neighbours(v, c, n=n) for v, c in zip(views, candidates, strict=True)]
        assert select_neighbours_many(views, candidates, n=n) == one_by_one
        from streetcd.geometry import neighbours

        small = neighbours.overlaps_many(views, candidates, block=5)
        assert [s.tolist() for s in small] == [
            neighbours.overlaps(v, c).tolist() for v, c in zip(views, candidates, strict=True)
        ]


def test_overlap_counts_the_samples_the_other_camera_projects_into_its_image():
    """The compiled count (:func:`_seen_counts`) against the library's own projection,
    ``camera.project``, sample by sample: in front and inside the pixel border, a distorted
    camera and cameras looking away included (up to rounding at the border)."""
    from dataclasses import replace

    from streetcd.geometry.camera import project
    from streetcd.geometry.neighbours import frustum_samples, overlaps
    from streetcd.types import Pose

    bent = Intrinsics(640, 360, 420.0, 430.0, 319.5, 179.5, (-0.2, 0.05, 0.001, -0.002, 0.01))
    p = view("p.jpg", 0.0)
    others = [
        view("q.jpg", 3.0),
        view("away.jpg", 1.0, heading=-1.0),
        replace(view("bent.jpg", 2.5), intrinsics=bent),
        view("side.jpg", 6.0, y=12.0),
    ]
    # the samples in a frame at p's centre, as the kernel sees them, and each camera there
    local = replace(p, pose=Pose.from_center(p.pose.R, np.zeros(3)))
    samples = frustum_samples(local)
    expected = []
    for q in others:
        moved = Pose.from_center(q.pose.R, q.center - p.center)
        uv, depth = project(samples, q.intrinsics, moved)
        w, h = q.intrinsics.width, q.intrinsics.height
        with np.errstate(invalid="ignore"):
            inside = (uv[:, 0] >= -0.5) & (uv[:, 0] < w - 0.5)
            inside &= (uv[:, 1] >= -0.5) & (uv[:, 1] < h - 0.5)
        expected.append(np.count_nonzero((depth > 0) & inside) / len(samples))
    got = overlaps(p, others)
    assert got.tolist() == pytest.approx(expected, abs=1.5 / len(samples))
    assert got[1] == 0.0 and 0.0 < got[2] < 1.0 and got[0] > got[3]
