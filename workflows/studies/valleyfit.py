"""Where a camera-frame fit's pull along the d–E valley comes from: re-fit chosen lesions of a frames
benchmark folder with one ingredient changed at a time.

    elastimap study valleyfit --out runs/fb29 --n 120 --seed 2029 --lesions 2,60 \\
        --image world --start truth --maps fixed --fit corrected

A lesion of the benchmark (``workflows/frames_benchmark.py``; SYNTHETIC: its world solve in
``OUT/solves``, its calibration ``OUT/cal-morph-coarse-corr-fine.json``, the start network
``--model``; ``--n`` and ``--seed`` must be the benchmark's, checked against its records) is
re-fitted by :func:`elastimap.identify.fit.fit_image` with:

* ``--image frames``: the difference image recovered from the lesion's drifting-camera frames (the
  benchmark's own, :func:`~elastimap.workflows.benchmarks.frames.lesion_inputs`: same noise seeds)
  and its per-pixel noise; ``world``: the world's noise-free difference image with the same
  per-pixel noise (what the fit would do without camera noise);
* ``--start network``: the network's estimate and the E scan (the shipped fit); ``truth``: the true
  (d, h, E), no scan (whether the likelihood's maximum itself is off, or the way to it);
* ``--maps fixed``: the morphed maps with the fixed element sizing the shipped fit uses; ``by_d``:
  the ``by_d`` sizing of the world (docs/forward-model.md) on every level;
* ``--fit corrected``: the shipped fit, ``coarse`` defect-corrected by ``fine``, model error against
  ``default``; ``fine``: the ``fine`` map alone (model error against ``default``).

The calibration is the benchmark's (its FEM side from the fixed-sizing ``fine`` map) for every
variant.  Prints one row per lesion: the estimate, its error against the truth, the fit's own d
standard deviation, whether each 95 % interval holds the truth, the evaluations (fit level + model
error level + correcting level) and the CPU seconds (time it with nothing else running).  A study
of seen lesions: it diagnoses, nothing in it is a held-out score.
"""

from __future__ import annotations

import json
import os
import time

import click
import numpy as np

from elastimap.cli_util import run

IMAGES = ("frames", "world")
STARTS = ("network", "truth")
MAPS = ("fixed", "by_d")
FITS = ("corrected", "fine")


def _maps(sizing: str) -> dict:
    """The morphed maps of the three levels with element sizing ``sizing``."""
    from elastimap.identify.forward_maps import forward_map

    return {v: forward_map(v, "morph", sizing=sizing) for v in ("coarse", "default", "fine")}


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--out", "out", required=True, type=click.Path(file_okay=False), help="The frames benchmark folder.")
@click.option("--n", "n", required=True, type=click.IntRange(1, 100000), help="Its --n (the design).")
@click.option("--seed", required=True, type=int, help="Its --seed.")
@click.option("--lesions", required=True, help="Lesion indices, comma-separated (e.g. 2,60).")
@click.option("--model", default="runs/fb27/image-model", show_default=True, help="The start network.")
@click.option("--image", type=click.Choice(IMAGES), default="frames", show_default=True, help="Image fitted.")
@click.option("--start", type=click.Choice(STARTS), default="network", show_default=True, help="Where the fit starts.")
@click.option("--maps", type=click.Choice(MAPS), default="fixed", show_default=True, help="Element sizing of the maps.")
@click.option("--fit", "fit", type=click.Choice(FITS), default="corrected", show_default=True, help="Levels fitted.")
def main(out, n, seed, lesions, model, image, start, maps, fit):
    """Re-fit benchmark lesions with one ingredient changed (SYNTHETIC; seen lesions)."""
    from elastimap.camera import calibration as C
    from elastimap.camera.infer import load_identifiability, load_model
    from elastimap.camera.optics import SensorModel
    from elastimap.errors import UserError
    from elastimap.identify.fit import fit_image
    from elastimap.workflows.benchmarks.frames import draw_lesions, lesion_inputs, run_tags

    try:
        idx = [int(v) for v in lesions.split(",") if v.strip()]
    except ValueError:
        idx = []
    if not idx or min(idx) < 0 or max(idx) >= n:
        raise UserError("--lesions", f"comma-separated indices in 0..{n - 1} (got {lesions!r})")
    cal_tag, fits_tag = run_tags("morph", "coarse", "fine", ["default"], "contrast", "drift")  # the shipped fit's run
    cal_path = os.path.join(out, f"cal-{cal_tag}.json")
    if not os.path.exists(cal_path):
        raise UserError("--out", f"{cal_path} not found: run the benchmark's `run` stage first")
    truth = draw_lesions(n, seed)
    fits = os.path.join(out, f"fits-{fits_tag}")
    frames = {}
    for i in idx:  # the benchmark's own record of each lesion: same design, world solve present
        path = os.path.join(fits, f"lesion-{i:04d}.json")
        if not os.path.exists(path):
            raise UserError("--lesions", f"lesion {i} has no record in {fits}: run the benchmark's `run` stage first")
        with open(path) as fh:
            rec = json.load(fh)
        if not np.allclose(rec["truth"], truth[i], rtol=1e-9):
            raise UserError("--seed", f"lesion {i} of {out} is another lesion than --n {n} --seed {seed} draws")
        frames[i] = int(rec.get("frames", 30))
    cal = C.Calibration.load(cal_path)
    if SensorModel.from_dict(cal.sensor or {}) != SensorModel(seed=seed):
        raise UserError("--seed", f"{cal_path} was made with another camera seed")
    net_model, idm = load_model(model), load_identifiability("default")
    sensor = SensorModel(seed=seed)
    m = _maps(maps)
    if fit == "corrected":
        fwd, kw = m["coarse"], {"forward_alt": [m["default"]], "forward_fine": m["fine"]}
    else:
        fwd, kw = m["fine"], {"forward_alt": [m["default"]]}
    for i in idx:
        d, h, E = (float(v) for v in truth[i])
        one = lesion_inputs(i, truth[i], seed, sensor, cal, net_model, idm, out, "fine", "by_d", "drift", frames[i])
        w, di, net = one.world, one.recovered, one.network
        side = int(round(np.sqrt(di.image.size)))
        img = (np.asarray(w["image"], float) if image == "world" else np.asarray(di.image, float)).reshape(side, side)
        sig = np.asarray(di.sigma, float).reshape(side, side)
        th0 = np.asarray(truth[i], float) if start == "truth" else np.asarray(net.mean, float)
        c0 = time.process_time()
        r = fit_image(img, sig, th0, fwd, e_scan=0 if start == "truth" else 5, **kw)
        cpu = time.process_time() - c0
        cov = "".join("y" if r.lo[j] <= truth[i][j] <= r.hi[j] else "n" for j in range(3))
        click.echo(
            f"lesion {i} (SYNTHETIC; {image} image, {start} start, {maps} maps, {fit}): truth {d:.2f}/{h:.2f}/{E:.0f}"
            f"  fit {r.theta[0]:.2f}/{r.theta[1]:.2f}/{r.theta[2]:.0f}  d {100 * (r.theta[0] / d - 1):+.1f} %"
            f"  E {100 * (r.theta[2] / E - 1):+.0f} %  d sd {100 * r.relstd[0]:.1f} %  holds d/h/E {cov}"
            f"  {r.n_solves}+{r.n_alt}+{r.n_fine} evaluations  {cpu:.1f} s CPU"
            + ("" if r.converged else "  still moving")
        )


if __name__ == "__main__":
    import sys

    run(main, sys.argv[1:], prog_name="elastimap study valleyfit")
