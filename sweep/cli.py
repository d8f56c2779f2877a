"""``elastimap sweep`` (alias ``sweep``): run a batch of forward solves into a Parquet dataset.

    elastimap sweep run --n 512 --jobs 2                 # 512 LHS samples, default ranges, default mesh
    elastimap sweep run --n 64 --mesh tiny --phantoms    # + the nine calibration-phantom inclusions
    elastimap sweep run --samples table.csv --out sweeps/mine
    elastimap sweep bench --n 16 --mesh tiny             # samples/min at --jobs 1 and 2, driver overhead
    elastimap sweep bench --compare --n 64 --jobs-list 2 # the presses before vs as shipped, side by side
    elastimap sweep run --n 512 --moduli-per-mesh 8      # 64 geometries x 8 moduli: one mesh and factorisation each
    elastimap sweep bench --compare --paths separate,shared,morph --n 64 --jobs-list 2  # and morph/by_d
    elastimap sweep timeit --repeat 3 -- elastimap solve --d 8 --h 7 --E 50 --json  # any command, both presses

Rerunning the same command resumes: only samples with no landed row run.
"""

from __future__ import annotations

import sys

import click

from elastimap.cli_util import (
    CONTEXT_SETTINGS,
    Choice,
    geometry_option,
    jobs_option,
    mesh_option,
    options,
    out_option,
    param_flags,
    sizing_option,
)
from elastimap.cli_util import run as run_cli
from elastimap.solver.cli import sensor_option
from elastimap.solver.params import INTERFACES

from . import design as dsg


@click.group(context_settings=CONTEXT_SETTINGS)
def cli():
    """Batch sweeps of the forward model into Parquet datasets (see docs/sweep.md)."""


_common = options(
    click.option(
        "--n", "n", type=int, default=None, help="design samples (default 512; 0 with --samples unless given)"
    ),
    click.option("--seed", type=int, default=0, show_default=True, help="seed of the design"),
    mesh_option(),
    click.option(
        "--interface",
        type=Choice(INTERFACES),
        default=None,
        help="probe/tissue interface [default: the --sensor's, tied for the paper's]",
    ),
    click.option(
        "--design",
        type=Choice(dsg.DESIGNS),
        default="lhs",
        show_default=True,
        help="lhs (Latin hypercube) or sobol (scrambled)",
    ),
    click.option(
        "--moduli-per-mesh",
        type=int,
        default=1,
        show_default=True,
        help="K inclusion moduli per design geometry: n/K (d, h) points, each with one E in each of K strata "
        "of the E range; the K samples share one mesh and reference press (docs/sweep.md, 'What it samples')",
    ),
    click.option(
        "--ranges",
        default=None,
        help=f"NAME=LO:HI[:log] for d (mm), h (centre depth, mm or 'auto'), E (kPa); default {dsg.DEFAULT_RANGES}",
    ),
    click.option(
        "--samples",
        type=str,
        default=None,
        help="CSV/Parquet table of samples (columns d, h, E; optional sample_id, tissue_E, tissue_thickness)",
    ),
    click.option(
        "--phantoms", is_flag=True, help="add the nine calibration-phantom inclusions of dataset/phantoms.csv"
    ),
    # for tests and dry runs only (docs/sweep.md): 'synthetic[:KEY=VALUE,...]' runs the
    # SYNTHETIC stand-in of elastimap.solver.synthetic instead of the forward model
    click.option(
        "--solver",
        "solver_spec",
        default="fem",
        hidden=True,
        help="fem (the forward model) or synthetic[:KEY=VALUE,...] (the SYNTHETIC stand-in; tests and dry runs)",
    ),
)


