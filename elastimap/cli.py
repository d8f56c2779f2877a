"""``elastimap``: the umbrella command; ``elastimap demo`` runs the main job on a small default.

The demo chains the real stages on a small problem, each through its own
command, so that a fresh machine shows the whole pipeline working:

1. ``solve``        one sample at the default mesh, PNG of its elasticity image;
2. ``sweep run``    a small design (plus the nine calibration phantoms) landing in Parquet;
3. ``dataset inspect`` / ``dataset plot``;
4. ``train``        an MLP with SCG (6 hidden neurons: the demo's sweep is too small for the
                   paper's 25-10 net), hold-out on the phantoms, a few repeats.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time

import click

from .cli_util import run
from .errors import UserError


def _step(title: str, argv: list[str]) -> None:
    click.secho(f"\n== {title}\n$ {' '.join(argv)}", bold=True)
    t0 = time.perf_counter()
    exe = shutil.which(argv[0], path=os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", ""))
    if exe is None:
        raise click.ClickException(f"command {argv[0]!r} not found next to {sys.executable}")
    r = subprocess.run([exe, *argv[1:]])
    if r.returncode != 0:
        raise click.ClickException(f"step failed ({title}), exit code {r.returncode}")
    click.echo(f"-- {time.perf_counter() - t0:.1f} s")


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def cli():
    """elastimap: simulate an elasticity-imaging sensor, learn the inverse map, apply it.

    Stage commands: solve, sweep, dataset, train, camera (calibrate, infer), gap.  Units: mm, kPa, mN.
    """


@cli.command()
@click.option("--out", default="out/demo", show_default=True, help="Output folder.")
@click.option("--n", type=int, default=40, show_default=True, help="Design samples in the demo sweep.")
@click.option("--mesh", default="coarse", show_default=True, help="Mesh level of the demo sweep.")
@click.option("--jobs", type=int, default=2, show_default=True, help="Sweep worker processes.")
def demo(out, n, mesh, jobs):
    """Run the pipeline on a small default: solve → sweep → inspect/plot → train."""
    if n < 1:
        raise UserError("--n", f"must be >= 1 (got {n})")
    os.makedirs(out, exist_ok=True)
    data = os.path.join(out, "data")
    _step("one forward solve (default mesh)", ["solve", "--d", "8", "--h", "7", "--E", "50",
                                                "--image", os.path.join(out, "solve-d8-h7-E50.png")])
    _step(f"sweep of {n} samples + 9 calibration phantoms ({mesh} mesh)",
          ["sweep", "run", "--n", str(n), "--jobs", str(jobs), "--mesh", mesh, "--phantoms", "--out", data])
    _step("inspect the dataset", ["dataset", "inspect", data])
    _step("plot the dataset", ["dataset", "plot", data, "--out", os.path.join(out, "figures")])
    # the paper's 25-10 net has 393 weights and needs >= 131 samples; the demo's small sweep
    # trains a 6-neuron net instead (workflows/paper_table.py runs the real thing)
    _step("train an MLP (SCG, hold-out on the phantoms; 6 hidden neurons for this small demo)",
          ["train", "--algo", "scg", "--validate", "hov", "--repeats", "3", "--hidden", "6", "--data", data,
           "--out", os.path.join(out, "train")])
    click.secho(f"\ndemo done: results in {out}/", bold=True)


def main(argv=None):
    run(cli, argv, prog_name="elastimap")
