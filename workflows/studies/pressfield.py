"""The press correction (:func:`elastimap.camera.deflection.press_correction`) on a SYNTHETIC variant world,
through the camera.

    python -m elastimap.workflows.studies.pressfield --world-level coarse --product tiny --frames 30
    python -m elastimap.workflows.studies.pressfield --world-level coarse --product tiny --grid
    python -m elastimap.workflows.studies.pressfield --world-level default --product coarse --fits

The world: elastimap's remeshing solver at ``--world-level``, sized by d, with the contact interface, at the
nine calibration-phantom designs and three further lesions (:func:`elastimap.workflows.studies.modelform.variant_world`;
its background press differs from the product's).  Each of the twelve is rendered through the nominal
SYNTHETIC camera (``--frames`` lesion and background frames, one draw).  The lab's calibration: the nine
phantoms' FEM solves at ``--product`` (the remeshing solver, as ``camera calibrate --mesh`` solves them)
and their frames (:func:`elastimap.camera.calibration.deflection_calibration`), without (``before``) and
with (``after``) the press correction.

Scored per lesion, without any fit: the recovered difference image minus the world's own
(``chain``: relative rms over the image), and the fit's d, h, ln E bias linearised at the truth (one
generalised least-squares step, weights the recovered image's own sd, the ``--product`` map's exact
derivative) on the recovered minus the world's image (``chain``: the camera chain's part) and on the
recovered image minus the ``--product`` map (``total``: what the closed fit would be off by).  ``--grid`` scores the
settings' grid this way (how they were chosen).  ``--fits``: also the product's fit (``infer --refine``'s
maps at ``--product``, carrying the model-form term learnt from the nine: each phantom with the term and
the deflection calibration of all nine, fitted by :func:`elastimap.camera.calibration.loo_fits` with the
term learnt from the other eight; lesions 10-12 with the term of all nine, from the same kind of start).
Self-consistency only (elastimap's own solver on both sides).
"""

from __future__ import annotations

import itertools
import json
import os
import time

import click
import numpy as np

from elastimap.cli_util import MeshLevel, run

from . import modelform as mf

PIXEL = mf.PIXEL


class _Result:
    def __init__(self, z):
        self.image, self.image_raw, self.pixel = z["image"], z["image_raw"], PIXEL


def calibration_solves(thetas, mesh: str, cache: str) -> list:
    """The phantoms' FEM at ``mesh`` as ``camera calibrate`` solves them (remeshing, fixed sizing, tied)."""
    from elastimap.workflows.solves import cached_solve

    return [_Result(cached_solve(*map(float, th), mesh=mesh, cache=os.path.join(cache, "solves"))) for th in thetas]


def render(world, frames: int, seed: int) -> list:
    """(lesion, background) frame stacks of each world press through the nominal SYNTHETIC camera."""
    from elastimap.camera.optics import SensorModel, render_pair

    rng = np.random.default_rng(seed)
    s = SensorModel()
    return [render_pair(s, ph["ref"] + ph["diff"], ph["diff"], PIXEL, frames, rng) for ph in world]


def chain_scores(world, pairs, defl, model) -> list[dict]:
    """Per lesion: relative rms of (recovered - world image) and its linearised d, h, ln E bias (%)."""
    from elastimap.camera.calibration import recovered_images

    rows = []
    for ph, rec in zip(world, recovered_images(pairs, defl), strict=True):
        th = ph["theta"]
        m, J = model[mf.key(th)]
        Jx, X = mf.fit_jacobian(th, J)
        s = np.asarray(rec.sigma, float).ravel()
        A = Jx / s[:, None]
        H = np.linalg.pinv(A.T @ A)
        e = np.asarray(rec.image, float) - ph["diff"]
        G = X.dtheta(X.x(th)) @ H @ A.T  # one generalised least-squares step in (d, h, ln E)

        def step(r, G=G, th=th, s=s):
            dt = G @ (np.ravel(r) / s)
            return [100 * dt[0] / th[0], 100 * dt[1] / th[1], 100 * dt[2]]

        rows.append(
            {
                "phantom": ph["phantom"],
                "theta": th.tolist(),
                "chain_rel_rms": float(np.linalg.norm(e) / np.linalg.norm(ph["diff"])),
                "chain_bias_pct": step(e),
                "total_bias_pct": step(np.asarray(rec.image, float) - m),
            }
        )
    return rows