@cli.command("run", context_settings=CONTEXT_SETTINGS)
@_common
@sensor_option(
    "sensor description (TOML; docs/howto/your-own-sensor.md) [default: the paper's]; recorded in OUT's "
    "manifest: one folder holds one sensor"
)
@jobs_option(default=2, help="local worker processes (one solve each)")
@out_option(help="dataset directory (default sweeps/<mesh>-<interface>-<design><n>-s<seed>)")
@geometry_option()
@sizing_option()
@click.option("--retry-failed", is_flag=True, help="run samples that landed as failed again")
@click.option(
    "--scheduler",
    type=str,
    default=None,
    help="address of a running dask scheduler (tcp://host:8786) instead of a local cluster",
)
@click.option(
    "--dashboard",
    type=str,
    default=None,
    metavar="HOST:PORT",
    help="serve the local cluster's dask dashboard (no login) at this address: 127.0.0.1:8787 on this "
    "machine only, :8787 on every interface (default: no dashboard)",
)
@click.option("--batch-rows", type=int, default=256, show_default=True, help="rows per merged batch file")
@click.option(
    "--timeout",
    type=float,
    default=1800.0,
    show_default=True,
    help="seconds one sample may take before it is recorded as failed and its worker restarted (0: no limit)",
)
@click.option("--no-progress", is_flag=True, help="no progress bar")
@click.option(
    "--append",
    is_flag=True,
    help="add this command's samples to an OUT that holds another design (recorded in its manifest)",
)
@click.option(
    "--break-lock",
    is_flag=True,
    help="remove OUT's lock left by a sweep that is gone (e.g. a cancelled job on another host)",
)
@click.option(
    "--connect-timeout", type=float, default=30.0, show_default=True, help="seconds --scheduler has to answer"
)
@click.option(
    "--worker-wait",
    type=float,
    default=60.0,
    show_default=True,
    help="seconds the run waits while the cluster has no worker, then ends with exit code 3",
)
def run_cmd(
    sensor_path,
    n,
    seed,
    mesh,
    interface,
    design,
    moduli_per_mesh,
    ranges,
    samples,
    phantoms,
    solver_spec,
    jobs,
    out,
    geometry,
    sizing,
    retry_failed,
    scheduler,
    dashboard,
    batch_rows,
    timeout,
    no_progress,
    append,
    break_lock,
    connect_timeout,
    worker_wait,
):
    """Run one solve per sample (resumable) and land the rows in OUT."""
    from elastimap.sensor import Sensor, load

    from .jobs import resolve_solver
    from .run import SweepConfig, format_summary, make_plan, run

    sensor = load(sensor_path) if sensor_path else Sensor()
    cfg = SweepConfig(
        n=n,
        jobs=jobs,
        seed=seed,
        out=out,
        mesh=mesh,
        interface=interface or sensor.interface.model,
        geometry=geometry,
        sizing=sizing,
        design=design,
        moduli_per_mesh=moduli_per_mesh,
        ranges=dsg.parse_ranges_text(ranges),
        samples=samples,
        phantoms=phantoms,
        retry_failed=retry_failed,
        scheduler=scheduler,
        dashboard=dashboard,
        batch_rows=batch_rows,
        timeout=timeout,
        progress=not no_progress,
        append=append,
        break_lock=break_lock,
        connect_timeout=connect_timeout,
        worker_wait=worker_wait,
        argv=sys.argv[1:],
        solver=resolve_solver(solver_spec),
        sensor=sensor if sensor_path else None,
    )
    plan = make_plan(cfg)
    try:
        summary = run(cfg, plan)
    except OSError as exc:  # a full or read-only disk under --out: the landed rows stay, the lock is gone
        from elastimap.errors import UserError

        raise UserError(
            "out",
            f"writing in {plan.out} failed ({exc.strerror or exc}); the rows landed so far are kept: "
            "free space and rerun the same command to resume",
        ) from None
    click.echo(format_summary(summary))
    if scheduler and jobs != 2:  # after the run: a scheduler that does not answer is then the one line
        click.echo("note: --jobs is ignored with --scheduler (the cluster decides the workers)", err=True)
    if summary.get("aborted"):
        click.echo(f"error: {summary['aborted']}", err=True)
        return 3
    if summary["interrupted"]:
        sig = summary.get("signal", "SIGINT")
        click.echo(f"interrupted by {sig}: landed rows are kept; rerun the same command to resume", err=True)
        return 143 if sig == "SIGTERM" else 130
    return 0


@param_flags({"jobs": "--jobs-list", "counts": "--jobs-list"})
@cli.command("bench", context_settings=CONTEXT_SETTINGS)
@_common
@click.option("--jobs-list", default="1,2", show_default=True, help="comma-separated worker counts to time")
@click.option(
    "--compare",
    is_flag=True,
    help="run each count once per path of --paths: the timings, the ratios to the first path and "
    "the feature deviations from it (docs/sweep.md, 'Benchmark')",
)
@click.option(
    "--paths",
    default="separate,shared",
    show_default=True,
    help="with --compare: comma-separated paths, the first the baseline; separate = each press factorised "
    "for itself (remesh, fixed sizing: the path before), shared = remesh/fixed as shipped, "
    "morph = geometry morph, sizing by_d, morph-fixed = geometry morph, sizing fixed",
)
@out_option(help="keep the datasets under OUT/jobs<k> (with --compare OUT/<path>-jobs<k>; default: a temporary dir)")
def bench_cmd(jobs_list, compare, paths, out, **common):
    """Time the same sweep at several --jobs: samples/min, speed-up, driver overhead per sample."""
    from .bench import bench, format_bench, format_compare, parse_paths
    from .bench import compare as compare_paths
    from .jobs import resolve_solver

    try:
        counts = [int(x) for x in jobs_list.split(",")]
    except ValueError:
        from elastimap.errors import UserError

        raise UserError("jobs_list", f"expected integers like 1,2 (got {jobs_list!r})") from None
    run_bench, show = (compare_paths, format_compare) if compare else (bench, format_bench)
    extra = {"paths": parse_paths(paths)} if compare else {}
    n = common.pop("n")  # the sweep's options (_common), as SweepConfig takes them
    common.update(
        n=16 if n is None and not common["samples"] else n,
        interface=common["interface"] or "tied",
        ranges=dsg.parse_ranges_text(common["ranges"]),
        solver=resolve_solver(common.pop("solver_spec")),
    )
    res = run_bench(counts, out=out, **common, **extra)
    click.echo(show(res))
    return 0


@cli.command(
    "timeit", context_settings={**CONTEXT_SETTINGS, "ignore_unknown_options": True, "allow_interspersed_args": False}
)
@click.option("--repeat", type=int, default=3, show_default=True, help="interleaved rounds (each path once a round)")
@click.option("--json", "as_json", is_flag=True, help="print the summary and every run as JSON")
@click.argument("command", nargs=-1, type=click.UNPROCESSED)
def timeit_cmd(repeat, as_json, command):
    """Time COMMAND (after '--') whole-process with ELASTIMAP_PRESSES=separate (the presses before)
    and =shared (as shipped), interleaved: median wall and CPU, peak memory, ratios, and the
    features' deviation when it prints JSON (docs/sweep.md, 'Benchmark')."""
    import json

    from .timeit import report, timeit

    res = timeit(list(command), repeat=repeat)
    click.echo(json.dumps(res, indent=1) if as_json else report(res))
    return 0


def main(argv: list[str] | None = None) -> None:
    run_cli(cli, argv, prog_name="sweep")


if __name__ == "__main__":
    main()
