"""Benchmark of inference from SYNTHETIC camera frames: image network -> physics fit.

Stage ``lesions`` (no fit needed, run it first): held-out lesions drawn by a Latin hypercube over
the WHOLE design box (d 2-15 mm, the admissible centre depth, E 10-200 kPa log-uniform; own seed,
not the sweep's points) and the nine calibration phantoms, solved by the "world" forward model --
the remeshing solver on ``--truth-mesh`` (default ``default``), a different discretisation than the
fit's forward map -- and kept in the solve store ``OUT/solves``.  Resumable: solved lesions are
read back.  Everything it makes is SYNTHETIC.

    OMP_NUM_THREADS=1 .venv/bin/python workflows/frames_benchmark.py lesions --n 120 --out runs/frames-bench
"""

from __future__ import annotations

import os
import sys
import time

import click
import numpy as np

TRUTH_SEED = 2026


def draw_lesions(n: int, seed: int = TRUTH_SEED) -> np.ndarray:
    """(n, 3) lesions (d mm, h mm, E kPa): Latin hypercube over d, the admissible depth fraction and ln E."""
    from scipy.stats import qmc

    from elastimap.dataset.schema import DESIGN_BOX
    from elastimap.solver.params import depth_range

    (d0, d1), (e0, e1) = DESIGN_BOX["d"], DESIGN_BOX["E"]
    u = qmc.LatinHypercube(d=3, seed=seed).random(n)
    d = d0 + (d1 - d0) * u[:, 0]
    lo, hi = np.array([depth_range(x) for x in d]).T
    h = lo + u[:, 1] * (hi - lo)
    E = np.exp(np.log(e0) + (np.log(e1) - np.log(e0)) * u[:, 2])
    return np.column_stack([d, h, E])


def truth_solve(d, h, E, mesh: str, cache: str) -> dict:
    from elastimap.identify.solves import cached_solve

    return cached_solve(float(d), float(h), float(E), mesh=mesh, cache=cache)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main():
    """SYNTHETIC camera-frame benchmark of the physics fit (see the module docstring)."""


@main.command("lesions")
@click.option("--n", "n", default=120, show_default=True, type=int, help="Held-out lesions.")
@click.option("--seed", default=TRUTH_SEED, show_default=True, type=int, help="Seed of the lesion design.")
@click.option("--truth-mesh", default="default", show_default=True, help="Mesh level of the world's remeshing solver.")
@click.option("--out", required=True, help="Benchmark folder (solves land in OUT/solves).")
def lesions(n, seed, truth_mesh, out):
    """Solve the phantoms and the held-out lesions with the world's forward model (resumable)."""
    from tqdm import tqdm

    from elastimap.camera.calibration import load_phantoms

    cache = os.path.join(out, "solves")
    os.makedirs(cache, exist_ok=True)
    ph = load_phantoms()
    todo = [(float(r["d"]), float(r["h"]), float(r["E"])) for _, r in ph.iterrows()]
    todo += [tuple(map(float, t)) for t in draw_lesions(n, seed)]
    t0 = time.perf_counter()
    for d, h, E in tqdm(todo, desc=f"SYNTHETIC world solves ({truth_mesh} mesh, remeshing)"):
        truth_solve(d, h, E, truth_mesh, cache)
    click.echo(f"{len(todo)} solves ({len(ph)} phantoms + {n} lesions) in {time.perf_counter() - t0:.0f} s", err=True)


if __name__ == "__main__":
    from elastimap.cli_util import run

    sys.exit(run(main, prog_name="workflows/frames_benchmark.py"))
