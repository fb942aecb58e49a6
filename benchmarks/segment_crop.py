"""A worker's segment crops on the 1,000-view city: what reading the tile store costs a night.

    nice .venv/bin/python benchmarks/segment_crop.py                 # the city of city_scale.py
    nice .venv/bin/python benchmarks/segment_crop.py --segments 20 --repeat 3

Every night a worker crops the reference cloud once per street segment, for the segment's
views and their neighbours (:meth:`streetcd.run.worker.WorkerRuntime.segment_cloud`); on small
images that is a noticeable share of a view's work (docs/BENCHMARKS.md). The crop decodes
the tiles' chunks (Blosc-zstd and a CRC-32C each), keeps the points some view sees, and joins
them. Three ways, round-robin over the segments in plan order, each from an empty tile cache
(the decoding a night pays for at least once per tile):

* ``zarr, all fields``: the chunks through zarr's own pipeline, every point array (what the
  store did before it decoded its own chunks; the baseline);
* ``direct, all fields``: the same chunks decoded by :func:`streetcd.store.tiles.read_chunk`'s
  own path (CRC-32C, Blosc header check, Blosc), every point array;
* ``direct, detector's fields``: as the worker now crops (:data:`streetcd.detect.chain.CLOUD_FIELDS`:
  no ``gps_time``, which the detector never reads).

Printed: the median and mean seconds per segment crop and each against the baseline, and one
chunk of each field decoded both ways. The city is the one ``benchmarks/city_scale.py
--views 1000 --generate-only`` builds (rendering it takes ~20 min once; it is reused).
"""

from __future__ import annotations

import os

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"  # one core, as a worker

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CITY = ROOT / "out" / "city-scale" / "city-1000-320x180-seed0"


@contextmanager
def through_zarr():
    """read_chunk through zarr's pipeline (as before its own decoding path)."""
    from streetcd.store import tiles

    plain = tiles._plain_codecs
    tiles._plain_codecs = lambda a: False
    try:
        yield
    finally:
        tiles._plain_codecs = plain


def segment_batches(city: Path, n: int) -> list:
    """The first batch of each of the first ``n`` segments of the city's plan."""
    from streetcd.config import load_config
    from streetcd.run.plan import plan_run

    config = load_config(ROOT / "configs" / "default.yaml")
    with tempfile.TemporaryDirectory() as tmp:
        plan = plan_run(
            city / "images", city / "poses_opk.csv", city / "store.zarr",
            Path(tmp) / "index.sqlite", Path(tmp) / "out", config,
        )  # fmt: skip
    first: dict[str, object] = {}
    for b in plan.batches:
        first.setdefault(b.segment_id, b)
    return list(first.values())[:n]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--city", type=Path, default=CITY, help="a city folder of city_scale.py")
    ap.add_argument("--segments", type=int, default=30)
    ap.add_argument("--repeat", type=int, default=2, help="rounds over the segments")
    args = ap.parse_args()
    if not (args.city / "ingested").exists():
        raise SystemExit(
            f"{args.city}: no city; make it with "
            "`.venv/bin/python benchmarks/city_scale.py --views 1000 --generate-only`"
        )
    from streetcd.detect.chain import CLOUD_FIELDS
    from streetcd.run.worker import batch_views
    from streetcd.store.crop import crop_for_views
    from streetcd.store.tiles import TileStore, chunk_file, read_chunk, tile_cache

    batches = segment_batches(args.city, args.segments)
    store = TileStore.open(args.city / "store.zarr")
    ways = {
        "zarr, all fields": (True, None),
        "direct, all fields": (False, None),
        "direct, detector's fields": (False, CLOUD_FIELDS),
    }
    times: dict[str, list[float]] = {w: [] for w in ways}
    points: dict[str, int] = {}

    def crop(batch, zarr_path: bool, fields) -> int:
        views = list(batch_views(batch))
        tile_cache().clear()
        if zarr_path:
            with through_zarr():
                cloud = crop_for_views(store, views, max_range_m=batch.config.detect.max_range_m)
        else:
            cloud = crop_for_views(
                store, views, max_range_m=batch.config.detect.max_range_m, fields=fields
            )
        return len(cloud)

    for zarr_path, fields in ways.values():  # warm-up: imports, numba, page cache
        crop(batches[0], zarr_path, fields)
    for _ in range(args.repeat):
        for b in batches:
            for way, (zarr_path, fields) in ways.items():
                t0 = time.perf_counter()
                n = crop(b, zarr_path, fields)
                times[way].append(time.perf_counter() - t0)
                points[way] = points.get(way, 0) + n
    if len(set(points.values())) != 1:
        raise SystemExit(f"the ways kept different points: {points}")

    base = statistics.median(times["zarr, all fields"])
    print(f"{len(batches)} segment crops × {args.repeat}, tile cache emptied before each\n")
    print(f"{'way':<28} {'median s':>9} {'mean s':>8} {'× baseline':>10}")
    for way, ts in times.items():
        med = statistics.median(ts)
        print(f"{way:<28} {med:>9.4f} {statistics.mean(ts):>8.4f} {med / base:>10.2f}")

    print(f"\n{'one chunk of':<16} {'MB':>5} {'zarr ms':>8} {'direct ms':>9} {'× zarr':>7}")
    source, key = 0, store.sources[0][1]
    for name, a in store._source_arrays(source).items():
        folder = store.path / "points" / key / name
        one = {}
        for way in ("zarr", "direct"):
            ts = []
            for _ in range(9):
                t0 = time.perf_counter()
                if way == "zarr":
                    with through_zarr():
                        read_chunk(a, folder, 0)
                else:
                    read_chunk(a, folder, 0)
                ts.append(time.perf_counter() - t0)
            one[way] = statistics.median(ts) * 1000
        mb = chunk_file(a, folder, 0).stat().st_size / 1e6
        print(
            f"{name:<16} {mb:>5.2f} {one['zarr']:>8.2f} {one['direct']:>9.2f} "
            f"{one['direct'] / one['zarr']:>7.2f}"
        )
    print(f"\n(python {sys.version.split()[0]}, one thread)")


if __name__ == "__main__":
    main()
