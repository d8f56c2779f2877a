"""Benchmark: LOOCV x repeats trainings per second on the SYNTHETIC toy table.

    python -m elastimap.training.bench --n 512 --repeats 10              # the full goal problem
    python -m elastimap.training.bench --n 512 --repeats 1 --folds 64    # a slice of it, projected

Trains ``folds x repeats`` leave-one-out networks (``folds`` defaults to all
``n``) exactly as ``train --validate loocv`` does, and prints wall time, CPU
time, trainings per second and the projected wall time of the full
``n x repeats`` LOOCV.  Data are the analytic toy table
(:func:`elastimap.training.data.synthetic_table`), so only the timings mean anything.
"""

from __future__ import annotations

import os
import platform
import time

import click
import numpy as np

from elastimap.cli_util import CONTEXT_SETTINGS, no_progress_option, run
from elastimap.errors import UserError


def _cpu() -> float:
    """CPU seconds of this process and its finished children (the worker processes)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


@click.command(context_settings=CONTEXT_SETTINGS)
@click.option("--n", "n", default=512, show_default=True, help="Samples in the SYNTHETIC toy table.")
@click.option("--repeats", default=10, show_default=True, help="Independent random initialisations per fold.")
@click.option("--folds", default=0, help="LOOCV folds actually trained (0 = all n); the rest is projected.")
@click.option("--algo", default="scg,lm", show_default=True, help="Comma-separated: scg, lm.")
@click.option("--epochs", default=100, show_default=True, help="Training epochs per network (the most).")
@click.option("--hidden", default="25,10", show_default=True, help="Hidden layer sizes, as train --hidden.")
@click.option("--device", default=None, help="cpu or cuda (default: cuda when available).")
@click.option(
    "--threads",
    default=1,
    show_default=True,
    help="Torch CPU threads (0 = torch default); more threads were slower on the shared 2-core machine.",
)
@click.option("--float32", "float32", is_flag=True, help="Single precision (as train --float32).")
@click.option(
    "--workers",
    default=1,
    show_default=True,
    help="CPU processes sharing the networks (0 = one per core); each uses one thread.",
)
@no_progress_option()
def cli(n, repeats, folds, algo, epochs, hidden, device, threads, float32, workers, no_progress):
    """Time batched LOOCV training on the SYNTHETIC toy table."""
    import torch

    from .data import FEATURES, TARGETS, synthetic_table
    from .experiment import TrainConfig, make_batch, train_batch
    from .net import parse_hidden
    from .perf import set_threads, tune_malloc

    algos = [a.strip() for a in algo.split(",") if a.strip()]
    for a in algos:
        if a not in ("scg", "lm"):
            raise UserError("--algo", f"unknown algorithm {a!r}; use scg and/or lm")
    if n < 20:
        raise UserError("--n", f"need at least 20 samples (got {n})")
    if repeats < 1:
        raise UserError("--repeats", f"must be >= 1 (got {repeats})")
    if workers < 0:
        raise UserError("--workers", f"must be >= 0 (got {workers})")
    folds = n if folds in (0, None) else int(folds)
    if not 1 <= folds <= n:
        raise UserError("--folds", f"must be in [1, {n}] (got {folds})")
    tune_malloc()
    nthreads = set_threads(threads)
    cfg = TrainConfig(
        hidden=parse_hidden(hidden),
        epochs=epochs,
        device=device,
        dtype=torch.float32 if float32 else torch.float64,
        progress=not no_progress,
        workers=workers,
    )
    df = synthetic_table(n, seed=0)
    X, T = df[list(FEATURES)].to_numpy(), df[list(TARGETS)].to_numpy()
    fit = np.ones((repeats * folds, n), bool)
    fold_idx = np.tile(np.arange(folds), repeats)
    fit[np.arange(repeats * folds), fold_idx] = False
    dev = cfg.resolved_device()
    click.echo(
        f"SYNTHETIC toy table n={n}; LOOCV {folds}/{n} folds x {repeats} repeats = {fit.shape[0]} trainings "
        f"per algorithm; {cfg.arch.describe()} ({cfg.arch.n_params} weights), {epochs} epochs, "
        f"{str(cfg.dtype).replace('torch.', '')}, device {dev}, {nthreads} thread(s), "
        f"{workers or os.cpu_count()} worker process(es) (1 thread each when > 1), {os.cpu_count()} CPU(s) visible, {platform.processor() or platform.machine()}"
    )
    if dev.type == "cuda":
        click.echo(f"GPU: {torch.cuda.get_device_name(dev)}")
    rows = []
    for a in algos:
        b = make_batch(X, T, fit, ~fit, cfg, np.random.default_rng(0), torch.Generator().manual_seed(0))
        if dev.type == "cuda":
            torch.cuda.synchronize()
        t0, c0 = time.perf_counter(), _cpu()
        res = train_batch(a, b.obj, b.theta0, cfg, desc=f"bench {a}")
        if dev.type == "cuda":
            torch.cuda.synchronize()
        wall, cpu = time.perf_counter() - t0, _cpu() - c0
        k = fit.shape[0]
        full = n * repeats
        rows.append(
            (
                a,
                k,
                wall,
                cpu,
                k / wall,
                full / (k / wall),
                n * 10 / (k / wall),
                n * 10 * cpu / k,
                float(res.epochs.double().mean()),
            )
        )
    click.echo("")
    click.echo(
        f"| algo | trainings | wall s | CPU s | trainings/s | projected LOOCV x {repeats} wall (min) "
        f"| projected LOOCV x 10 wall (min) | LOOCV x 10 CPU (min) | mean epochs |"
    )
    click.echo("|---|---|---|---|---|---|---|---|---|")
    for a, k, wall, cpu, rate, proj, proj10, cpu10, ep in rows:
        click.echo(
            f"| {a.upper()} | {k} | {wall:.1f} | {cpu:.1f} | {rate:.2f} | {proj / 60:.1f} | {proj10 / 60:.1f} "
            f"| {cpu10 / 60:.1f} | {ep:.1f} |"
        )
    return 0


def main(argv: list[str] | None = None) -> None:
    run(cli, argv, prog_name="python -m elastimap.training.bench")


if __name__ == "__main__":
    main()
