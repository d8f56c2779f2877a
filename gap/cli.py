"""``elastimap gap`` (alias ``gap``): synth, diagnose, selftest, effects.

    elastimap gap synth --out M --effect friction=0.3 [--mesh tiny] [--n 12]
    elastimap gap diagnose --measured M --out DIR [--effects a,b] [--no-inverse]
    elastimap gap selftest --trials 20 --out DIR [--mesh tiny]
    elastimap gap effects

User errors print one ``error:`` line and exit 2.  Solves are cached under ``--cache``
(default ``$ELASTIMAP_GAP_CACHE`` or ``~/.cache/elastimap/gap``).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import click

from elastimap.cli_util import CONTEXT_SETTINGS, jobs_option, mesh_option, options
from elastimap.cli_util import run as run_cli
from elastimap.errors import UserError

from . import effects as fx


def default_cache() -> str:
    return os.environ.get("ELASTIMAP_GAP_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "elastimap", "gap")


def _sim(cache, mesh, backend, jobs, quiet):
    from .simulate import Simulator

    def prog(i, n):
        if not quiet:
            click.echo(f"\rsolves {i}/{n}", nl=(i == n), err=True)
    return Simulator(None if cache == "none" else os.path.join(cache, f"{backend}-{mesh}"), mesh, backend, jobs, prog)


common = options(
    click.option("--cache", default=None, help="solve cache folder ('none' = no cache)"),
    click.option("--backend", type=click.Choice(["fem", "toy"]), default="fem", show_default=True,
                 help="fem = DOLFINx forward model; toy = analytic TOY stand-in (tests only)"),
    jobs_option(default=1, help="worker processes for missing solves"),
    click.option("--quiet", is_flag=True),
)


@click.group(context_settings=CONTEXT_SETTINGS)
def main_group():
    """Sim-to-real gap diagnosis.  Synthetic data are labelled SYNTHETIC."""


@main_group.command("effects", context_settings=CONTEXT_SETTINGS)
def effects_cmd():
    """List the effects library."""
    for e in fx.EFFECTS.values():
        click.echo(f"{e.name:13s} {e.stage:9s} nominal {e.nominal:g} {e.unit}; grid {list(e.grid)}; "
                   f"blind {list(e.blind)}  {e.description}")


@main_group.command("synth", context_settings=CONTEXT_SETTINGS)
@click.option("--out", required=True, type=click.Path(file_okay=False))
@click.option("--effect", "effect", default="", help="NAME=MAGNITUDE[,NAME=MAGNITUDE] (empty: baseline only)")
@click.option("--phantoms", type=click.Path(), default=None, help="CSV with id (or name), d, h, E; default an LHS design")
@click.option("--n", "n", type=int, default=12, show_default=True)
@mesh_option(default="coarse")
@click.option("--frames", type=int, default=10, show_default=True)
@click.option("--noise-scale", type=float, default=1.0, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--format", "fmt", type=click.Choice(["csv", "parquet"]), default="csv", show_default=True)
@common
def synth_cmd(out, effect, phantoms, n, mesh, frames, noise_scale, seed, fmt, cache, backend, jobs, quiet):
    """Generate a SYNTHETIC measured dataset (truth sealed in SEALED_truth.json)."""
    import numpy as np

    from . import measured, synth

    effs = fx.parse_spec(effect) if effect else []
    ids = None
    if phantoms:
        from elastimap.camera.calibration import load_phantoms
        df = load_phantoms(phantoms) if "name" in open(phantoms).read(2000) else None
        if df is None:
            import pandas as pd
            df = pd.read_csv(phantoms, comment="#").rename(columns={"id": "name"})
        dhe = df[["d", "h", "E"]].to_numpy(float)
        ids = [str(x) for x in df["name"]]
    else:
        if n < 4:
            raise UserError("n", "need at least 4 phantoms")
        dhe = synth.phantom_design(n, seed)
    sim = _sim(cache or default_cache(), mesh, backend, jobs, quiet)
    meas, truth = synth.synthesize(dhe, effs, sim, frames=frames, seed=seed, ids=ids, noise_scale=noise_scale)
    tp = measured.write(meas, out, fmt)
    synth.seal(truth, out)
    click.echo(f"SYNTHETIC measured data: {tp} ({meas.n} phantoms, truth sealed in {Path(out) / measured.SEALED})")
    return 0


@main_group.command("diagnose", context_settings=CONTEXT_SETTINGS)
@click.option("--measured", "mpath", required=True, type=click.Path())
@click.option("--out", required=True, type=click.Path(file_okay=False))
@click.option("--effects", default=None, help="comma-separated candidate effects (default: all but offaxis)")
@mesh_option(default=None, help="override the sidecar's mesh level")
@click.option("--no-inverse", is_flag=True, help="skip the (d, h, E) retraining step")
@click.option("--n-train", type=int, default=40, show_default=True, help="simulations per inverse training set")
@click.option("--model-floor", type=float, default=0.005, show_default=True)
@click.option("--explain-min", type=float, default=0.7, show_default=True)
@click.option("--resid-max", type=float, default=4.0, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--json", "as_json", is_flag=True, help="print the summary as JSON")
@common
def diagnose_cmd(mpath, out, effects, mesh, no_inverse, n_train, model_floor, explain_min, resid_max, seed,
                 as_json, cache, backend, jobs, quiet):
    """Diagnose the sim-to-real gap of a measured dataset: report.md, PNG figures, diagnosis.json."""
    from . import measured, report
    from .diagnose import Settings, diagnose

    meas = measured.load(mpath)
    cands = fx.parse_list(effects)
    st = Settings(model_floor=model_floor, explain_min=explain_min, resid_max=resid_max, seed=seed,
                  inverse=not no_inverse, n_train=n_train)
    sim = _sim(cache or default_cache(), mesh or meas.mesh, backend, jobs, quiet)
    res = diagnose(meas, cands, sim, st)
    doc = report.write(res, out)
    s = doc["summary"]
    if as_json:
        click.echo(json.dumps(report._jsonable(s), indent=2))
    else:
        click.echo(f"{'SYNTHETIC data: ' if meas.synthetic else ''}outcome: {s['outcome']}"
                   + (f"; winner {s['winner']} = {s['magnitude']:.4g} {s['unit']} "
                      f"[{s['magnitude_ci'][0]:.4g}, {s['magnitude_ci'][1]:.4g}], runner-up {s['runner_up']}"
                      if s["winner"] else f"; best candidate {s.get('best_candidate')}"))
        click.echo(f"report: {Path(out) / 'report.md'}")
    return 0


@main_group.command("selftest", context_settings=CONTEXT_SETTINGS)
@click.option("--trials", type=int, default=20, show_default=True)
@click.option("--out", type=click.Path(file_okay=False), default=None)
@mesh_option(default="tiny")
@click.option("--effects", default=None)
@click.option("--n-phantoms", type=int, default=12, show_default=True)
@click.option("--frames", type=int, default=10, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--inverse", is_flag=True, help="also retrain the inverse in every trial (slow)")
@click.option("--no-withheld", is_flag=True, help="skip the true-effect-removed mode")
@common
def selftest_cmd(trials, out, mesh, effects, n_phantoms, frames, seed, inverse, no_withheld, cache, backend, jobs, quiet):
    """Blind check: random sealed effect + magnitude, diagnose, score (SYNTHETIC)."""
    from . import selftest
    from .diagnose import Settings

    if trials < 1:
        raise UserError("trials", "must be >= 1")
    sim = _sim(cache or default_cache(), mesh, backend, jobs, quiet)
    res = selftest.run(trials, sim, fx.parse_list(effects), n_phantoms, frames, seed, Settings(inverse=inverse),
                       not no_withheld, log=None if quiet else lambda s: click.echo(s, err=True))
    md = selftest.markdown(res)
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / "selftest.md").write_text(md)
        from .report import _jsonable
        (Path(out) / "selftest.json").write_text(json.dumps(_jsonable(res), indent=2) + "\n")
    click.echo(md)
    return 0


def main(argv=None):
    run_cli(main_group, argv, prog_name="gap")


if __name__ == "__main__":
    main(sys.argv[1:])