def calibrate(results, pairs, press: bool, **settings) -> dict:
    """The deflection calibration of the nine (``settings``: the press correction's, default the shipped)."""
    from elastimap.camera import calibration as C
    from elastimap.camera.optics import SensorModel

    return C.deflection_calibration(results, pairs, SensorModel(), press=(settings or True) if press else False)


def product_fits(world, pairs, defl, level: str) -> list[dict]:
    """The product's fit of all twelve (module docstring); rows as :func:`loo_fits` gives them."""
    import pandas as pd

    from elastimap.camera import calibration as C
    from elastimap.camera.optics import SensorModel
    from elastimap.identify.discrepancy import Discrepancy
    from elastimap.identify.fit import fit_image
    from elastimap.identify.forward_maps import fit_maps

    ph = pd.DataFrame(
        [{"name": w["phantom"], "d": w["theta"][0], "h": w["theta"][1], "E": w["theta"][2]} for w in world[: mf.N_CAL]]
    )
    s = SensorModel()
    rec9 = C.learn_discrepancy(ph, pairs[: mf.N_CAL], defl, level, s)
    rows = C.loo_fits(rec9, ph, pairs[: mf.N_CAL], defl, s)["rows"]
    disc = Discrepancy.from_dict(rec9["term"])  # the term of all nine, as infer --refine loads it
    maps = fit_maps(*C.refine_levels(level))
    th9 = np.array([w["theta"] for w in world[: mf.N_CAL]])
    start = np.array([th9[:, 0].mean(), th9[:, 1].mean(), float(np.exp(np.log(th9[:, 2]).mean()))])
    for w, rec in zip(world[mf.N_CAL :], C.recovered_images(pairs[mf.N_CAL :], defl), strict=True):
        th = w["theta"]
        t0 = time.process_time()
        r = fit_image(
            rec.image,
            rec.sigma,
            start,
            maps.forward,
            forward_alt=maps.forward_alt,
            forward_fine=maps.forward_fine,
            discrepancy=disc,
            pixel=PIXEL,
        )
        rows.append(
            {
                "name": w["phantom"],
                "truth": th.tolist(),
                "theta": r.theta.tolist(),
                "lo": r.lo.tolist(),
                "hi": r.hi.tolist(),
                "covered": [bool(r.lo[j] <= th[j] <= r.hi[j]) for j in range(3)],
                "reported": [bool(r.relstd[j] <= 0.10 and not r.at_bound) for j in range(3)],
                "at_bound": r.at_bound,
                "seconds": time.process_time() - t0,
            }
        )
    return rows


def fit_summary(rows) -> dict:
    cov = np.array([r["covered"] for r in rows], bool)
    rep = np.array([r["reported"] for r in rows], bool)
    err = np.array([(np.array(r["theta"]) - r["truth"]) / np.array(r["truth"]) for r in rows])
    return {
        "n": len(rows),
        "covered": cov.sum(axis=0).tolist(),
        "reported": rep.sum(axis=0).tolist(),
        "mre_reported_pct": [
            float(100 * np.abs(err[rep[:, j], j]).mean()) if rep[:, j].any() else float("nan") for j in range(3)
        ],
        "bias_reported_pct": [
            float(100 * err[rep[:, j], j].mean()) if rep[:, j].any() else float("nan") for j in range(3)
        ],
        "reported_missed": (rep & ~cov).sum(axis=0).tolist(),
        "E_at_edge": int(sum("E" in r["at_bound"] for r in rows)),
        "at_edge_printed": int(sum(bool(r["at_bound"]) and any(r["reported"]) for r in rows)),
    }


