"""``elastimap dataset`` (alias ``dataset``): look at, plot, export and compact sample datasets.

elastimap dataset inspect sweeps/default-tied-lhs512-s0
elastimap dataset plot sweeps/default-tied-lhs512-s0 --out figs/
elastimap dataset export sweeps/default-tied-lhs512-s0 --out table.csv
elastimap dataset compact sweeps/default-tied-lhs512-s0
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import click

from elastimap.cli_util import CONTEXT_SETTINGS, Choice, out_option, param_flags
from elastimap.cli_util import run as run_cli
from elastimap.errors import UserError


@click.group(context_settings=CONTEXT_SETTINGS)
def cli():
    """Sample datasets landed by `sweep run` (see docs/dataset.md)."""


@cli.command("inspect")
@click.argument("path")
@click.option("--json", "as_json", is_flag=True, help="print the report as JSON")
@click.option("--top", default=5, show_default=True, help="how many slowest samples / failures to list")
def inspect_cmd(path, as_json, top):
    """Schema, counts by status, parameter/feature ranges, NaN check, slowest samples, failures."""
    from .inspect import format_report, report

    rep = report(path, top=top)
    click.echo(json.dumps(rep, indent=1, default=str) if as_json else format_report(rep))
    return 0


@param_flags({"n_images": "--n-images", "out_dir": "--out"})
@cli.command("plot")
@click.argument("path")
@out_option(required=True, help="directory for the PNG figures")
@click.option("--n-images", "images", default=12, show_default=True, help="example images in the grid of images.png")
def plot_cmd(path, out, images):
    """PNG figures: the paper's 3-D scatter per feature, features vs parameters, example images."""
    from elastimap.outputs import check_inputs_kept

    from .plot import plot_all

    check_inputs_kept(out, "--out", PATH=path)  # figures never land among the data
    for f in plot_all(path, out, n_images=images):
        click.echo(str(f))
    return 0


@cli.command("export")
@click.argument("path")
@out_option(help="CSV file to write (default: <PATH>.csv next to the dataset); '-' for stdout")
@click.option(
    "--status",
    type=Choice(["ok", "failed", "all"]),
    default="all",
    show_default=True,
    help="Which samples to write: the solved ones, the failed ones or all.",
)
@click.option(
    "--image-column/--no-image-column",
    "images",
    default=False,
    show_default=True,
    help="include the elasticity image as one column of space-separated values (mm)",
)
def export_cmd(path, out, status, images):
    """One CSV table for spreadsheets (one row per sample, parameters, features, status, statistics)."""
    from elastimap.outputs import check_out_file

    from . import io

    src = Path(path).resolve()
    target = out or str(src.with_suffix(".csv") if src.is_file() else src.with_name(src.name + ".csv"))
    if target != "-":
        check_out_file(target, "--out", inputs={"PATH": path})  # before reading
    df = io.read_samples(path, status=None if status == "all" else status)
    if images:
        df["image"] = [" ".join(f"{x:.6g}" for x in v) if v is not None else "" for v in df["image"]]
    else:
        df = df.drop(columns=["image"])
    if target == "-":
        click.echo(df.to_csv(index=False), nl=False)
        return 0
    from elastimap.outputs import write_or_fallback

    t = write_or_fallback(lambda f: df.to_csv(f, index=False), target, "--out")
    click.echo(f"wrote {len(df)} rows to {t}")
    return 0


@cli.command("compact")
@click.argument("path")
@click.option("--batch-rows", default=256, show_default=True, help="rows per batch file")
def compact_cmd(path, batch_rows):
    """Merge a dataset's files into batch files, dropping superseded rows (safe to interrupt)."""
    from . import io

    if not Path(path).is_dir():
        raise UserError("path", f"{path} is not a dataset directory")
    if batch_rows < 1:
        raise UserError("--batch-rows", f"must be >= 1 (got {batch_rows})")
    if not os.access(path, os.W_OK | os.X_OK):
        raise UserError("path", f"cannot compact {path}: no write permission (the dataset is unchanged)")
    try:
        lock = io.acquire_lock(path, param="path")
        try:
            r = io.compact(path, batch_rows)
        finally:
            lock.unlink(missing_ok=True)
    except OSError as exc:  # read-only or full file system: compaction is safe to interrupt
        raise UserError("path", f"cannot compact {path} ({exc.strerror or exc}); its rows are unchanged") from None
    click.echo(
        f"{path}: {r['files_before']} files -> {r['files_after']}, {r['rows']} rows, "
        f"{r['dropped']} superseded rows dropped"
    )
    return 0


def main(argv: list[str] | None = None) -> None:
    run_cli(cli, argv, prog_name="dataset")


if __name__ == "__main__":
    main()
