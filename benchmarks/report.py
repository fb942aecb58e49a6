"""The review page of a night of many views: ``streetcd report`` against its irreducible work.

    .venv/bin/python benchmarks/report.py [--views 1000] [--repeat 3] [--size 1920x1080]

The night is the one of ``tests/test_report.py::make_night`` (imported from there): ``--views``
cameras along a façade, JPEGs of ``--size``, every 2nd view flagged with one change, the last
one failed, all written through the store API (index, tile store, pose file). It is built
once, untimed, in a temporary folder (removed at the end).

:func:`streetcd.report.site.write_report` is timed ``--repeat`` times after a warm-up, each
time into a fresh folder: wall and CPU seconds (this process, all its threads), medians.

Baseline in the same run: the work no report can skip. For the same views the report
pictures (every view a change cites), read the JPEG at reduced size with OpenCV (libjpeg's
DCT scaling, ``cv2.IMREAD_REDUCED_COLOR_{2,4,8}``: the largest reduction that keeps at least
480 px, as :func:`streetcd.report.render.read_thumbnail` picks it), fit it to 480 px wide and
write it as a JPEG thumbnail, in as many threads as the report renders with
(:data:`streetcd.report.site.RENDER_THREADS`), each time into a fresh folder. The report does
that and more (the change outlined, the old cloud cropped and drawn from each view's pose,
the page's data): the ratio says how much more. Report and baseline alternate, so load from
other work drifts over both; on a busy machine read the ratio, not the seconds.

Goal (issue 18): the report of a 1,000-view run in ≤ 30 s wall, judged from the report's
wall median when ``--views`` is 1000.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # make_night: the test's night, not a copy of it

GOAL_VIEWS = 1000
GOAL_S = 30.0


def cited_images(index: Path, images: Path) -> list[Path]:
    """The image of every view a change cites: the views the report pictures."""
    from streetcd.report.changes import load_changes

    cited = {v["view"] for c in load_changes(index) for v in c.get("views") or ()}
    return [images / name for name in sorted(cited)]


def reduced_flag(image_width: int, width: int) -> int:
    """OpenCV's largest reduced decode that keeps at least ``width`` px."""
    from streetcd.report.render import REDUCED_FLAGS

    for factor, flag in REDUCED_FLAGS:
        if image_width // factor >= width:
            return flag
    return cv2.IMREAD_COLOR


def thumbnail(path: Path, out: Path, flag: int, width: int) -> None:
    """Read ``path`` with ``flag``, fit it to ``width`` px wide, write it to ``out`` as JPEG."""
    from streetcd.report.render import JPEG_QUALITY

    image = cv2.imdecode(np.fromfile(path, dtype=np.uint8), flag)
    if image is None:
        raise SystemExit(f"cannot decode {path}")
    h, w = image.shape[:2]
    if w != width:
        image = cv2.resize(image, (width, round(h * width / w)), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise SystemExit(f"cannot encode a thumbnail of {path}")
    out.write_bytes(buf.tobytes())


def time_report(index: Path, out: Path):
    """One :func:`write_report` into the fresh folder ``out``: (wall s, CPU s, result)."""
    from streetcd.report.site import write_report

    shutil.rmtree(out, ignore_errors=True)
    t0, cpu0 = time.perf_counter(), time.process_time()
    result = write_report(index, out)
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    shutil.rmtree(out, ignore_errors=True)
    return wall, cpu, result


def time_baseline(paths: list[Path], out: Path, flag: int) -> tuple[float, float]:
    """The baseline's thumbnails of ``paths`` into the fresh folder ``out``: (wall s, CPU s)."""
    from streetcd.report.render import THUMB_WIDTH_PX
    from streetcd.report.site import RENDER_THREADS

    shutil.rmtree(out, ignore_errors=True)
    t0, cpu0 = time.perf_counter(), time.process_time()
    out.mkdir(parents=True)
    with ThreadPoolExecutor(RENDER_THREADS) as pool:
        jobs = [
            pool.submit(thumbnail, p, out / f"{p.stem}.jpg", flag, THUMB_WIDTH_PX) for p in paths
        ]
        for job in jobs:
            job.result()
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    shutil.rmtree(out, ignore_errors=True)
    return wall, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=GOAL_VIEWS, help="views in the night")
    ap.add_argument("--repeat", type=int, default=3, help="timed runs of each (median)")
    ap.add_argument("--size", default="1920x1080", help="image size WxH")
    args = ap.parse_args()
    w, h = map(int, args.size.lower().split("x"))

    from test_report import make_night

    from streetcd.report.render import THUMB_WIDTH_PX

    work = Path(tempfile.mkdtemp(prefix="streetcd-bench-report-"))
    try:
        t0 = time.perf_counter()
        night = make_night(work / "night", n_views=args.views, image_size=(w, h))
        paths = cited_images(night.index, night.images)
        flag = reduced_flag(w, THUMB_WIDTH_PX)
        print(
            f"night: {args.views} views of {w}x{h} built in {time.perf_counter() - t0:.0f} s",
            file=sys.stderr,
        )
        time_report(night.index, work / "site")  # warm-up: imports, page cache, tile cache
        time_baseline(paths, work / "thumbs", flag)
        reports, baselines = [], []
        for _ in range(args.repeat):
            reports.append(time_report(night.index, work / "site"))
            baselines.append(time_baseline(paths, work / "thumbs", flag))
    finally:
        shutil.rmtree(work, ignore_errors=True)

    result = reports[0][2]
    if result.views != len(paths):
        sys.exit(f"the report pictured {result.views} views, the baseline {len(paths)}")
    wall = statistics.median(r[0] for r in reports)
    cpu = statistics.median(r[1] for r in reports)
    base_wall = statistics.median(b[0] for b in baselines)
    base_cpu = statistics.median(b[1] for b in baselines)
    if args.views == GOAL_VIEWS:
        goal = "met" if wall <= GOAL_S else "missed"
    else:
        goal = f"not judged ({args.views} views)"
    print(
        "| views | views pictured | changes | pictures | report s (wall) | report s (CPU) | "
        "baseline s (wall) | baseline s (CPU) | × baseline (wall) | × baseline (CPU) | "
        f"goal: {GOAL_VIEWS:,} views ≤ {GOAL_S:.0f} s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print(
        f"| {args.views:,} | {result.views:,} | {result.changes:,} | {result.pictures:,} | "
        f"{wall:.1f} | {cpu:.1f} | {base_wall:.1f} | {base_cpu:.1f} | "
        f"{wall / base_wall:.1f} | {cpu / base_cpu:.1f} | {goal} |"
    )
    print(
        f"\n{args.size} JPEGs, median of {args.repeat} after a warm-up; baseline: reduced "
        f"decode + {THUMB_WIDTH_PX} px JPEG of the {len(paths)} pictured views, same threads",
        file=sys.stderr,
    )


if __name__ == "__main__":
    main()
