"""Is a sweep with several inclusion moduli per mesh as good a training set as a Latin hypercube?

    elastimap study moduli_per_mesh --mesh coarse --n 256 --k 8 --test 128 --out DIR

``sweep run --moduli-per-mesh k`` (docs/sweep.md, 'What it samples') puts n/k geometries (d, h) in
the design, each with k moduli, so that a geometry's samples share one mesh, one model and one
reference press: more samples for the same CPU, but fewer distinct geometries.  This study measures
what that does to the inverse map the samples train:

* sweeps (elastimap's forward model, ``--mesh``): ``lhs`` -- a Latin hypercube of n samples (k = 1,
  seed 0); ``grouped`` -- the same n with k moduli per mesh (seed 0); ``grouped-budget`` -- k moduli
  per mesh, as many samples as the ``lhs`` sweep's worker CPU buys at the grouped sweep's cost a
  sample (rounded down to a multiple of k); ``test`` -- an independent Latin hypercube (seed 99,
  k = 1) that no training set shares a geometry with;
* each training set: an SCG ensemble (``--repeats`` networks, the product's default architecture);
* the test samples' (d, h, E) from their features: the mean relative error of the ensemble's
  median, per target, and the workers' CPU of each sweep.

Self-consistency only (every set is elastimap's own solver): what it measures is the design, not the
forward model.  Prints a table; ``--out DIR`` keeps the sweeps and ``DIR/summary.json``.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import click
import numpy as np

from elastimap.cli_util import MeshLevel, run


def _sweep(out: Path, mesh: str, n: int, k: int, seed: int, jobs: int) -> dict:
    """One sweep into ``out``; returns its rows and its workers' CPU seconds."""
    from elastimap.dataset import io
    from elastimap.sweep.run import SweepConfig, make_plan
    from elastimap.sweep.run import run as run_sweep

    cfg = SweepConfig(n=n, moduli_per_mesh=k, seed=seed, mesh=mesh, jobs=jobs, out=str(out), progress=False)
    t0 = os.times()
    s = run_sweep(cfg, make_plan(cfg))
    t1 = os.times()
    cpu = (t1.children_user + t1.children_system) - (t0.children_user + t0.children_system)
    return {"rows": io.read_samples(out), "worker_cpu_s": cpu, "ok": s["ok"], "n": n, "k": k}


def _errors(train, test, repeats: int, seed: int) -> dict:
    """Mean relative error (%) of the ensemble median's d, h, E on ``test``."""
    from elastimap.training.api import fit_ensemble
    from elastimap.training.data import FEATURES, TARGETS

    ens = fit_ensemble(train, algo="scg", repeats=repeats, seed=seed)
    pred = np.median(ens.predict(test[list(FEATURES)].to_numpy(float)), axis=0)
    truth = test[list(TARGETS)].to_numpy(float)
    mre = 100 * np.mean(np.abs(pred / truth - 1), axis=0)
    return dict(zip(TARGETS, (float(v) for v in mre)))


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--mesh", type=MeshLevel(), default="coarse", show_default=True, help="Mesh level of every sweep.")
@click.option("--n", "n", type=click.IntRange(8, 100_000), default=256, show_default=True, help="Samples of `lhs`.")
@click.option("--k", "k", type=click.IntRange(2, 64), default=8, show_default=True, help="Moduli per mesh.")
@click.option("--test", "n_test", type=click.IntRange(8, 100_000), default=128, show_default=True, help="Test samples.")
@click.option("--repeats", type=click.IntRange(1, 100), default=5, show_default=True, help="Networks per ensemble.")
@click.option("--jobs", type=click.IntRange(1, 64), default=2, show_default=True, help="Sweep worker processes.")
@click.option("--out", "out", required=True, help="Folder for the sweeps and summary.json (must not exist).")
def main(mesh, n, k, n_test, repeats, jobs, out):
    """Train on a Latin hypercube and on k-moduli-per-mesh designs; score each on an independent test set."""
    root = Path(out)
    if root.exists():
        from elastimap.errors import UserError

        raise UserError("out", f"{root} exists; choose a new folder")
    root.mkdir(parents=True)
    n = n - n % k
    t_all = time.perf_counter()
    sets = {
        "test": _sweep(root / "test", mesh, n_test, 1, 99, jobs),
        "lhs": _sweep(root / "lhs", mesh, n, 1, 0, jobs),
        "grouped": _sweep(root / "grouped", mesh, n, k, 0, jobs),
    }
    per = sets["grouped"]["worker_cpu_s"] / n
    n_budget = int(sets["lhs"]["worker_cpu_s"] / per) // k * k
    sets["grouped-budget"] = _sweep(root / "grouped-budget", mesh, n_budget, k, 1, jobs)
    test = sets["test"]["rows"]
    rows = []
    for name in ("lhs", "grouped", "grouped-budget"):
        s = sets[name]
        err = _errors(s["rows"], test, repeats, seed=0)
        rows.append(
            {"set": name, "n": s["n"], "k": s["k"], "ok": s["ok"], "worker_cpu_s": s["worker_cpu_s"], "mre_pct": err}
        )
    click.echo(f"test: {len(test)} samples (LHS seed 99, mesh {mesh}); SCG ensembles of {repeats}")
    click.echo(f"{'set':>15} {'n':>6} {'k':>3} {'worker CPU s':>12} {'CPU s/sample':>12}  MRE d / h / E (%)")
    for r in rows:
        e = r["mre_pct"]
        click.echo(
            f"{r['set']:>15} {r['n']:>6} {r['k']:>3} {r['worker_cpu_s']:>12.1f} {r['worker_cpu_s'] / r['n']:>12.3f}"
            f"  {e['d']:.2f} / {e['h']:.2f} / {e['E']:.2f}"
        )
    summary = {"mesh": mesh, "test": len(test), "repeats": repeats, "rows": rows, "wall_s": time.perf_counter() - t_all}
    (root / "summary.json").write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    run(main)
