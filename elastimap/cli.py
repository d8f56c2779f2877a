"""``elastimap``: the one command; every stage is a subcommand, imported only when it runs.

    elastimap solve --d 8 --h 7 --E 50          one forward sample
    elastimap sweep run --n 512 --jobs 2        a design of solves into Parquet
    elastimap dataset inspect DIR               look at / plot / export a dataset
    elastimap train --algo lm --validate loocv  the inverse MLP
    elastimap camera calibrate|infer|...        the camera side
    elastimap gap diagnose ...                  sim-to-real diagnosis
    elastimap study crbmap ...                  the studies (maps, image model, intervals)
    elastimap demo                              the whole pipeline on a small default

The stage commands are also installed under their own names (``solve``, ``sweep``,
``dataset``, ``train``, ``camera``, ``calibrate``, ``infer``, ``gap``): the same click
objects, so flags, help and errors are identical.

``elastimap demo`` chains the real stages on a small problem, each through its own
subcommand, so that a fresh machine shows the whole pipeline working:

1. ``solve``        one sample at the default mesh, PNG of its elasticity image;
2. ``sweep run``    a small design (plus the nine calibration phantoms) landing in Parquet;
3. ``dataset inspect`` / ``dataset plot``;
4. ``train``        an MLP with SCG (6 hidden neurons: the demo's sweep is too small for the
                   paper's 25-10 net), hold-out on the phantoms, a few repeats.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import click

from .cli_util import CONTEXT_SETTINGS, LazyGroup, mesh_option, out_option, run
from .errors import UserError

#: The stages: subcommand -> ("module:attr" of its click object, the line ``elastimap --help`` shows).
STAGES = {
    "solve": ("elastimap.solver.cli:cli", "One forward solve: features, force and image of one inclusion."),
    "sweep": ("elastimap.sweep.cli:cli", "Batch sweeps of the forward model into Parquet datasets."),
    "dataset": ("elastimap.dataset.cli:cli", "Inspect, plot, export and compact sample datasets."),
    "train": ("elastimap.training.cli:cli", "Train and validate the inverse MLP (LM/SCG, HOV/LOOCV)."),
    "camera": ("elastimap.camera.cli:cli", "Camera side: synthetic frames, features, calibrate, infer, detect."),
    "gap": ("elastimap.gap.cli:cli", "Sim-to-real gap diagnosis (synth, diagnose, selftest)."),
}


class StudyGroup(LazyGroup):
    """``elastimap study``: its subcommands are the one registry of studies
    (:data:`elastimap.workflows.studies.STUDIES`), read when the group first lists or runs one."""

    @property
    def lazy(self) -> dict[str, tuple[str, str]]:
        from elastimap.workflows.studies import command_specs

        return command_specs()

    @lazy.setter
    def lazy(self, value) -> None:  # LazyGroup.__init__ assigns it; the registry is the only source
        pass


@click.group(cls=LazyGroup, lazy=STAGES, context_settings=CONTEXT_SETTINGS)
@click.version_option(package_name="elastimap", message="%(prog)s %(version)s")
def cli():
    """elastimap: simulate an elasticity-imaging sensor, learn the inverse map, apply it.

    Every stage is a subcommand (`elastimap STAGE -h` for its options); the stages are also
    installed as commands of their own (solve, sweep, dataset, train, camera, calibrate,
    infer, gap).  Units: mm, kPa, mN.
    """


@cli.group(
    cls=StudyGroup,
    context_settings=CONTEXT_SETTINGS,
    short_help="The studies behind the shipped map, model and intervals (crbmap, image_model, ...).",
)
def study():
    """The studies: how the shipped identifiability map, the deployed image model, the calibrated
    intervals and the docs' tables were made (each also runs as python -m
    elastimap.workflows.studies.NAME)."""


def _step(title: str, argv: list[str]) -> None:
    """Run ``elastimap ARGV`` in a fresh process (each stage as a user would run it)."""
    click.secho(f"\n== {title}\n$ elastimap {' '.join(argv)}", bold=True)
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "elastimap.cli", *argv])
    if r.returncode != 0:
        raise click.ClickException(f"step failed ({title}), exit code {r.returncode}")
    click.echo(f"-- {time.perf_counter() - t0:.1f} s")


@cli.command(context_settings=CONTEXT_SETTINGS, short_help="The whole pipeline on a small default (make demo).")
@out_option(help="Output folder.", default="out/demo")
@click.option("--n", type=int, default=40, show_default=True, help="Design samples in the demo sweep.")
@mesh_option(default="coarse", help="Mesh level of the demo sweep.")
@click.option("--jobs", type=int, default=2, show_default=True, help="Sweep worker processes.")
@click.option(
    "--sensor",
    "sensor_path",
    type=click.Path(dir_okay=False),
    default=None,
    help="Sensor description (TOML; docs/howto/your-own-sensor.md) the solve and the sweep use [default: the paper's].",
)
def demo(out, n, mesh, jobs, sensor_path):
    """Run the pipeline on a small default: solve → sweep → inspect/plot → train."""
    from .outputs import check_out_dir
    from .sensor import load

    sensor = ["--sensor", os.path.abspath(sensor_path)] if sensor_path else []
    if sensor_path:
        load(sensor_path)  # a bad description: one line, before anything runs

    # the training step's net (3 -> DEMO_HIDDEN -> 3) needs one design sample per 3 weights
    min_n = ((3 + 1) * DEMO_HIDDEN + (DEMO_HIDDEN + 1) * 3) // 3
    if n < min_n:
        raise UserError("n", f"must be >= {min_n}: the demo trains a {DEMO_HIDDEN}-neuron net on the sweep (got {n})")
    check_out_dir(out, "out", allow_existing=True)  # the demo resumes in its folder ...
    _check_demo_folder(out)  # ... and only there
    data = os.path.join(out, "data")
    from elastimap.sweep.run import SweepConfig, make_plan

    # the sweep step's settings and folder, checked before the first step (--jobs 99999 failed after a solve)
    make_plan(SweepConfig(n=n, jobs=jobs, mesh=mesh, phantoms=True, out=data).validate())
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, DEMO_MARK), "w") as fh:
        json.dump({"kind": "elastimap.demo", "note": "made by elastimap demo; a rerun resumes here"}, fh)
        fh.write("\n")
    _step(
        "one forward solve (default mesh)",
        ["solve", *sensor, "--d", "8", "--h", "7", "--E", "50", "--image", os.path.join(out, "solve-d8-h7-E50.png")],
    )
    _step(
        f"sweep of {n} samples + 9 calibration phantoms ({mesh} mesh)",
        ["sweep", "run", *sensor, "--n", str(n), "--jobs", str(jobs), "--mesh", mesh, "--phantoms", "--out", data],
    )
    _step("inspect the dataset", ["dataset", "inspect", data])
    _step("plot the dataset", ["dataset", "plot", data, "--out", os.path.join(out, "figures")])
    # the paper's 25-10 net has 393 weights and needs >= 131 samples; the demo's small sweep
    # trains a 6-neuron net instead (workflows/paper_table.py runs the real thing)
    _step(
        "train an MLP (SCG, hold-out on the phantoms; 6 hidden neurons for this small demo)",
        [
            "train",
            "--algo",
            "scg",
            "--validate",
            "hov",
            "--repeats",
            "3",
            "--hidden",
            str(DEMO_HIDDEN),
            "--data",
            data,
            "--out",
            os.path.join(out, "train"),
            "--overwrite",
        ],
    )  # a rerun of the demo replaces its run
    click.secho(f"\ndemo done: results in {out}/", bold=True)


DEMO_MARK = "demo.json"
DEMO_HIDDEN = 6  # hidden neurons of the demo's net (the paper's 25-10 net needs >= 131 samples)


def _check_demo_folder(out: str) -> None:
    """An existing ``--out`` must be an earlier demo's folder (it holds ``demo.json``): the demo
    replaces its ``train`` folder and adds to its ``data`` sweep, which must never be the user's."""
    if os.path.isdir(out) and any(os.scandir(out)) and not os.path.isfile(os.path.join(out, DEMO_MARK)):
        raise UserError(
            "out",
            f"{out} holds files but is not an earlier demo's folder (no {DEMO_MARK}); the demo replaces "
            "its train/ and adds to its data/, so it only reruns in its own folder (choose another)",
        )


def main(argv=None):
    run(cli, argv, prog_name="elastimap")


if __name__ == "__main__":
    main()
