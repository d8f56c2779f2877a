"""Validation of the image model (image PCA -> the paper's MLP -> d, h, E), and the deployed one.

    elastimap study image_model --validate hov|loocv [--algo scg,lm] [--log-e] [--save-model DIR]
    elastimap study image_model --validate none --save-model models/image   # only the deployed model

The problem: the paper's MLP sees three features (O1, O2, O3) of the elasticity image; the image
model sees ln(peak) and the first k-1 shape-PCA scores of the whole FEM difference image
(:mod:`elastimap.identify.image_model`).  How much better does it identify (d, h, E)?

HOV (the 9 phantom rows) / LOOCV x repeats of :func:`elastimap.identify.image_model.run_image_validation`,
with the same splits, seeds, metrics and table layout as ``train``; writes ``results.csv``,
``results.md`` and the held-out predictions ``pred-<algo>[-lnE]-<validation>.npz`` (read by the
``region_score`` and ``refine`` studies).  ``--save-model DIR`` also trains the ensemble on every
row (:func:`elastimap.identify.image_model.fit_image_model`) for ``infer --model DIR``.  A refused
argument leaves nothing behind: ``--out`` is created only when results are written.
"""

from __future__ import annotations

import os

import click
import numpy as np

from elastimap.cli_util import CONTEXT_SETTINGS, param_flags, run
from elastimap.errors import UserError


