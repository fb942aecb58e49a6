"""``streetcd detect``: one view against the reference cloud, mask + overlay + JSON summary.

streetcd detect --cloud FILE [FILE ...] --poses POSES --images DIR --view NAME
                [--neighbours NAME,NAME] [--config YAML] --out DIR
"""

from __future__ import annotations

import time
from pathlib import Path

import click

from streetcd.errors import StreetcdError

USAGE = (
    "--cloud FILE [FILE ...] --poses POSES --images DIR --view NAME "
    "[--neighbours NAME,NAME] [--config YAML] --out DIR"
)


class _DetectCommand(click.Command):
    """Shows ``--cloud FILE [FILE ...]`` in the usage line: files after the first one are
    collected as extra arguments (click options take a fixed number of values)."""

    def collect_usage_pieces(self, ctx: click.Context) -> list[str]:
        return [USAGE]


@click.command("detect", cls=_DetectCommand)
@click.option(
    "--cloud",
    "clouds",
    multiple=True,
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Reference LAS/LAZ file(s): --cloud A.laz B.laz … (several files share one local frame).",
)
@click.argument(
    "more_clouds", nargs=-1, type=click.Path(dir_okay=False, path_type=Path), metavar=""
)
@click.option(
    "--poses",
    required=True,
    type=click.Path(path_type=Path),
    help="COLMAP images.txt (cameras.txt beside it), images.bin, or an OPK CSV.",
)
@click.option(
    "--images",
    "image_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Folder of the images.",
)
@click.option("--view", "view_name", required=True, help="Image name (or stem) to check.")
@click.option(
    "--neighbours",
    default=None,
    help="Comma-separated neighbour views; default: the best-overlapping ones.",
)
@click.option(
    "--config",
    "--params",
    "params_path",
    default=None,
    type=click.Path(path_type=Path),
    help="Settings YAML (configs/default.yaml layout; its detect: block is used); default: the defaults.",
)
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Output folder.",
)
def detect(
    clouds: tuple[Path, ...],
    more_clouds: tuple[Path, ...],
    poses: Path,
    image_dir: Path,
    view_name: str,
    neighbours: str | None,
    params_path: Path | None,
    out_dir: Path,
) -> None:
    """Detect changes in one view: writes OUT/<stem>.mask.png, .overlay.jpg and .json."""
    from streetcd.config import load_config
    from streetcd.io.las import load_clouds
    from streetcd.io.outputs import summary, write_outputs
    from streetcd.io.poses import read_poses
    from streetcd.run.single import detect_files

    t0 = time.perf_counter()
    try:
        params = load_config(params_path).detect
        pose_set = read_poses(poses, image_dir)
        cloud = load_clouds([*clouds, *more_clouds])
        t_load = time.perf_counter() - t0
        names = (
            None if neighbours is None else [n.strip() for n in neighbours.split(",") if n.strip()]
        )
        result, view, image = detect_files(view_name, pose_set, image_dir, cloud, params, names)
        result.timings["load_inputs"] = t_load
        result.timings["total"] = time.perf_counter() - t0
        paths = write_outputs(result, view, image, out_dir)
    except StreetcdError as exc:
        raise click.ClickException(
            f"view {view_name!r}: {exc}" if view_name not in str(exc) else str(exc)
        ) from None
    info = summary(result, view)
    click.echo(
        f"{view.name}: score {info['score']:.3f}, changed {100 * result.changed_fraction:.2f} %"
        f", {len(result.regions)} region(s), neighbours {', '.join(result.neighbours) or '-'}"
        f" → {paths['mask']}"
    )
