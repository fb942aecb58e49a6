"""``streetcd check``: a night's inputs checked in a second or two, before a run (which runs
the same check first: :func:`streetcd.run.check.check_inputs`)."""

from __future__ import annotations

import click

from streetcd.errors import StreetcdError


@click.command("check")
@click.option(
    "--images",
    required=True,
    type=click.Path(),
    help="Folder of the new images.",
)
@click.option(
    "--poses",
    required=True,
    type=click.Path(),
    help="Their poses: COLMAP images.txt/.bin (or its folder) or an OPK .csv.",
)
@click.option(
    "--store", required=True, type=click.Path(), help="Tile store (zarr) of the reference cloud."
)
@click.option(
    "--index",
    type=click.Path(dir_okay=False),
    help="Change index the run will write (its CRS must agree; it must not be in use).",
)
@click.option(
    "--config",
    "config_file",
    type=click.Path(exists=True, dir_okay=False),
    help="Settings (YAML): detect.max_range_m and run.max_image_pixels are used.",
)
def check(images: str, poses: str, store: str, index: str | None, config_file: str | None) -> None:
    """Check a night's inputs without running it: image sizes against the cameras, CRS of
    poses, store and index, poses against the store's extent, images without poses and
    poses without images, class codes. Reads image headers only.

    Exit code 0: the night can run (warnings name views that will fail alone); 2: it
    cannot, the one-line error says which file and field.
    """
    from streetcd.config import load_config
    from streetcd.run.check import check_inputs

    try:
        report = check_inputs(images, poses, store, index, load_config(config_file))
    except StreetcdError as exc:
        click.echo(f"Error: {exc}", err=True)
        raise click.exceptions.Exit(2) from None
    for note in report.notes:
        click.echo(f"note: {note}")
    for warning in report.warnings:
        click.echo(f"warning: {warning}")
    click.echo(
        f"ok: {len(report.image_names)} images, {len(report.pose_names)} poses, "
        f"CRS {report.crs or 'none (a local frame)'}; {len(report.warnings)} warning(s); "
        f"checked in {report.seconds:.2f} s"
    )
