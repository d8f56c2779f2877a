"""``elastimap gap`` (alias ``gap``): synth, diagnose, selftest, bench, effects (docs/gap.md, 'Usage').

    elastimap gap synth --out M --effect friction=0.3 [--mesh tiny] [--n 12]
    elastimap gap diagnose --measured M --out DIR [--effects a,b] [--no-inverse] [--error-mesh default]
    elastimap gap selftest --trials 30 --out DIR [--mesh tiny] [--data-mesh coarse] [--data-interface contact]
                           [--data-sizing by_d]
    elastimap gap bench [--n 12] [--mesh coarse] [--out bench.json]
    elastimap gap effects

User errors print one ``error:`` line and exit 2.  Solves are cached under ``--cache``
(default ``$ELASTIMAP_GAP_CACHE`` or ``~/.cache/elastimap/gap``); ``--no-progress`` silences the
solve progress.  The library modules (numpy, scipy, matplotlib, torch) are imported inside the
commands, so that ``--help`` starts fast.
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

import click

from elastimap.cli_util import CONTEXT_SETTINGS, jobs_option, mesh_option, options, param_flags
from elastimap.cli_util import run as run_cli
from elastimap.constraints import Interval, validate_params
from elastimap.dataset.phantoms import read_phantoms
from elastimap.errors import UserError
from elastimap.outputs import check_out_dir, check_out_file, write_dir
from elastimap.sensor import Sensor
from elastimap.sensor import load as load_sensor
from elastimap.solver.cli import sensor_option

from . import effects as fx
from .adopt import ADOPTED
from .settings import FINER, Settings


def default_cache() -> str:
    return os.environ.get("ELASTIMAP_GAP_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "elastimap", "gap")


def _sim(cache, mesh, backend, jobs, no_progress):
    from elastimap.sweep.run import MAX_JOBS

    from .simulate import Simulator

    validate_params({"jobs": jobs}, {"jobs": [Interval(int, 1, MAX_JOBS)]})
    if cache != "none":
        check_out_dir(cache, "cache", allow_existing=True)  # a file or a folder we cannot write: before any solve

    def prog(i, n):
        if not no_progress:
            click.echo(f"\rsolves {i}/{n}", nl=(i == n), err=True)

    return Simulator(None if cache == "none" else os.path.join(cache, f"{backend}-{mesh}"), mesh, backend, jobs, prog)


common = options(
    click.option(
        "--cache",
        default=None,
        help="Solve cache folder ('none' = no cache; default $ELASTIMAP_GAP_CACHE or ~/.cache/elastimap/gap).",
    ),
    click.option(
        "--backend",
        type=click.Choice(["fem", "toy"]),
        default="fem",
        show_default=True,
        help="fem = DOLFINx forward model; toy = analytic TOY stand-in (tests only).",
    ),
    jobs_option(default=1, help="Worker processes for missing solves."),
    click.option("--no-progress", is_flag=True, help="Print no solve progress (stderr)."),
)


@click.group(context_settings=CONTEXT_SETTINGS)
def cli():
    """Sim-to-real gap diagnosis.  Synthetic data are labelled SYNTHETIC."""


@cli.command("effects", context_settings=CONTEXT_SETTINGS)
def effects_cmd():
    """List the effects library."""
    for e in fx.EFFECTS.values():
        click.echo(
            f"{e.name:14s} {e.stage:9s} nominal {e.nominal:g} {e.unit}; grid {list(e.grid)}; "
            f"blind {list(e.blind)}  {e.description}" + ("  [SYNTHETIC data only]" if e.name in fx.OUTSIDE_ONLY else "")
        )
    for f in fx.FAMILIES.values():
        click.echo(f"{f.name:14s} family    k = {f.n_params}: {', '.join(f.members)}  {f.description}")


@cli.command("synth", context_settings=CONTEXT_SETTINGS)
@click.option(
    "--out",
    required=True,
    type=click.Path(file_okay=False),
    help="New folder for the SYNTHETIC measured dataset (an existing one only with --overwrite).",
)
@click.option(
    "--overwrite",
    is_flag=True,
    help="Replace an earlier SYNTHETIC dataset in --out (real measured data is never replaced).",
)
@sensor_option("The lab's sensor description (TOML; docs/howto/your-own-sensor.md) [default: the paper's].")
@click.option(
    "--effect",
    "effect",
    default="",
    help="NAME=MAGNITUDE[,NAME=MAGNITUDE] on top of the --sensor (empty: baseline only).",
)
@click.option(
    "--phantoms", type=click.Path(), default=None, help="CSV with id (or name), d, h, E (default: an LHS design)."
)
@click.option(
    "--n", "n", type=int, default=12, show_default=True, help="Phantoms of the LHS design (ignored with --phantoms)."
)
@mesh_option(default="coarse", help="Mesh level of the data's forward model (tiny is for tests only).")
@click.option("--frames", type=int, default=10, show_default=True, help="Camera frames per phantom (and background).")
@click.option("--noise-scale", type=float, default=1.0, show_default=True, help="Multiplies the camera's frame noise.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seeds the phantom design and the frame noise.")
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["csv", "parquet"]),
    default="csv",
    show_default=True,
    help="File format of the measured table.",
)
@click.option(
    "--interface",
    type=click.Choice(["tied", "contact", "bonded"]),
    default=None,
    help="Probe-tissue interface of the data's forward model [default: the --sensor's, tied].",
)
@click.option(
    "--force-noise", type=float, default=None, help="Also 'measure' the plate force with this relative error."
)
@click.option(
    "--label-phantom",
    default=None,
    help="Id of the phantom whose table entry a label effect (mislabel_d/h/E) changes [default: the first].",
)
@common
def synth_cmd(
    out,
    overwrite,
    sensor_path,
    effect,
    phantoms,
    n,
    mesh,
    frames,
    noise_scale,
    seed,
    fmt,
    interface,
    force_noise,
    label_phantom,
    cache,
    backend,
    jobs,
    no_progress,
):
    """Generate a SYNTHETIC measured dataset (truth sealed in SEALED_truth.json)."""
    from . import measured, synth

    synth.check_out(out, overwrite)
    sensor = load_sensor(sensor_path) if sensor_path else None
    effs = fx.parse_spec(effect, table=fx.for_sensor(sensor or Sensor())) if effect else []
    base_interface = (sensor or Sensor()).interface.model
    if frames < 1:
        raise UserError("frames", f"must be >= 1 (got {frames})")
    ids = None
    if phantoms:
        table = read_phantoms(phantoms, min_rows=4, why="for a diagnosis")
        dhe, ids = table[["d", "h", "E"]].to_numpy(float), list(table["name"])
    else:
        if n < 4:
            raise UserError("n", f"need at least 4 phantoms (got {n})")
        dhe = synth.phantom_design(n, seed)
    names = ids or [f"P{i + 1:02d}" for i in range(len(dhe))]
    if label_phantom is not None and label_phantom not in names:
        raise UserError("label-phantom", f"{label_phantom!r} is not a phantom id (ids: {', '.join(names[:5])}, ...)")
    if label_phantom is not None and not any(e.stage == "label" for e, _ in effs):
        raise UserError("label-phantom", "needs a label effect in --effect (mislabel_d, mislabel_h, mislabel_E)")
    sim = _sim(cache or default_cache(), mesh, backend, jobs, no_progress)
    if force_noise is not None and not force_noise > 0:
        raise UserError("force-noise", "must be > 0")
    meas, truth = synth.synthesize(
        dhe,
        effs,
        sim,
        frames=frames,
        seed=seed,
        ids=ids,
        noise_scale=noise_scale,
        disc={"interface": interface} if interface and interface != base_interface else None,
        force_noise=force_noise,
        description=sensor,
        label_phantom=0 if label_phantom is None else names.index(label_phantom),
    )

    def _write(folder):
        measured.write(meas, folder, fmt)
        synth.seal(truth, folder)

    write_dir(out, _write, "out", overwrite=overwrite)  # whole; on a full disk the set goes to $TMPDIR
    tp = Path(out) / ("measured.parquet" if fmt == "parquet" else "measured.csv")
    click.echo(f"SYNTHETIC measured data: {tp} ({meas.n} phantoms, truth sealed in {Path(out) / measured.SEALED})")
    return 0


@param_flags({"effect": "--effects"})
@cli.command("diagnose", context_settings=CONTEXT_SETTINGS)
@click.option(
    "--measured",
    "mpath",
    required=True,
    type=click.Path(),
    help="Measured dataset: a folder (or its table) as written by 'gap synth' (docs/gap.md, 'Measured-data format').",
)
@click.option(
    "--out",
    required=True,
    type=click.Path(file_okay=False),
    help="Folder for report.md, report.html, diagnosis.json and the PNG figures.",
)
@sensor_option(
    "The sensor the phantoms were pressed with (TOML; docs/howto/your-own-sensor.md) [default: the measured "
    f"set's, else the paper's]; the diagnosis writes it with the identified effect(s) as OUT/{ADOPTED}."
)
@click.option("--effects", default=None, help="Comma-separated candidate effects (default: all but offaxis).")
@mesh_option(default=None, help="Mesh level of the diagnosis (default: the measured sidecar's).")
@click.option("--no-inverse", is_flag=True, help="Skip the (d, h, E) retraining step.")
@click.option("--n-train", type=int, default=40, show_default=True, help="Simulations per inverse training set.")
@click.option(
    "--error-mesh",
    default=None,
    help="Finer mesh level for the measured model error (default: the next finer level; 'none': assumed floor).",
)
@click.option(
    "--model-floor",
    type=float,
    default=0.005,
    show_default=True,
    help="Relative model error used only with --error-mesh none.",
)
@click.option("--alpha", type=float, default=0.01, show_default=True, help="Level of the calibrated chi-square tests.")
@click.option(
    "--model-form",
    type=click.Choice(["prior", "none"]),
    default="prior",
    show_default=True,
    help="Model-form level in the decision: 'prior' = identify.discrepancy's prior scales (2 % amplitude "
    "and width of each phantom's bump, 1 % smooth remainder; docs/gap.md, 'Model-form level'); "
    "'none' = noise and discretisation only (the closed world).",
)
@click.option(
    "--seed",
    type=int,
    default=0,
    show_default=True,
    help="Seeds the folds, the bootstrap, the proposed phantoms and the inverse training.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON (stdout).")
@click.option(
    "--allow-outside", is_flag=True, help="Let --measured's table name files outside its folder (absolute paths, '..')."
)
@common
def diagnose_cmd(
    mpath,
    out,
    sensor_path,
    effects,
    mesh,
    no_inverse,
    n_train,
    error_mesh,
    model_floor,
    alpha,
    model_form,
    seed,
    as_json,
    allow_outside,
    cache,
    backend,
    jobs,
    no_progress,
):
    """Diagnose the sim-to-real gap of a measured dataset: report.md, PNG figures, diagnosis.json."""
    from elastimap.provenance import stamp
    from elastimap.sensor import dumps

    from . import adopt, measured, report
    from .diagnose import diagnose

    if not 0 < alpha < 0.5:
        raise UserError("alpha", "must be in (0, 0.5)")
    if not (math.isfinite(model_floor) and model_floor >= 0):
        raise UserError("model_floor", f"must be a finite number >= 0 (got {model_floor:g})")
    if n_train < 2:
        raise UserError("n_train", f"must be >= 2 (got {n_train})")
    if seed < 0:
        raise UserError("seed", f"must be an integer >= 0 (got {seed})")
    check_out_dir(out, "out", allow_existing=True)
    report.check_out(out)
    meas = measured.load(mpath, load_sensor(sensor_path) if sensor_path else None, allow_outside=allow_outside)
    sensor = meas.sensor_description or Sensor().replace(camera=meas.sensor_model().spec())
    if effects is not None and not effects.strip():
        raise UserError("--effects", "name at least one effect (leave --effects out for the default candidates)")
    cands = fx.parse_list(effects, table=fx.for_sensor(sensor))
    st = Settings(
        model_floor=model_floor,
        alpha=alpha,
        seed=seed,
        inverse=not no_inverse,
        n_train=n_train,
        model_form=model_form == "prior",
    )
    sim = _sim(cache or default_cache(), mesh or meas.mesh, backend, jobs, no_progress)
    fine = error_mesh_sim(error_mesh, sim, cache, backend, jobs, no_progress)
    res = diagnose(meas, cands, sim, st, fine)
    adoption, note = adopt.from_diagnosis(res, sensor)
    res.update(sensor.record(), provenance=stamp(), adoption=adopt.record(adoption, note, sensor))

    def write(folder):
        docs.append(report.write(res, folder))
        if adoption.adopted:
            (Path(folder) / ADOPTED).write_text(dumps(adoption.sensor, f"gap diagnose --measured {mpath}: {note}"))

    # the report replaces the folder whole (never a mix of two runs); on a full disk it goes to $TMPDIR
    docs = []
    write_dir(out, write, "out", overwrite=True)
    s = docs[-1]["summary"]
    if as_json:
        click.echo(json.dumps(report._jsonable(s), indent=2))
    else:
        click.echo(f"{'SYNTHETIC data: ' if meas.synthetic else ''}{report.verdict_line(res)}")
        click.echo(f"sensor: {note}" + (f" -> {Path(out) / ADOPTED}" if adoption.adopted else ""))
        click.echo(f"report: {Path(out) / 'report.md'}")
    return 0


def error_mesh_sim(error_mesh, sim, cache, backend, jobs, no_progress):
    """The simulator of the finer mesh level for the model error (None: assumed floor)."""
    level = FINER.get(sim.mesh) if error_mesh is None else (None if error_mesh == "none" else error_mesh)
    if level is None:
        return None
    if level not in FINER or level == sim.mesh:
        raise UserError(
            "error-mesh", f"must be a mesh level other than {sim.mesh} (tiny, coarse, default, fine) or none"
        )
    return _sim(cache or default_cache(), level, backend, jobs, no_progress)


@param_flags({"effect": "--effects/--outside"})
@cli.command("selftest", context_settings=CONTEXT_SETTINGS)
@click.option("--trials", type=int, default=30, show_default=True, help="Blind trials to run.")
@click.option(
    "--out",
    type=click.Path(file_okay=False),
    default=None,
    help="Folder for selftest.md and selftest.json, rewritten after every trial (default: print only).",
)
@mesh_option(default="tiny", help="Mesh level of the diagnosis.")
@click.option("--error-mesh", default=None, help="Model-error mesh level (default: next finer; 'none': assumed floor).")
@click.option("--data-mesh", default=None, help="Mesh level of the measured data (default: the next finer level).")
@click.option(
    "--data-interface",
    type=click.Choice(["tied", "contact", "bonded"]),
    default="contact",
    show_default=True,
    help="Probe-tissue interface of the measured data (the diagnosis uses tied).",
)
@click.option(
    "--data-sizing",
    type=click.Choice(["fixed", "by_d"]),
    default="by_d",
    show_default=True,
    help="Element sizing of the measured data's mesh (the diagnosis and its error mesh use fixed).",
)
@click.option("--effects", default=None, help="Candidates (default: all defaults but the outside ones).")
@click.option(
    "--outside",
    default="aspect,skin,led_imbalance,stray_light",
    show_default=True,
    help="Effects drawn for out-of-library trials (never candidates; also core_shell, mislabel_d/h/E).",
)
@click.option("--n-phantoms", type=int, default=12, show_default=True, help="Phantoms per trial.")
@click.option("--frames", type=int, default=10, show_default=True, help="Camera frames per phantom.")
@click.option("--seed", type=int, default=0, show_default=True, help="Draws the trials (effects, magnitudes, noise).")
@click.option(
    "--phantom-seed",
    type=int,
    default=None,
    help="Draws the phantom set (default: --seed); keep it to reuse the cache.",
)
@click.option("--inverse", is_flag=True, help="Also retrain the inverse in every trial (slow).")
@click.option(
    "--model-form",
    type=click.Choice(["prior", "none"]),
    default="prior",
    show_default=True,
    help="Model-form level in each trial's decision (as 'gap diagnose --model-form').",
)
@click.option(
    "--start", type=int, default=0, show_default=True, help="First trial to run (resume a cut run: same draws)."
)
@common
def selftest_cmd(
    start,
    trials,
    out,
    mesh,
    error_mesh,
    data_mesh,
    data_interface,
    data_sizing,
    effects,
    outside,
    n_phantoms,
    frames,
    seed,
    phantom_seed,
    inverse,
    model_form,
    cache,
    backend,
    jobs,
    no_progress,
):
    """Blind benchmark with model-form error: no-effect, in-library and out-of-library trials (SYNTHETIC)."""
    from . import selftest

    if trials < 1:
        raise UserError("trials", f"must be >= 1 (got {trials})")
    if not 0 <= start < trials:
        raise UserError("start", f"must be in [0, trials) (got {start})")
    if n_phantoms < 4:
        raise UserError("n_phantoms", f"need at least 4 phantoms (got {n_phantoms})")
    if frames < 1:
        raise UserError("frames", f"must be >= 1 (got {frames})")
    for name, v in (("seed", seed), ("phantom_seed", phantom_seed)):
        if v is not None and v < 0:
            raise UserError(name, f"must be an integer >= 0 (got {v})")
    if out:
        check_out_dir(out, "out", allow_existing=True)
    if out and Path(out).exists() and any(Path(out).iterdir()):
        raise UserError("out", f"{out} exists and is not empty (not overwritten)")
    outs = fx.parse_list(outside, outside_only=True, flag="outside")
    cands = selftest.default_candidates([e.name for e in outs]) if effects is None else fx.parse_list(effects)
    if {e.name for e in cands} & {e.name for e in outs}:
        raise UserError("outside", "an outside effect is also a candidate")
    sim = _sim(cache or default_cache(), mesh, backend, jobs, no_progress)
    fine = error_mesh_sim(error_mesh, sim, cache, backend, jobs, no_progress)
    dm = data_mesh or FINER.get(mesh) or mesh
    if dm not in FINER:
        raise UserError("data-mesh", "must be tiny, coarse, default or fine")
    sim_data = sim if dm == mesh else _sim(cache or default_cache(), dm, backend, jobs, no_progress)

    def write(res):
        if not out:
            return
        from .report import _jsonable

        Path(out).mkdir(parents=True, exist_ok=True)
        for name, text in (
            ("selftest.md", selftest.markdown(res)),
            ("selftest.json", json.dumps(_jsonable(res), indent=2) + "\n"),
        ):
            tmp = Path(out) / f".{name}.tmp"
            tmp.write_text(text)
            os.replace(tmp, Path(out) / name)

    res = selftest.run(
        trials,
        sim,
        sim_data,
        cands,
        outs,
        fine,
        n_phantoms,
        frames,
        seed,
        Settings(inverse=inverse, model_form=model_form == "prior"),
        data_disc={
            k: v for k, v in (("interface", data_interface), ("sizing", data_sizing)) if v not in ("tied", "fixed")
        }
        or None,
        log=None if no_progress else lambda s: click.echo(s, err=True),
        on_trial=write,  # the scores so far after every trial (marked PARTIAL until the last)
        start=start,
        phantom_seed=phantom_seed,
    )
    write(res)
    click.echo(selftest.markdown(res))
    return 0


@cli.command("bench", context_settings=CONTEXT_SETTINGS)
@click.option("--n", "n", type=int, default=12, show_default=True, help="Phantoms of the SYNTHETIC data.")
@mesh_option(default="coarse", help="Mesh level of the diagnosis.")
@jobs_option(default=2, help="Worker processes for the solves.")
@click.option(
    "--effect", default="background_E=6.5", show_default=True, help="Effect in the SYNTHETIC data ('' = none)."
)
@click.option("--data-mesh", default="default", show_default=True, help="Mesh level of the SYNTHETIC data.")
@click.option(
    "--data-interface",
    type=click.Choice(["tied", "contact", "bonded"]),
    default="contact",
    show_default=True,
    help="Probe-tissue interface of the SYNTHETIC data's forward model.",
)
@click.option(
    "--data-cache", default=None, help="Solve cache of the data (default: the gap cache); the diagnosis uses none."
)
@click.option("--inverse", is_flag=True, help="Include the inverse retraining step.")
@click.option("--full-grid", is_flag=True, help="Solve every grid magnitude (the method before adaptive refinement).")
@click.option(
    "--out",
    type=click.Path(dir_okay=False),
    default=None,
    help="Also write the benchmark's numbers to this JSON file (default: print only).",
)
def bench_cmd(n, mesh, jobs, effect, data_mesh, data_interface, data_cache, inverse, full_grid, out):
    """Time a first diagnosis (no solve cache) of SYNTHETIC data: solves, seconds, where the time goes."""
    from . import bench
    from .report import _jsonable

    if n < 4:
        raise UserError("n", f"need at least 4 phantoms (got {n})")
    if jobs < 1:
        raise UserError("jobs", f"must be >= 1 (got {jobs})")
    if effect:
        fx.parse_spec(effect)
    if data_mesh not in ("tiny", "coarse", "default", "fine"):
        raise UserError("data-mesh", f"must be tiny, coarse, default or fine (got {data_mesh!r})")
    if out:
        check_out_file(out, "out")
    check_out_dir(data_cache or default_cache(), "data_cache", allow_existing=True)  # before any solve
    res = bench.run(
        n, mesh, jobs, effect, data_mesh, data_interface, data_cache or default_cache(), inverse, not full_grid
    )
    if out:
        Path(out).write_text(json.dumps(_jsonable(res), indent=2) + "\n")
    return 0


def main(argv=None):
    run_cli(cli, argv, prog_name="gap")


if __name__ == "__main__":
    main(sys.argv[1:])
