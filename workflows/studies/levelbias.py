"""How far each mesh level of the morphed forward map is from a finer world, and where it moves (d, h, E).

    elastimap study levelbias --n 10 --seed 99 --world fine --levels coarse,default,fine
    elastimap study levelbias --n 10 --seed 99 --world fine --levels coarse \\
        --coarse-sizes 1.1,14,0.45,10

Calibration lesions (SYNTHETIC; a Latin hypercube over the design box like the frames benchmark's,
with another seed, so none of them is a benchmark lesion).  At each lesion θ = (d, h, E):

* the world's difference image w (mm): the remeshing solver at ``--world`` (gmsh mesh at θ itself);
* each level's morphed map m_L(θ) and its exact derivative J = ∂m/∂(d, h, E) (one solve and three
  back-solves on the bin's reference mesh, :meth:`elastimap.identify.forward_maps.ForwardMap.tangent`);
* the image error rms(w − m_L) / peak(w) and the relative parameter shift s that it causes to first
  order, the unweighted least-squares solution of (J diag θ) s = w − m_L: a fit on m_L of the
  noise-free world image lands near θ (1 + s).  The shift runs along the d–h–E valley, so its E part
  can be large even where the image error is small.

``--coarse-sizes h0,h_max,grading,per_d`` replaces the ``coarse`` level's sizes (mm; see
:data:`elastimap.solver.geometry.LEVELS`) for this process only: which part of a finer level removes
the coarse level's bias (docs/camera.md, 'Inference').  Prints one row per lesion and level and a summary;
``--out FILE.json`` keeps the rows.
"""

from __future__ import annotations

import json
import os
import time

import click
import numpy as np

from elastimap.cli_util import MeshLevel, run


def level_errors(theta: np.ndarray, world: np.ndarray, fmap) -> dict:
    """Image error of the map ``fmap`` (a :class:`~elastimap.identify.forward_maps.ForwardMap`) at ``theta``
    against the world's image ``world`` (mm) and the first-order relative shift it causes."""
    d, h, E = (float(v) for v in theta)
    t = time.process_time()
    res, J = fmap.pin(d, h).tangent(d, h, E)
    cpu = time.process_time() - t
    diff = world - np.asarray(res.image, float)
    peak = float(np.abs(world).max())
    Jr = np.asarray(J, float).reshape(3, -1).T * np.array([d, h, E])
    shift, *_ = np.linalg.lstsq(Jr, diff.ravel(), rcond=None)
    return {
        "rms_pct": float(100 * np.sqrt(np.mean(diff**2)) / peak),
        "max_pct": float(100 * np.abs(diff).max() / peak),
        "shift_pct": [float(v) for v in 100 * shift],
        "cpu_seconds": cpu,
    }


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--n", "n", default=10, show_default=True, type=click.IntRange(1, 500), help="Calibration lesions.")
@click.option(
    "--seed", default=99, show_default=True, type=int, help="Their Latin-hypercube seed (the benchmark's is 2026)."
)
@click.option(
    "--world",
    "mesh",
    type=MeshLevel(),
    default="fine",
    show_default=True,
    help="Mesh level of the world's remeshing solver.",
)
@click.option("--levels", default="coarse,default,fine", show_default=True, help="Morphed map levels, comma-separated.")
@click.option(
    "--coarse-sizes", default=None, help="h0,h_max,grading,per_d replacing the coarse level's (this process only)."
)
@click.option("--cache", default="runs/levelbias-cache", show_default=True, help="Folder of the world's solves.")
@click.option(
    "--out", default=None, type=click.Path(dir_okay=False), help="Also write the rows here (.json; must not exist)."
)
def main(n, seed, mesh, levels, coarse_sizes, cache, out):
    """Image error of each morphed level against the remeshing world and the (d, h, E) shift it causes."""
    from elastimap.errors import UserError
    from elastimap.identify.forward_maps import forward_map
    from elastimap.solver import geometry
    from elastimap.solver.params import MESH_LEVELS
    from elastimap.workflows.benchmarks.frames import draw_lesions
    from elastimap.workflows.solves import cached_solve

    names = [v.strip() for v in levels.split(",") if v.strip()]
    bad = [v for v in names if v not in MESH_LEVELS]
    if not names or bad:
        raise UserError("--levels", f"comma-separated levels of {', '.join(MESH_LEVELS)} (got {levels!r})")
    if out and os.path.exists(out):
        raise UserError("--out", f"{out} exists; choose another name")
    if coarse_sizes:
        try:
            sizes = tuple(float(v) for v in coarse_sizes.split(","))
        except ValueError:
            sizes = ()
        if len(sizes) != 4 or min(sizes) <= 0:
            raise UserError("--coarse-sizes", f"four positive numbers h0,h_max,grading,per_d (got {coarse_sizes!r})")
        geometry.LEVELS["coarse"] = sizes
    maps = {v: forward_map(v, "morph") for v in names}
    rows = []
    for theta in draw_lesions(n, seed):
        w = np.asarray(cached_solve(*(float(v) for v in theta), mesh=mesh, cache=cache)["image"], float)
        row = {"theta": [float(v) for v in theta], "world": f"remeshing solver, {mesh} mesh", "synthetic": True}
        for v, f in maps.items():
            row[v] = level_errors(theta, w, f)
        rows.append(row)
        click.echo(
            f"d={theta[0]:5.2f} h={theta[1]:5.2f} E={theta[2]:6.1f}  "
            + " | ".join(
                f"{v}: rms {row[v]['rms_pct']:.2f} %, shift d {row[v]['shift_pct'][0]:+.1f} h {row[v]['shift_pct'][1]:+.1f}"
                f" E {row[v]['shift_pct'][2]:+.0f} %"
                for v in maps
            )
        )
    for v in maps:
        sh = np.abs(np.array([r[v]["shift_pct"] for r in rows]))
        rms = np.array([r[v]["rms_pct"] for r in rows])
        click.echo(
            f"{v}{' (sizes ' + coarse_sizes + ')' if coarse_sizes and v == 'coarse' else ''}: image error rms "
            f"median {np.median(rms):.2f} % of the peak; mean |shift| d {sh[:, 0].mean():.1f} %, h {sh[:, 1].mean():.2f} %, "
            f"E {sh[:, 2].mean():.0f} %; CPU {np.mean([r[v]['cpu_seconds'] for r in rows]):.2f} s per solve + derivative"
        )
    if out:
        with open(out, "w") as fh:
            json.dump(
                {"synthetic": True, "seed": seed, "world": mesh, "coarse_sizes": coarse_sizes, "rows": rows},
                fh,
                indent=1,
            )


if __name__ == "__main__":
    import sys

    run(main, sys.argv[1:], prog_name="elastimap study levelbias")
