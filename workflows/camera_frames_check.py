"""Bounded accuracy check of inference from SYNTHETIC camera frames (image model, --refine).

Held-out lesions (a Latin hypercube over the design box with its own seed, not the sweep's
points) are solved on ``--mesh``, rendered to ``--frames`` lesion + background frames by the
nominal synthetic camera (its own noise seed), and estimated three ways:

* ``network (FEM image)``  - the image model on the noise-free FEM difference image (no camera);
* ``frames -> network``    - frames -> inverse response -> FEM-equivalent image -> the image model;
* ``frames -> refine``     - that estimate refined by the maximum-likelihood FEM fit, every pixel
  weighted by its noise from the frames' scatter (the first ``--refine-n`` lesions).

Reports per output the mean relative error, the fraction of lesions whose interval ``[lo, hi]``
holds the truth, and how many were reportable (printed as a number).  The calibration (nine
phantoms) and, unless ``--model`` is given, the image model (trained on ``--data``) are made here.

    .venv/bin/python workflows/camera_frames_check.py --data SWEEP --mesh tiny --n 20 --refine-n 4 --out runs/frames-check

The ≥ 100-lesion benchmark, with the lesion data from another discretisation than the fit's map,
is ``workflows/frames_benchmark.py``.
"""

from __future__ import annotations

import copy
import json
import os
import sys
import time

import click
import numpy as np

from elastimap.dataset.schema import THICKNESS


def _lesions(n: int, seed: int) -> np.ndarray:
    from scipy.stats import qmc

    from elastimap.solver.params import depth_range

    u = qmc.LatinHypercube(d=3, seed=seed).random(n)
    d = 2.0 + 13.0 * u[:, 0]
    h = np.array([depth_range(di)[0] + ui * (depth_range(di)[1] - depth_range(di)[0]) for di, ui in zip(d, u[:, 1])])
    E = np.exp(np.log(10.0) + np.log(20.0) * u[:, 2])
    return np.column_stack([d, h, E])


