"""``elastimap train`` (alias ``train``): validate the inverse MLP (HOV / LOOCV, LM / SCG) and save the ensemble.

    elastimap train --data runs/sweep512 --algo all --validate all --repeats 10 --out runs/train

Writes to ``--out``: ``results.csv``, ``results.md`` (also printed),
``curves-<algo>-<validation>.png``, ``run.json`` and, per algorithm,
``model-<algo>/`` -- the ensemble of ``--repeats`` networks trained on all
non-test rows (all rows unless only HOV was asked for), loadable with
:meth:`elastimap.training.model.Ensemble.load`.  ``--out`` holds exactly one
run: the run writes into a hidden temporary sibling folder that replaces
``--out`` whole when it finishes (and is removed if it fails); an existing
``--out`` that holds files is refused unless ``--overwrite``.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass

import click

from elastimap.cli_util import CONTEXT_SETTINGS, Choice, data_option, no_progress_option, out_option, run
from elastimap.errors import UserError
from elastimap.outputs import check_inputs_kept, check_out_dir

ALGO_CHOICES = ("lm", "scg", "all")
VALIDATE_CHOICES = ("hov", "loocv", "all")


@click.command(context_settings=CONTEXT_SETTINGS)
@data_option()
@click.option(
    "--synthetic",
    type=int,
    default=None,
    metavar="N",
    help="Use the SYNTHETIC analytic toy table with N rows instead of --data (development only).",
)
@click.option(
    "--algo",
    type=Choice(ALGO_CHOICES),
    default="scg",
    show_default=True,
    help="Levenberg–Marquardt, scaled conjugate gradient or both.",
)
@click.option(
    "--validate",
    type=Choice(VALIDATE_CHOICES),
    default="hov",
    show_default=True,
    help="Hold-out (the phantom rows), leave-one-out or both.",
)
@click.option("--repeats", default=10, show_default=True, type=int, help="Independent random initialisations.")
@click.option("--epochs", default=100, show_default=True, type=int, help="Training epochs per network (the most).")
@click.option(
    "--hidden",
    default="25,10",
    show_default=True,
    help="Hidden layer sizes; per-layer transfer function with ':', e.g. 25,10,7:purelin.",
)
@click.option("--activation", default="tansig", show_default=True, help="Hidden transfer function: tansig or logsig.")
@click.option(
    "--feature-noise",
    default=0.0,
    show_default=True,
    type=float,
    help="Relative Gaussian noise on O1..O3 (0.01 = 1 %), drawn per network.",
)
@click.option("--test-split", default=None, type=float, help="HOV: random test fraction instead of the phantom rows.")
@click.option(
    "--val-fraction",
    default=0.0,
    show_default=True,
    type=float,
    help="Validation rows per network for early stopping (6 failures); 0 = none.",
)
@click.option(
    "--seed",
    default=0,
    show_default=True,
    type=int,
    help="Seed of the initial weights, the splits and the feature noise (and of --synthetic's table).",
)
@out_option(default="runs/train", help="Output directory (one run; an existing one only with --overwrite).")
@click.option(
    "--overwrite", is_flag=True, help="Replace an existing --out folder whole (after the new run has finished)."
)
@click.option("--device", default=None, help="cpu or cuda (default: cuda when available).")
@click.option(
    "--threads",
    default=1,
    show_default=True,
    type=int,
    help="Torch CPU threads (0 = torch default); more threads were slower on the shared 2-core machine.",
)
@click.option(
    "--float32",
    "float32",
    is_flag=True,
    help="Single precision: about 2x faster on the CPU; see docs/training.md for its effect on the table.",
)
@click.option(
    "--workers",
    default=0,
    show_default=True,
    type=int,
    help="CPU processes sharing the networks (0 = one per core); each uses one torch thread. "
    "Results do not depend on it.",
)
@click.option("--no-model", is_flag=True, help="Skip training the saved ensemble.")
@no_progress_option()
def cli(
    data,
    synthetic,
    algo,
    validate,
    repeats,
    epochs,
    hidden,
    activation,
    feature_noise,
    test_split,
    val_fraction,
    seed,
    out,
    overwrite,
    device,
    threads,
    float32,
    workers,
    no_model,
    no_progress,
):
    """Train and validate the inverse MLP (O1, O2, O3) -> (d, h, E)."""
    import torch

    from elastimap.constraints import validate_params

    from .data import load_samples, prepare, synthetic_table
    from .experiment import ALGOS, RUN_CONSTRAINTS, VALIDATIONS, TrainConfig
    from .net import parse_hidden
    from .perf import set_threads, tune_malloc

    # the rules are declared next to the parameters they govern; all checked before any work
    validate_params(dict(repeats=repeats, seed=seed, test_split=test_split), RUN_CONSTRAINTS)
    if (data is None) == (synthetic is None):
        raise UserError("data", "give exactly one of --data PATH or --synthetic N")
    hidden_t = parse_hidden(hidden, activation)
    cfg = TrainConfig(
        hidden=hidden_t,
        epochs=epochs,
        feature_noise=feature_noise,
        val_fraction=val_fraction,
        device=device,
        dtype=torch.float32 if float32 else torch.float64,
        progress=not no_progress,
        workers=workers,
    ).validate()
    if device and device.startswith("cuda") and not torch.cuda.is_available():
        raise UserError("device", "cuda requested but no GPU is available")
    if threads < 0:
        raise UserError("threads", f"must be >= 0 (0 = torch's default; got {threads})")
    if data is not None:
        check_inputs_kept(out, "out", data=data)
    check_out_dir(out, "out", overwrite=overwrite, marker="run.json")  # before any work; the run is staged below

    if synthetic is not None:
        if synthetic < 10:
            raise UserError("synthetic", f"need at least 10 rows (got {synthetic})")
        samples = prepare(synthetic_table(synthetic, seed=seed), source=f"SYNTHETIC toy table (n={synthetic})")
    else:
        samples = load_samples(data)
    tune_malloc()
    nthreads = set_threads(threads)
    algos = list(ALGOS) if algo == "all" else [algo]
    vals = list(VALIDATIONS) if validate == "all" else [validate]
    spec = RunSpec(
        algos=algos,
        validations=vals,
        repeats=repeats,
        seed=seed,
        test_split=test_split,
        hidden=hidden,
        activation=activation,
        threads=nthreads,
        save_models=not no_model,
    )
    _run(samples, cfg, spec, out, overwrite)
    click.echo(f"wrote {out}", err=True)
    return 0


@dataclass(frozen=True)
class RunSpec:
    """What one ``train`` run does besides how each network trains (that is :class:`TrainConfig`)."""

    algos: list[str]
    validations: list[str]
    repeats: int
    seed: int
    test_split: float
    hidden: str  # as typed, for run.json
    activation: str
    threads: int
    save_models: bool


def _run(samples, cfg, spec: RunSpec, out: str, overwrite: bool) -> None:
    """The run: every network trained first, then everything written as one folder
    (:func:`elastimap.outputs.write_dir`: ``out`` is replaced whole, and on a full disk the
    finished run goes to a temporary folder that the error line names)."""
    from elastimap.outputs import write_dir

    from .data import data_hash
    from .experiment import check_trainable
    from .report import markdown, table

    check_trainable(samples.n, cfg.arch, "data set")  # every fold is smaller: refuse before any output
    click.echo(samples.report(), err=True)
    click.echo(
        f"network {cfg.arch.describe()} ({cfg.arch.n_params} weights), device "
        f"{cfg.resolved_device()}, {spec.threads} thread(s)",
        err=True,
    )
    t0 = time.perf_counter()
    results = _validate_all(samples, cfg, spec)
    df = table(results)
    df.insert(0, "data_sha256", data_hash(samples.df))
    df.insert(0, "data", samples.source)
    title = (
        f"Test errors, {samples.source}, {cfg.arch.describe()}, {cfg.epochs} epochs, feature noise "
        f"{cfg.feature_noise:g}; mean [2.5 %, 97.5 %] over {spec.repeats} repeat(s). MSE×100 is paper eq. (1) "
        f"on mapminmax [-1, 1]-scaled targets."
    )
    md = markdown(df, title)
    click.echo(md)

    ensembles = _fit_models(samples, cfg, spec) if spec.save_models else {}
    models = {a: os.path.join(out, f"model-{a}") for a in ensembles}
    doc = _run_doc(samples, cfg, spec, models, time.perf_counter() - t0)
    write_dir(out, lambda folder: _write(folder, results, df, md, ensembles, doc), "out", overwrite=overwrite)
    for a, (ens, n) in ensembles.items():
        click.echo(f"saved {ens.n_members}-member {a} ensemble ({n} training rows) to {models[a]}", err=True)


def _validate_all(samples, cfg, spec: RunSpec) -> list:
    """Every (validation, algorithm) pair of ``spec`` trained and scored, in that order."""
    from .experiment import run_validation

    results = []
    for v in spec.validations:
        for a in spec.algos:
            r = run_validation(samples, a, v, spec.repeats, cfg, seed=spec.seed, test_split=spec.test_split)
            results.append(r)
            click.echo(
                f"{a} {v}: {r.row['trainings']} trainings in {r.wall_s:.1f} s "
                f"({r.row['trainings_per_s']:.2f}/s); stops {r.row['stops']}",
                err=True,
            )
    return results


def _fit_models(samples, cfg, spec: RunSpec) -> dict:
    """``{algo: (ensemble, training rows)}``: the ensembles ``--save-models`` keeps, trained on every
    row (with ``--validate hov`` alone: every row but the hold-out test rows)."""
    from .api import fit_ensemble
    from .data import prepare

    s = samples
    if spec.validations == ["hov"]:
        from .experiment import rng_for, split_rows

        test_rows, _ = split_rows(samples, "hov", spec.test_split, rng_for(spec.seed, "hov")[0])
        s = prepare(samples.df[~test_rows], source=samples.source)
        s.n_failed = samples.n_failed
    ensembles = {}
    for a in spec.algos:
        ens = fit_ensemble(
            s,
            algo=a,
            repeats=spec.repeats,
            epochs=cfg.epochs,
            hidden=cfg.hidden,
            seed=spec.seed,
            feature_noise=cfg.feature_noise,
            val_fraction=cfg.val_fraction,
            device=cfg.device,
            progress=cfg.progress,
            dtype=cfg.dtype,
        )
        ensembles[a] = (ens, s.n)
    return ensembles


def _run_doc(samples, cfg, spec: RunSpec, models: dict, wall_s: float) -> dict:
    """``run.json``: the data, the settings and where the models went."""
    from .data import data_hash

    return {
        "data": samples.source,
        "n_samples": samples.n,
        "n_failed_excluded": samples.n_failed,
        "data_sha256": data_hash(samples.df),
        "algo": spec.algos,
        "validate": spec.validations,
        "repeats": spec.repeats,
        "epochs": cfg.epochs,
        "hidden": spec.hidden,
        "activation": spec.activation,
        "feature_noise": cfg.feature_noise,
        "test_split": spec.test_split,
        "val_fraction": cfg.val_fraction,
        "seed": spec.seed,
        "device": str(cfg.resolved_device()),
        "threads": spec.threads,
        "workers": cfg.workers,
        "dtype": str(cfg.dtype),
        "wall_s": round(wall_s, 3),
        "models": models,
    }


def _write(folder, results, df, md: str, ensembles: dict, doc: dict) -> None:
    """Everything one run writes, into ``folder``."""
    from .report import plot_curves, write_tables

    for r in results:
        plot_curves(r, os.path.join(folder, f"curves-{r.algo}-{r.validate}.png"), label=f", {doc['data']}")
    write_tables(folder, df, md)
    for a, (ens, _) in ensembles.items():
        ens.save(os.path.join(folder, f"model-{a}"))
    with open(os.path.join(folder, "run.json"), "w") as f:
        json.dump(doc, f, indent=2)


def main(argv: list[str] | None = None) -> None:
    run(cli, argv, prog_name="train")


if __name__ == "__main__":
    main()