@param_flags({"path": "--data"})
@click.command(context_settings=CONTEXT_SETTINGS)
@click.option(
    "--data",
    "data_path",
    default="data/sweep512",
    show_default=True,
    help="Sweep directory with stored elasticity images.",
)
@click.option("--algo", default="scg", show_default=True, help="scg, lm or scg,lm.")
@click.option(
    "--validate", default="hov", show_default=True, help="hov, loocv, hov,loocv, or none (only --save-model)."
)
@click.option("--repeats", default=10, show_default=True, type=int, help="Random initialisations per validation.")
@click.option(
    "--hidden",
    default="25,10",
    show_default=True,
    help="Hidden layers, e.g. 25,10 (tansig) or 12:logsig; as train's --hidden.",
)
@click.option(
    "--k",
    "k",
    default=10,
    show_default=True,
    type=int,
    help="Inputs from the image: ln(peak) and k-1 shape-PCA scores.",
)
@click.option("--force", is_flag=True, help="Add the plate-force difference 100 dF/F_ref as an input.")
@click.option(
    "--image-noise",
    default=0.01,
    show_default=True,
    type=float,
    help="Per-pixel Gaussian noise, relative to each image's peak, drawn per repeat.",
)
@click.option(
    "--log-e",
    "log_e",
    is_flag=True,
    help="The network learns ln E instead of E (metrics still on E; algo row '<algo>-image-lnE').",
)
@click.option("--epochs", default=100, show_default=True, type=int, help="Training epochs per network.")
@click.option("--workers", default=0, show_default=True, type=int, help="Training processes (0 = one per core).")
@click.option("--float32", "float32", is_flag=True, help="Single precision.")
@click.option("--seed", default=0, show_default=True, type=int, help="Seed of the splits, initialisations and noise.")
@click.option("--no-progress", is_flag=True, help="No progress bars.")
@click.option("--out", default="runs/image-inverse", show_default=True, help="Output directory.")
@click.option(
    "--save-model",
    "save_model",
    default=None,
    help="Also train on every row (first --algo, --repeats initialisations) and save the model "
    "here, for `infer --model DIR --fem-image ...` / camera frames.",
)
def main(
    data_path,
    algo,
    validate,
    repeats,
    hidden,
    k,
    force,
    image_noise,
    log_e,
    epochs,
    workers,
    float32,
    seed,
    no_progress,
    out,
    save_model,
):
    """Validate the image-based inverse (image PCA -> the paper's MLP -> d, h, E).

    Same HOV split (the 9 phantom rows), LOOCV folds, seeds, metrics and table layout as
    `train`, so the rows sit next to the feature MLP's (docs/identifiability.md).
    """
    import torch

    from elastimap.identify.image_model import fit_image_model, run_image_validation
    from elastimap.identify.measure import load
    from elastimap.outputs import check_out_dir
    from elastimap.training.experiment import ALGOS, VALIDATIONS, TrainConfig
    from elastimap.training.net import parse_hidden
    from elastimap.training.perf import set_threads, tune_malloc
    from elastimap.training.report import markdown, table, write_tables

    algos = [a.strip() for a in algo.split(",") if a.strip()]
    vals = [v.strip() for v in validate.split(",") if v.strip()]
    if vals == ["none"]:
        vals = []
        if not save_model:
            raise UserError("--validate", "none needs --save-model DIR (otherwise there is nothing to do)")
    for a in algos:
        if a not in ALGOS:
            raise UserError("--algo", f"must be scg and/or lm (got {a!r})")
    for v in vals:
        if v not in VALIDATIONS:
            raise UserError("--validate", f"must be hov and/or loocv (got {v!r})")
    if repeats < 1:
        raise UserError("--repeats", f"must be >= 1 (got {repeats})")
    if save_model:
        from elastimap.outputs import check_inputs_kept

        check_inputs_kept(save_model, "--save-model", data=data_path)  # the model never lands on its data
    if not 2 <= k <= 50:
        raise UserError("--k", f"must be in [2, 50] (got {k})")
    if not 0 <= image_noise < 1:
        raise UserError("--image-noise", f"must be in [0, 1) (got {image_noise:g})")
    if workers < 0:
        raise UserError("--workers", f"must be >= 0 (got {workers})")
    layers = parse_hidden(hidden, param="--hidden")
    if vals:
        check_out_dir(out, "--out", allow_existing=True)
    tune_malloc()
    set_threads(1)
    data = load(data_path)
    cfg = TrainConfig(
        hidden=layers,
        epochs=epochs,
        progress=not no_progress,
        workers=workers,
        dtype=torch.float32 if float32 else torch.float64,
    )
    results = []
    for v in vals:
        for a in algos:
            r = run_image_validation(
                data, a, v, repeats, cfg, seed=seed, k=k, image_noise=image_noise, force=force, log_e=log_e
            )
            results.append(r)
            os.makedirs(out, exist_ok=True)  # only now: a refused run leaves no empty --out
            # held-out predictions (repeats, rows, 3: d mm, h mm, E kPa; NaN where not a test row)
            extra = (
                {}
                if r.extra["pred_shared_noise"] is None
                else {"pred_shared_noise": r.extra["pred_shared_noise"], "image_noise": image_noise, "seed": seed}
            )
            np.savez(
                os.path.join(out, f"pred-{a}{'-lnE' if log_e else ''}-{v}.npz"),
                pred=r.extra["pred"],
                ids=np.asarray(data.ids, dtype=str),
                theta=data.theta,
                **extra,
            )
            click.echo(f"{a}-image {v}: {r.row['trainings']} trainings in {r.wall_s:.1f} s", err=True)
    if save_model:
        model = fit_image_model(
            data, algos[0], repeats, cfg, seed=seed, k=k, force=force, image_noise=image_noise, log_e=log_e
        )
        model.save(save_model)
        click.echo(f"saved {algos[0]}-image ensemble ({repeats} members, {data.n} rows) to {save_model}", err=True)
    if not results:
        return 0
    df = table(results)
    df.insert(0, "data", data.source)
    title = (
        f"Image-based inverse, {data.source} ({data.n} rows), inputs ln(peak) + {k - 1} shape-PCA scores"
        f"{' + force' if force else ''}{', target ln E' if log_e else ''}, image noise {image_noise:g} of the peak, {epochs} epochs; "
        f"mean [2.5 %, 97.5 %] over {repeats} repeat(s)."
    )
    md = markdown(df, title)
    write_tables(out, df, md)
    click.echo(md)
    return 0


if __name__ == "__main__":
    run(main, prog_name="elastimap study image_model")