def _table(name: str, truth: np.ndarray, ests) -> list[str]:
    est = np.array([e.mean for e in ests])
    lo = np.array([e.lo if e.lo is not None else np.full(3, np.nan) for e in ests])
    hi = np.array([e.hi if e.hi is not None else np.full(3, np.nan) for e in ests])
    rep = np.array([[e.reportable(q) for q in "dhE"] for e in ests])
    rel = np.abs(est - truth) / truth
    cov = (lo <= truth) & (truth <= hi)
    cells = []
    for j in range(3):
        r = rel[rep[:, j], j]
        cells.append(
            f"{100 * rel[:, j].mean():.1f} % | {100 * (np.median(rel[:, j])):.1f} % | "
            f"{100 * r.mean() if r.size else float('nan'):.1f} % ({rep[:, j].sum()}) | {100 * cov[:, j].mean():.0f} %"
        )
    return [f"| {name} | {len(ests)} | " + " | ".join(cells) + " |"]


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--data", "data_path", required=True, help="Sweep with stored images (trains the image model).")
@click.option("--model", "model_dir", default=None, help="An image model instead of training one on --data.")
@click.option("--mesh", default="tiny", show_default=True, help="The sweep's mesh (lesions, phantoms, refine).")
@click.option("--n", "n", default=20, show_default=True, type=int, help="Held-out lesions.")
@click.option("--refine-n", default=4, show_default=True, type=int, help="How many of them to refine.")
@click.option("--frames", default=30, show_default=True, type=int)
@click.option("--seed", default=101, show_default=True, type=int, help="Seed of the held-out design and the noise.")
@click.option("--cache", default="data/identify/solves", show_default=True, help="Solve cache.")
@click.option("--out", required=True)
def main(data_path, model_dir, mesh, n, refine_n, frames, seed, cache, out):
    from elastimap.camera import calibration as C
    from elastimap.camera.deflection import difference_image
    from elastimap.camera.features import FeatureSettings
    from elastimap.camera.infer import estimate_fem_images, load_identifiability, refine_estimates
    from elastimap.camera.optics import SensorModel, render_pair
    from elastimap.workflows.studies.solves import cached_solve

    os.makedirs(out, exist_ok=True)
    t0 = time.perf_counter()
    log = open(os.path.join(out, "log.txt"), "a")

    def say(msg):
        click.echo(msg, err=True)
        log.write(msg + "\n")
        log.flush()

    if model_dir is None:
        from elastimap.identify.imagenet import fit_image_model
        from elastimap.identify.measure import load
        from elastimap.training.experiment import TrainConfig

        data = load(data_path, design_only=True)
        model = fit_image_model(
            data,
            "scg",
            repeats=4,
            cfg=TrainConfig(hidden=((12, "tansig"), (6, "tansig")), epochs=300, progress=False),
            k=10,
            image_noise=0.01,
            log_e=True,
        )
        model_dir = os.path.join(out, "image-model")
        os.makedirs(model_dir, exist_ok=True)
        model.save(model_dir)
        say(
            f"image model: scg, 4 members, k 10, 10-12-6-3, ln E, 300 epochs, 1 % image noise, {data.n} rows of {data_path} "
            f"({time.perf_counter() - t0:.0f} s)"
        )
    from elastimap.camera.infer import load_model

    model = load_model(model_dir)
    sensor = SensorModel(seed=seed)

    def fem(d, h, E, tissue_E=5.0, thickness=THICKNESS):
        from types import SimpleNamespace

        from elastimap.solver.image import features

        r = cached_solve(d, h, E, mesh=mesh, cache=cache)
        o = features(r["image"], 0.5)
        return SimpleNamespace(image=r["image"], image_raw=r["image_raw"], pixel=0.5, O1=o[0], O2=o[1], O3=o[2])

    t = time.perf_counter()
    pairs = []
    ph = C.load_phantoms()
    fem_f, cam_f, res = C.simulate_phantoms(ph, fem, sensor, FeatureSettings(), frames, seed, frames_out=pairs)
    defl = C.deflection_calibration(res, pairs, sensor)
    cal = C.fit_calibration(ph, fem_f, cam_f, FeatureSettings().to_dict(), sensor.to_dict(), True, {"mesh": mesh}, defl)
    cal.save(os.path.join(out, "cal.json"))
    say(
        f"calibration: scale {defl['scale']:.4f}, phantom rel. rms {min(defl['rel_rms']):.3f}-{max(defl['rel_rms']):.3f}"
        f" ({time.perf_counter() - t:.0f} s)"
    )
    ref, pixel = cal.reference_image()
    idm = load_identifiability("default")
    truth = _lesions(n, seed)
    rng = np.random.default_rng([seed, 1])
    fem_imgs, di = [], []
    t = time.perf_counter()
    for i, (d, h, E) in enumerate(truth):
        r = fem(d, h, E)
        F, B = render_pair(sensor, r.image_raw, r.image, r.pixel, frames, rng)
        di.append(difference_image(F, B, sensor, ref, pixel, scale=defl["scale"]))
        fem_imgs.append(r.image)
        z = (di[-1].image - r.image) / di[-1].sigma
        say(
            f"lesion {i}: d {d:.2f} h {h:.2f} E {E:.1f}  peak {r.image.max():.4g} mm, recovered "
            f"{di[-1].peak:.4g}, z rms {np.sqrt(np.mean(z**2)):.2f}"
        )
    t_frames = time.perf_counter() - t
    ids = [str(i) for i in range(n)]
    net = estimate_fem_images(np.array(fem_imgs), model, ids, idm)
    cam = estimate_fem_images(np.array([x.image for x in di]), model, ids, idm, sigma=np.array([x.sigma for x in di]))
    lines = [
        "| estimator | lesions | d MRE | d median | d MRE reportable (n) | d coverage | h MRE | h median | "
        "h MRE reportable (n) | h coverage | E MRE | E median | E MRE reportable (n) | E coverage |",
        "|" + "---|" * 14,
    ]
    lines += _table("network (FEM image, no camera)", truth, net)
    lines += _table("frames -> network", truth, cam)
    zr = [float(np.sqrt(np.mean(((x.image - f) / x.sigma) ** 2))) for x, f in zip(di, fem_imgs)]
    extra = [f"recovered image vs FEM image: z rms median {np.median(zr):.2f} (max {np.max(zr):.2f}) over {n} lesions"]
    if refine_n > 0:
        sub = [copy.deepcopy(cam[i]) for i in range(min(refine_n, n))]  # cam stays the network's
        t = time.perf_counter()
        times = []

        def progress(i, k):
            times.append(time.perf_counter())

        ref_ests = refine_estimates(sub, None, mesh=mesh, progress=progress)
        wall = time.perf_counter() - t
        lines += _table("network (FEM image) [refined subset]", truth[: len(sub)], net[: len(sub)])
        lines += _table(
            "frames -> network [refined subset]",
            truth[: len(sub)],
            estimate_fem_images(np.array([x.image for x in di[: len(sub)]]), model, ids[: len(sub)], idm),
        )
        lines += _table("frames -> refine", truth[: len(sub)], ref_ests)
        ts = time.perf_counter()
        cached_solve(8.1234, 7.0, 50.0, mesh=mesh, cache=os.path.join(out, "timing-cache"))
        one = time.perf_counter() - ts
        extra.append(
            f"refine (maximum-likelihood fit, elastimap.identify.refine.fit_image): {wall / len(sub):.0f} s per lesion ({len(sub)} lesions); one uncached "
            f"{mesh}-mesh solve (inclusion + reference) took {one:.1f} s at the time"
        )
        with open(os.path.join(out, "refined.json"), "w") as fh:
            json.dump([e.to_dict() for e in ref_ests], fh, indent=2)
    md = (
        "\n".join(
            [
                f"SYNTHETIC camera frames, {n} held-out lesions (LHS seed {seed}), mesh {mesh}, {frames} frames, "
                f"model {model_dir}; frames {t_frames:.0f} s; total {time.perf_counter() - t0:.0f} s",
                "",
            ]
            + lines
            + [""]
            + extra
        )
        + "\n"
    )
    with open(os.path.join(out, "results.md"), "w") as fh:
        fh.write(md)
    with open(os.path.join(out, "estimates.json"), "w") as fh:
        json.dump(
            {"truth": truth.tolist(), "network": [e.to_dict() for e in net], "frames": [e.to_dict() for e in cam]},
            fh,
            indent=2,
        )
    click.echo(md)


if __name__ == "__main__":
    from elastimap.cli_util import run

    sys.exit(run(main, prog_name="workflows/camera_frames_check.py"))