def chain_summary(rows) -> str:
    b = np.array([r["chain_bias_pct"] for r in rows])
    t = np.array([r["total_bias_pct"] for r in rows])
    rel = np.array([r["chain_rel_rms"] for r in rows])
    return (
        f"chain rel rms median {100 * np.median(rel):.2f} %; mean |bias| d/h (chain) {np.abs(b[:, 0]).mean():.1f}/"
        f"{np.abs(b[:, 1]).mean():.1f} %, (total) {np.abs(t[:, 0]).mean():.1f}/{np.abs(t[:, 1]).mean():.1f} %"
        f" [without the 12 lesions' worst d: {np.sort(np.abs(t[:, 0]))[:-1].mean():.1f} %]"
    )


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--world-level", type=MeshLevel(), default="coarse", show_default=True, help="The variant world's level.")
@click.option(
    "--product", type=MeshLevel(), default="tiny", show_default=True, help="The calibration's and fit's level."
)
@click.option("--frames", default=30, show_default=True, type=click.IntRange(2, 1000), help="Camera frames per press.")
@click.option("--seed", default=0, show_default=True, type=int, help="Camera noise seed.")
@click.option("--grid", is_flag=True, help="Score the settings' grid (chain only).")
@click.option("--fits", is_flag=True, help="Also the product's fits, before and after (and each --press).")
@click.option(
    "--press",
    "extra",
    multiple=True,
    help="Also these press-correction settings: ELL_MM,PRIOR_MM,FORM (repeatable).",
)
@click.option("--cache", default="runs/modelform-cache", show_default=True, help="Folder of the solves.")
@click.option(
    "--out", default=None, type=click.Path(dir_okay=False), help="Write the rows here (.json; must not exist)."
)
def main(world_level, product, frames, seed, grid, fits, extra, cache, out):
    """Camera chain of a variant world without and with the press correction."""
    from elastimap.errors import UserError

    if out and os.path.exists(out):
        raise UserError("--out", f"{out} exists; choose another name")
    world = mf.variant_world(world_level, cache)
    thetas = [w["theta"] for w in world]
    results = calibration_solves(thetas[: mf.N_CAL], product, cache)
    model = mf.model_at(thetas, product, cache)
    pairs = render(world, frames, seed)
    result = {"world": f"elastimap remesh {world_level}, by_d, contact (SYNTHETIC)", "product": product}
    result.update(frames=frames, seed=seed, runs={})
    runs = {"before": {"press": False}, "after": {"press": True}}
    for e in extra:
        try:
            ell, tau, form = (float(v) for v in e.split(","))
        except ValueError:
            raise UserError("--press", f"ELL_MM,PRIOR_MM,FORM (got {e!r})") from None
        runs[f"ell {ell:g} tau {tau:g} form {form:g}"] = {"press": True, "ell_mm": ell, "prior_mm": tau, "form": form}
    if grid:
        for ell, tau, form in itertools.product((0.5, 1.0, 2.0), (0.003, 0.01, 0.03), (0.005, 0.01, 0.02)):
            runs[f"ell {ell} tau {tau} form {form}"] = {"press": True, "ell_mm": ell, "prior_mm": tau, "form": form}
    for name, kw in runs.items():
        t0 = time.process_time()
        defl = calibrate(results, pairs[: mf.N_CAL], **kw)
        rows = chain_scores(world, pairs, defl, model)
        pc = defl.get("press_correction")
        dmax = float(np.abs(np.asarray(pc["delta"])).max()) if pc else 0.0
        click.echo(
            f"{name:32s} scale {defl['scale']:.4f}  |δ| max {dmax:.4f} mm  {chain_summary(rows)}"
            f"  ({time.process_time() - t0:.0f} s)"
        )
        run_ = {"settings": kw, "scale": defl["scale"], "delta_max_mm": dmax, "chain": rows}
        if fits and (name in ("before", "after") or name.startswith("ell") and not grid):
            fr = product_fits(world, pairs, defl, product)
            run_["fits"] = {"rows": fr, "summary": fit_summary(fr)}
            for r in fr:
                click.echo(
                    f"  {r['name']} truth {np.round(r['truth'], 2).tolist()} fit {np.round(r['theta'], 2).tolist()}"
                    f" covered {r['covered']} printed {r['reported']} edge {r['at_bound']} {r['seconds']:.1f} s"
                )
            click.echo(f"  fits: {json.dumps(run_['fits']['summary'])}")
        result["runs"][name] = run_
    if out:
        with open(out, "w") as fh:
            json.dump(result, fh, indent=1)


if __name__ == "__main__":
    import sys

    run(main, sys.argv[1:], prog_name="python -m elastimap.workflows.studies.pressfield")
