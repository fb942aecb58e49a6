"""``streetcd synth``: generate a synthetic street (or small city) with ground truth."""

from __future__ import annotations

import json
import time
from pathlib import Path

import click


def _size(ctx: click.Context, param: click.Parameter, value: str | None) -> tuple[int, int] | None:
    if value is None:
        return None
    try:
        w, h = (int(x) for x in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(
            f"expected WIDTHxHEIGHT such as 1920x1080, got {value!r}"
        ) from None
    if w < 16 or h < 16:
        raise click.BadParameter(f"image size must be at least 16x16, got {value!r}")
    return w, h


@click.command("synth")
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Folder to write (created if missing).",
)
@click.option("--seed", default=0, show_default=True, type=int, help="Random seed.")
@click.option(
    "--images",
    "n_images",
    default=None,
    type=click.IntRange(min=1),
    help="Images (per street with --city). [default: 24, or 8 per street]",
)
@click.option(
    "--size",
    default=None,
    callback=_size,
    help="Image size WIDTHxHEIGHT. [default: 1920x1080, or 960x540 with --city]",
)
@click.option(
    "--pose-noise-px",
    default=0.0,
    show_default=True,
    type=click.FloatRange(min=0),
    help="RMS reprojection error added to the written poses, pixels.",
)
@click.option(
    "--length",
    "length_m",
    default=None,
    type=click.FloatRange(30, 1000),
    help="Street length in metres. [default: 150, or 50 per street with --city]",
)
@click.option("--no-changes", is_flag=True, help="Epoch 2 identical to epoch 1 (no disturbances).")
@click.option("--city", is_flag=True, help="A small city of several streets (nightly demo).")
@click.option(
    "--streets",
    "n_streets",
    default=3,
    show_default=True,
    type=click.IntRange(min=1),
    help="Streets in the city (with --city).",
)
def synth(
    out_dir: Path,
    seed: int,
    n_images: int | None,
    size: tuple[int, int] | None,
    pose_noise_px: float,
    length_m: float | None,
    no_changes: bool,
    city: bool,
    n_streets: int,
) -> None:
    """Generate an epoch-1 MLS archive, epoch-2 posed images and change ground truth."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from streetcd.synth import generate_city, generate_street

    console = Console()
    start = time.perf_counter()
    with Progress(
        TextColumn("[bold]synth[/]"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task("synth", total=None)

        def progress(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        if city:
            manifest_path = generate_city(
                out_dir,
                seed=seed,
                n_streets=n_streets,
                images_per_street=n_images or 8,
                size=size or (960, 540),
                pose_noise_px=pose_noise_px,
                length_m=length_m or 50.0,
                changes=not no_changes,
                progress=progress,
            )
        else:
            manifest_path = generate_street(
                out_dir,
                seed=seed,
                n_images=n_images or 24,
                size=size or (1920, 1080),
                pose_noise_px=pose_noise_px,
                length_m=length_m or 150.0,
                changes=not no_changes,
                progress=progress,
            )
    seconds = time.perf_counter() - start
    m = json.loads(manifest_path.read_text(encoding="utf-8"))
    changed_views = sum(1 for v in m["views"] if v["changed_instances"])
    console.print(
        f"[green]wrote[/] {out_dir}: {m['scan']['n_points']:,} points in "
        f"{len(m['files']['cloud'])} LAZ files, {m['images']['count']} images "
        f"{m['images']['width']}x{m['images']['height']}, {len(m['changes'])} changes "
        f"(seen in {changed_views} images), pose noise {m['pose_noise']['achieved_rms_px']:.2f} px "
        f"RMS, {seconds:.1f} s"
    )
