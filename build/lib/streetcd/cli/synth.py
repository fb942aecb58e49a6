"""``streetcd synth``: generate a synthetic street (or small city) with ground truth."""

from __future__ import annotations

import json
import time
from pathlib import Path

import click

from streetcd.synth.kinds import PATHS, PRESET_HELP, PRESETS, SCHEMES, UNCLASSIFIED


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


def _density(
    ctx: click.Context, param: click.Parameter, value: str | None
) -> tuple[float | None, float | None]:
    """``F`` (a fraction of the points) or ``Sm`` (a point spacing at 10 m, metres)."""
    if value is None:
        return None, None
    text = value.strip().lower()
    try:
        if text.endswith("m"):
            return None, float(text[:-1])
        return float(text), None
    except ValueError:
        raise click.BadParameter(
            f"expected a fraction such as 0.1 or a spacing such as 0.3m, got {value!r}"
        ) from None


_KINDS_EPILOG = "\b\nKinds (--kind NAME; explicit options override the preset's):\n" + "\n".join(
    f"  {name:<16} {PRESET_HELP[name]}" for name in PRESETS
)


@click.command("synth", epilog=_KINDS_EPILOG)
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
@click.option(
    "--kind",
    type=click.Choice(list(PRESETS)),
    help="A named street kind (listed below). [default: default]",
)
@click.option(
    "--path",
    "camera_path",
    type=click.Choice(list(PATHS)),
    help="Camera path: today's strip (vehicle) or a pedestrian on the near (right) or far "
    "(left) sidewalk. [default: vehicle]",
)
@click.option(
    "--plain/--textured",
    default=None,
    help="Uniformly painted objects, some ~1 m in front of plain walls. [default: textured]",
)
@click.option(
    "--colour/--no-colour",
    default=None,
    help="Write the cloud with RGB (LAS format 7) or without (format 6). [default: colour]",
)
@click.option(
    "--density",
    callback=_density,
    help="Sparser cloud: a fraction of the points (0.1 keeps a tenth) or a point spacing at "
    "10 m range such as 0.3m (a coarser scanner).",
)
@click.option(
    "--class-codes",
    help=f"Coding of the cloud's classes: {', '.join([*SCHEMES, UNCLASSIFIED])}, or a YAML "
    "file with detect: classes:. Writes DIR/streetcd.yaml, the class map to pass as "
    "--config. [default: streetcd's codes, no file]",
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
    kind: str | None,
    camera_path: str | None,
    plain: bool | None,
    colour: bool | None,
    density: tuple[float | None, float | None],
    class_codes: str | None,
) -> None:
    """Generate an epoch-1 MLS archive, epoch-2 posed images and change ground truth."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from streetcd.errors import StreetcdError
    from streetcd.synth import generate_city, generate_street
    from streetcd.synth.kinds import resolve_kind

    fraction, spacing = density
    try:
        street_kind = resolve_kind(
            kind,
            path=camera_path,
            plain=plain,
            colour=colour,
            density=fraction,
            point_spacing_m=spacing,
            class_codes=class_codes,
        )
    except StreetcdError as exc:
        raise click.ClickException(str(exc)) from None
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
                kind=street_kind,
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
                kind=street_kind,
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
    if m.get("class_codes", {}).get("config"):
        console.print(f"class map: pass --config {out_dir / m['class_codes']['config']}")
