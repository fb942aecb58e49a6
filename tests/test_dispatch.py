"""Which batch each worker runs next (streetcd.run.dispatch.WorkQueues): exact bookkeeping on
hand-made batches; the Dispatcher on a real cluster is tested in test_pipeline."""

from __future__ import annotations

import numpy as np
from distributed.protocol import dumps, loads
from distributed.protocol.serialize import ToPickle

from streetcd.config import Config
from streetcd.run.dispatch import WorkQueues, split_tail
from streetcd.run.plan import Batch, ViewTask, _batches
from streetcd.run.segments import Segment
from streetcd.types import Intrinsics, Pose, View

PARAMS = Config()


def view(name: str) -> View:
    return View(name, Intrinsics(4, 3, 1.0, 1.0, 2.0, 1.5), Pose(np.eye(3), np.zeros(3)))


def segment(seg: str, n_views: int, size: int = 4) -> list[Batch]:
    """The batches of a segment of ``n_views`` views, ``size`` views each."""
    views = [view(f"{seg}{k}") for k in range(n_views)]
    tasks = [ViewTask(v, (), seg, f"h-{v.name}") for v in views]
    return [
        Batch(seg, k // size, tuple(tasks[k : k + size]), "store", "out", PARAMS, "p", tuple(views))
        for k in range(0, n_views, size)
    ]


def names(b: Batch) -> list[str]:
    return [t.view.name for t in b.tasks]


def test_the_tail_is_cut_into_single_views_in_order():
    batches = segment("A", 6) + segment("B", 9)  # A: 4+2, B: 4+4+1
    out = split_tail(batches, tail_views=3)
    # B's last batch is single already; its batch before is cut (1 + 4 >= 3), no more
    assert [len(b.tasks) for b in out] == [4, 2, 4, 1, 1, 1, 1, 1]
    assert [n for b in out for n in names(b)] == [n for b in batches for n in names(b)]
    assert [b.part for b in out[3:]] == [0, 1, 2, 3, None]
    assert len({b.key for b in out}) == len(out)
    assert all(b.crop_views == batches[0].crop_views for b in out[:2])
    assert split_tail(batches, 0) == batches


def test_a_worker_runs_its_own_share_in_order_and_is_told_what_follows():
    a, b = segment("A", 8), segment("B", 4)
    work = WorkQueues({"w0": a + b}, tail_views=0)
    got = []
    while (batch := work.take("w0", {"w0"})) is not None:
        got.append(batch)
        nxt, seg = work.ahead("w0", batch)
        assert nxt is (work.queues["w0"][0] if work.queues["w0"] else None)
        assert seg is (b[0] if batch.segment_id == "A" else None)
    assert got == a + b
    assert work.ahead("w0", b[-1]) == (None, None) and len(work) == 0


def test_a_worker_out_of_work_takes_the_last_single_view_of_the_longest_queue():
    live = {"w0", "w1", "w2"}
    work = WorkQueues(
        {"w0": segment("A", 4), "w1": segment("B", 8), "w2": segment("C", 6)}, tail_views=2
    )
    own = [work.take("w0", live) for _ in range(4)]
    assert [names(b) for b in own if b] == [["A0"], ["A1"], ["A2"], ["A3"]]
    stolen = work.take("w0", live)
    assert stolen is not None and names(stolen) == ["B7"]  # w1 had the most views queued
    # detected on its segment's crop, as its owner would have (the spacing estimate reads
    # the whole crop: docs/DECISIONS.md, "The crop a view is detected on")
    assert stolen.crop_views == work.queues["w1"][0].crop_views != ()
    assert work.views["w1"] == 7
    # the queue it came from still runs in order, and its owner is told so
    assert work.ahead("w1", own[0])[0] is work.queues["w1"][0]
    assert names(work.take("w1", live)) == ["B0", "B1", "B2", "B3"]


def test_the_queue_of_a_worker_that_is_gone_is_served_from_its_front():
    work = WorkQueues({"w0": segment("A", 4), "gone": segment("B", 8)}, tail_views=0)
    assert names(work.take("w0", {"w0"})) == ["A0", "A1", "A2", "A3"]
    first = work.take("w0", {"w0"})
    assert first is not None and names(first) == ["B0", "B1", "B2", "B3"]
    assert first.crop_views != ()  # a whole batch keeps the segment's shared crop
    assert names(work.take("w0", {"w0"})) == ["B4", "B5", "B6", "B7"]
    assert work.take("w0", {"w0"}) is None and len(work) == 0


def test_a_worker_that_joins_takes_from_the_back_of_the_longest_queue():
    work = WorkQueues({"w0": segment("A", 8), "w1": segment("B", 4)}, tail_views=0)
    late = work.take("new", {"w0", "w1", "new"})
    assert late is not None and names(late) == ["A4", "A5", "A6", "A7"]
    assert late.crop_views != ()
    assert [names(work.take("w0", {"w0"})) for _ in range(1)] == [["A0", "A1", "A2", "A3"]]


def test_a_batch_travels_to_dask_as_one_pickle_not_a_frame_per_pose():
    """Poses pickle in-band (Pose.__reduce__): a segment's batch with its crop views is one
    pickle, where numpy's out-of-band buffers made two frames for every pose."""
    batch = segment("s", 25, size=8)[0]
    frames = dumps({"batch": ToPickle(batch)})
    assert len(frames) <= 3, len(frames)
    back = loads(frames)["batch"]
    assert [t.view.name for t in back.tasks] == names(batch)
    assert all(
        a.pose.R.tobytes() == b.pose.R.tobytes() and a.pose.t.tobytes() == b.pose.t.tobytes()
        for a, b in zip(back.crop_views, batch.crop_views, strict=True)
    )


def test_a_segments_batches_crop_all_its_views_done_or_not():
    # a night resumed after a kill: one view of six left to do. Its batch still crops the
    # segment's views and their neighbours, as a clean night's batches do: the detector
    # estimates the point spacing from the crop it is given (docs/DECISIONS.md, "The crop a
    # view is detected on"), so a smaller crop would give the view another result
    views = [view(n) for n in "abcdefg"]  # g: a neighbour in the next segment
    neighbours = (("b",), ("a", "c"), ("b", "d"), ("c", "e"), ("d", "f"), ("e", "g"))
    seg = Segment("S", tuple("abcdef"), neighbours, np.zeros((1, 2)), (0, 0, 1, 1), 10.0)
    store = type("Store", (), {"index": {"generation": 1}})()
    todo = {"S": [ViewTask(views[2], (views[1], views[3]), "S", "h-c")]}
    (batch,) = _batches([seg], todo, views, PARAMS, "store", "out", "p", store)
    assert [t.view.name for t in batch.tasks] == ["c"]
    assert [v.name for v in batch.crop_views] == list("abcdefg")
