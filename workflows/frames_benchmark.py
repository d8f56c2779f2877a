"""Benchmark of inference from SYNTHETIC camera frames: image network -> physics fit.

Stage ``lesions`` (no fit needed, run it first): held-out lesions drawn by a Latin hypercube over
the WHOLE design box (d 2-15 mm, the admissible centre depth, E 10-200 kPa log-uniform; own seed,
not the sweep's points) and the nine calibration phantoms, solved by the "world" forward model --
the remeshing solver on ``--truth-mesh`` (default ``default``), a different discretisation than the
fit's forward map -- and kept in the solve store ``OUT/solves``.  Resumable: solved lesions are
read back; ``--shard K/N`` splits the solves between processes, ``--first K`` solves only the
first K lesions of the design (a subset on a costlier world, e.g. ``--truth-mesh fine``).
Everything it makes is SYNTHETIC.

    OMP_NUM_THREADS=1 .venv/bin/python workflows/frames_benchmark.py lesions --n 120 --out runs/frames-bench

Stage ``network``: the start network (the image model's SCG ensemble, the recipe of docs/camera.md
4d) trained on a sweep's design rows, into ``OUT/image-model``.

    .venv/bin/elastimap sweep run --n 160 --mesh tiny --seed 0 --jobs 1 --out runs/sweep-tiny160
    .venv/bin/python workflows/frames_benchmark.py network --sweep runs/sweep-tiny160 --out runs/frames-bench

Stage ``run``: the calibration (the nine phantoms' frames rendered from the world's solves, their
FEM side -- reference press, scale, feature lines -- from the fit's forward map), then per lesion
30 lesion + 30 background frames from the nominal SYNTHETIC camera (own noise seed per lesion) ->
the FEM-equivalent difference image and its per-pixel noise (:mod:`elastimap.camera.deflection`) ->
the image network (``--model``) -> the maximum-likelihood fit on the forward map at ``--fit-mesh``
(:func:`elastimap.camera.infer.refine_estimates`), its model error measured against
``--error-mesh`` (default: the neighbouring coarser level).  ``--correct-mesh LEVEL`` (finer than
``--fit-mesh``) defect-corrects the fit's map by that level at the start of every pass after the
first (``fit_image(forward_fine=...)``); the fit then stands for that level (the calibration's
FEM side is solved on it) and its model error is measured against that level's neighbour.  One
JSON file per lesion in ``OUT/fits`` (resumable; a folder holding lesions of another design --
another ``--seed``, ``--n``, ``--inside`` or ``--outside`` -- is refused; ``--shard K/N`` splits the lesions between
processes; the calibration and the fits are kept per forward map, ``OUT/cal-<tag>.json`` and
``OUT/fits-<tag>``, tag ``<geometry>-<mesh>`` plus ``-corr-<level>`` with ``--correct-mesh`` and
``-err-<level>`` when ``--error-mesh`` is not the default).  Measurement knobs (docs/camera.md 4j),
each marked in the tag: ``--correct-sizing by_d`` sizes the correcting level and its model-error
level by d (``-corr-<level>-by_d``); ``--fine-mode direct`` makes the passes after the first fit
the correcting level itself instead of correcting the fit's map (``-direct``); ``--max-passes N``
(``-p<N>`` when not 2).  Each record keeps the fit's Gauss–Newton interval beside the reported one, its
Gauss–Newton relative sds and the reported interval's scales (``identify.intervals``).

    OMP_NUM_THREADS=1 .venv/bin/python workflows/frames_benchmark.py run --model M --out runs/frames-bench

``--session drift`` takes each lesion's frames with a camera whose LED powers and vignetting drift
from the calibration's (:func:`session_sensor`); inference keeps the nominal model.

``--inside E`` (give it to ``lesions`` and ``run`` alike) replaces the whole-design draw by a
region-stratified one: the first N lesions of an overdrawn Latin hypercube at which the shipped
map's ``frames`` set calls E identifiable (:func:`draw_lesions`; about 3 % of the design: large,
soft, shallow-to-mid inclusions), so that a quantity identifiable over a small part of the design
is scored on enough lesions.  ``--outside d`` is its mirror: lesions where the map does NOT call d
identifiable (about a quarter of the design: small or deep inclusions), to score the intervals
outside a region on more lesions than a design draw holds.  Neither set is a sample of the design:
report them apart.

Stage ``report``: the table (printed, ``OUT/benchmark.md``), ``OUT/benchmark.json`` and
``OUT/benchmark.png``.  Regions: the shipped identifiability map (``--region-set``, default the
``frames`` set; 10 % threshold) evaluated at the TRUE lesion says whether d, h and E are
identifiable there.  Errors (MRE) are over
the identifiable lesions whose frames show a signal (``no_signal`` lesions report nothing);
coverage is over all lesions.  A second table scores each estimator where it itself reports a
quantity as a number (its own interval within the threshold, decided from the frames alone: what a
user is told to trust).

    .venv/bin/python workflows/frames_benchmark.py report --out runs/frames-bench

Stage ``press`` (a check of the fit's map, writes nothing): at the first lesions, how far the pinned
map's first-order reference press is from the re-solved one, against the map's own discretisation
error (docs/camera.md 4c).

    OMP_NUM_THREADS=1 .venv/bin/python workflows/frames_benchmark.py press --n 5
"""

from __future__ import annotations

import copy
import os
import sys
import time
from dataclasses import dataclass

import click
import numpy as np

from elastimap.cli_util import shard_option, sizing_option
from elastimap.identify.coords import COORDS
from elastimap.identify.fit import FINE_MODES, STILL_MOVING
from elastimap.solver.params import MESH_LEVELS, SIZINGS

TRUTH_SEED = 2026


#: how many design points per wanted lesion ``draw_lesions(inside=...)`` draws (the region of
#: E from frames is about 3 % of the design)
INSIDE_OVERDRAW = 200


def draw_lesions(n: int, seed: int = TRUTH_SEED, inside: str | None = None, outside: str | None = None) -> np.ndarray:
    """(n, 3) lesions (d mm, h mm, E kPa): Latin hypercube over d, the admissible depth fraction and ln E.

    ``inside`` (d, h or E): a region-stratified set instead -- the first n of a Latin hypercube of
    ``INSIDE_OVERDRAW`` n points at which the shipped map's ``frames`` set calls that quantity
    identifiable (10 %), decided from the truth before any fit, so that a quantity identifiable
    over a small part of the design can be scored on enough lesions.  ``outside``: the same, at
    points where the map does NOT call it identifiable (to score the intervals there on more than
    the quarter of a design draw that lies outside d's region).  At most one of the two."""
    from elastimap.errors import UserError

    if inside is not None and outside is not None:
        raise UserError("outside", f"give inside or outside, not both (got inside={inside!r}, outside={outside!r})")
    if inside is None and outside is None:
        return _lhs_lesions(n, seed)
    q = inside or outside
    cand = _lhs_lesions(INSIDE_OVERDRAW * n, seed)
    ident = identifiable_at(cand, "frames")[:, "dhE".index(q)]
    keep = cand[ident if inside is not None else ~ident]
    if len(keep) < n:
        where = "identifiable" if inside is not None else "not identifiable"
        raise UserError("n", f"at most {len(keep)} lesions with {q} {where} at seed {seed} (got {n})")
    return keep[:n]


def _design(n: int, seed: int, inside: str | None, outside: str | None = None) -> np.ndarray:
    """:func:`draw_lesions` for the commands: its errors name the flags."""
    from elastimap.errors import UserError

    try:
        return draw_lesions(n, seed, inside, outside)
    except UserError as exc:
        raise UserError("--n" if exc.param == "n" else "--outside", exc.message) from None


def _design_record(n: int, seed: int, inside: str | None, outside: str | None) -> dict:
    """The ``design`` a lesion record keeps (``outside`` only when given, so whole-design and
    ``--inside`` records read as before)."""
    rec = {"n": n, "seed": seed, "inside": inside}
    if outside is not None:
        rec["outside"] = outside
    return rec


def _drawn(design: dict | None) -> str:
    """Where a record's lesions were drawn, for the report's header and the figure's title ("" for
    the whole design box)."""
    design = design or {}
    if design.get("inside"):
        return f"drawn where the map's 'frames' set calls {design['inside']} identifiable"
    if design.get("outside"):
        return f"drawn where the map's 'frames' set does not call {design['outside']} identifiable"
    return ""


def _lhs_lesions(n: int, seed: int) -> np.ndarray:
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


SESSIONS = ("nominal", "drift")


def session_sensor(sensor, rng: np.random.Generator):
    """The camera of one SYNTHETIC session: ``sensor`` with each LED's power times U(0.8, 1.2) and
    the vignetting drawn from U(0.05, 0.3) -- what drifts between a calibration and a clinic's
    session; inference keeps the calibration's nominal model (the background frames' flat field
    should absorb both)."""
    return sensor.replace(
        led_power=tuple(float(p) * float(rng.uniform(0.8, 1.2)) for p in sensor.led_power),
        vignetting=float(rng.uniform(0.05, 0.3)),
    )


def truth_solve(d, h, E, mesh: str, cache: str, sizing: str = "fixed") -> dict:
    from elastimap.workflows.studies.solves import cached_solve

    return cached_solve(float(d), float(h), float(E), mesh=mesh, cache=cache, sizing=sizing)


def world_label(mesh: str, sizing: str) -> str:
    return f"remeshing solver, {mesh} mesh" + (", by_d sizing" if sizing == "by_d" else "")


TRUTH_SIZING = sizing_option(
    flag="--truth-sizing",
    help="Element sizing of the world's mesh near the inclusion (by_d: sized by the inclusion's diameter).",
)


def _region_option(flag: str, where: str, why: str):
    """``--inside`` / ``--outside``: a region-stratified lesion set (:func:`draw_lesions`)."""
    return click.option(
        flag,
        type=click.Choice(tuple("dhE")),
        default=None,
        help=f"A region-stratified lesion set: only design points where the shipped map's frames set {where} "
        f"this quantity identifiable ({why}). Give the same value to lesions and run.",
    )


INSIDE = _region_option("--inside", "calls", "draw_lesions; for scoring E, identifiable over ~3 % of the design")
OUTSIDE = _region_option(
    "--outside", "does NOT call", "to score intervals outside a region on enough lesions; not with --inside"
)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main():
    """SYNTHETIC camera-frame benchmark of the physics fit (see the module docstring)."""


@main.command("lesions")
@click.option("--n", "n", default=120, show_default=True, type=int, help="Held-out lesions.")
@click.option("--seed", default=TRUTH_SEED, show_default=True, type=int, help="Seed of the lesion design.")
@click.option("--truth-mesh", default="default", show_default=True, help="Mesh level of the world's remeshing solver.")
@TRUTH_SIZING
@INSIDE
@OUTSIDE
@shard_option("K/N: this process solves items i with i % N == K.")
@click.option(
    "--first", default=0, show_default=True, type=int, help="Only the first K lesions of the design (0: all)."
)
@click.option("--out", required=True, help="Benchmark folder (solves land in OUT/solves).")
def lesions(n, seed, truth_mesh, truth_sizing, inside, outside, shard, first, out):
    """Solve the phantoms and the held-out lesions with the world's forward model (resumable)."""
    from tqdm import tqdm

    from elastimap.camera.calibration import load_phantoms
    from elastimap.errors import UserError

    k, nsh = shard
    if first < 0:
        raise UserError("--first", f"must be >= 0 (got {first})")
    design = _design(n, seed, inside, outside)  # before any folder is made: a bad draw is one line
    cache = os.path.join(out, "solves")
    os.makedirs(cache, exist_ok=True)
    ph = load_phantoms()
    todo = [(float(r["d"]), float(r["h"]), float(r["E"])) for _, r in ph.iterrows()]
    todo += [tuple(map(float, t)) for t in design[: first or n]]
    todo = todo[k::nsh]
    t0 = time.perf_counter()
    for d, h, E in tqdm(todo, desc=f"SYNTHETIC world solves ({world_label(truth_mesh, truth_sizing)})"):
        truth_solve(d, h, E, truth_mesh, cache, truth_sizing)
    click.echo(
        f"{len(todo)} solves (shard {k}/{nsh} of {len(ph)} phantoms + {first or n} lesions) in "
        f"{time.perf_counter() - t0:.0f} s",
        err=True,
    )


@main.command("network")
@click.option("--sweep", "sweep_dir", required=True, help="Sweep folder with stored images (its design rows are used).")
@click.option("--repeats", default=4, show_default=True, type=int, help="Ensemble members.")
@click.option("--epochs", default=300, show_default=True, type=int)
@click.option("--seed", default=0, show_default=True, type=int)
@click.option("--out", required=True, help="Benchmark folder: the network lands in OUT/image-model.")
def network_cmd(sweep_dir, repeats, epochs, seed, out):
    """Train the start network (the recipe of docs/camera.md 4d): SCG ensemble of the image model,
    hidden 12-6 tansig, ln(peak) + 9 shape-PCA scores, 1 % image noise, target ln E."""
    from elastimap.errors import UserError
    from elastimap.identify.imagenet import fit_image_model
    from elastimap.identify.measure import load
    from elastimap.training.experiment import TrainConfig

    path = os.path.join(out, "image-model")
    if os.path.exists(path):
        raise UserError("--out", f"{path} exists; remove it or choose another folder")
    for name, v in (("--repeats", repeats), ("--epochs", epochs)):
        if v < 1:
            raise UserError(name, f"must be >= 1 (got {v})")
    try:
        data = load(sweep_dir, design_only=True)
    except UserError as exc:  # the library names its parameter; this command's flag is --sweep
        raise UserError("--sweep", exc.message) from None
    cfg = TrainConfig(hidden=((12, "tansig"), (6, "tansig")), epochs=epochs)
    model = fit_image_model(data, "scg", repeats, cfg, seed=seed, k=10, image_noise=0.01, log_e=True)
    os.makedirs(out, exist_ok=True)
    model.save(path)
    click.echo(f"saved the start network ({repeats} members, {data.n} rows of {sweep_dir}) to {path}", err=True)


def _fit_results(forward, phantoms):
    """Objects with image, image_raw, pixel, O1..O3 for the calibration, from the fit's forward map."""
    from types import SimpleNamespace

    from elastimap.solver.image import features

    out = []
    for _, r in phantoms.iterrows():
        res = forward(float(r["d"]), float(r["h"]), float(r["E"]))
        img, raw = np.asarray(res.image, float), np.asarray(res.image_raw, float)
        o = features(img, float(res.pixel))
        out.append(SimpleNamespace(image=img, image_raw=raw, pixel=float(res.pixel), O1=o[0], O2=o[1], O3=o[2]))
    return out


def calibrate(out: str, truth_mesh: str, forward, frames: int, seed: int, tag: str, truth_sizing: str = "fixed"):
    """The SYNTHETIC calibration: phantom frames from the world, FEM side from the fit's map."""
    from elastimap.camera import calibration as C
    from elastimap.camera.features import FeatureSettings, camera_features
    from elastimap.camera.optics import SensorModel, render_pair

    path = os.path.join(out, f"cal-{tag}.json")
    sensor = SensorModel(seed=seed)
    if os.path.exists(path):  # kept per forward map: it must be this run's camera and world
        cal = C.Calibration.load(path)
        if SensorModel.from_dict(cal.sensor or {}) != sensor or cal.meta.get("world") != world_label(
            truth_mesh, truth_sizing
        ):
            from elastimap.errors import UserError

            raise UserError("--out", f"{path} was made with another camera seed or world; use another --out")
        return cal
    ph = C.load_phantoms()
    rng = np.random.default_rng([seed, 0])
    pairs, cam = [], []
    for _, r in ph.iterrows():
        w = truth_solve(r["d"], r["h"], r["E"], truth_mesh, os.path.join(out, "solves"), truth_sizing)
        F, B = render_pair(sensor, w["image_raw"], w["image"], 0.5, frames, rng)
        pairs.append((F, B))
        cam.append(camera_features(F, B, sensor.full_scale, sensor.window, sensor.pixel_mm, FeatureSettings()).values)
    res = _fit_results(forward, ph)
    defl = C.deflection_calibration(res, pairs, sensor)
    fem = np.array([[x.O1, x.O2, x.O3] for x in res])
    cal = C.fit_calibration(
        ph,
        fem,
        np.array(cam),
        FeatureSettings().to_dict(),
        sensor.to_dict(),
        True,
        {"world": world_label(truth_mesh, truth_sizing), "fit_map": tag},
        defl,
    )
    cal.save(path)
    return cal


class _Timed:
    """A forward map that adds its seconds and calls to ``acc[name]`` / ``acc[name + '_n']`` (pins pass through)."""

    def __init__(self, fn, acc: dict, name: str):
        self.fn, self.acc, self.name = fn, acc, name
        self.key = getattr(fn, "key", None)
        self.has_tangent = bool(getattr(fn, "has_tangent", False))
        self.E_tissue = getattr(fn, "E_tissue", None)
        if hasattr(fn, "pin"):
            self.pin = lambda d, h: _Timed(fn.pin(d, h), acc, name)
        if hasattr(fn, "pin_exact"):
            self.pin_exact = lambda d, h: _Timed(fn.pin_exact(d, h), acc, name)

    def _count(self, f, *a):
        t = time.perf_counter()
        try:
            return f(*a)
        finally:
            self.acc[self.name] = self.acc.get(self.name, 0.0) + time.perf_counter() - t
            self.acc[self.name + "_n"] = self.acc.get(self.name + "_n", 0) + 1

    def __call__(self, *a):
        return self._count(self.fn, *a)

    def tangent(self, *a):
        return self._count(self.fn.tangent, *a)


def _check_same_design(fits: str, truth: np.ndarray) -> None:
    """A one-line error naming --out when ``fits`` already holds a lesion whose truth is not this
    design's lesion of the same number (another --seed, --n, --inside or --outside): ``run`` skips lesions it
    finds, so it would otherwise mix two designs in one folder."""
    import glob
    import json

    from elastimap.errors import UserError

    for path in sorted(glob.glob(os.path.join(fits, "lesion-*.json"))):
        with open(path) as fh:
            rec = json.load(fh)
        i = int(rec["i"])
        if i >= len(truth) or not np.allclose(rec["truth"], truth[i], rtol=1e-12, atol=0.0):
            raise UserError(
                "--out",
                f"{fits} holds lesion {i} of another design (--seed, --n, --inside or --outside differ); use another --out",
            )


def run_tags(
    geometry: str,
    fit_mesh: str,
    correct_mesh: str | None,
    levels: list[str],
    coords: str,
    session: str,
    correct_sizing: str = "fixed",
):
    """(calibration tag, fits tag) of a ``run``: ``OUT/cal-<tag>.json`` and ``OUT/fits-<tag>`` are kept
    per forward map -- ``<geometry>-<mesh>`` plus ``-corr-<level>`` (``-corr-<level>-by_d`` when the
    correcting level is sized by d), ``-err-<levels>`` when the model error is not measured against the
    default neighbour; the fits also ``-log`` and ``-drift``."""
    from elastimap.identify.forward_maps import neighbour_level

    top = correct_mesh or fit_mesh
    tag = f"{geometry}-{fit_mesh}" + (f"-corr-{correct_mesh}" if correct_mesh else "")
    tag += f"-{correct_sizing}" if correct_mesh and correct_sizing != "fixed" else ""
    tag += "" if levels == [neighbour_level(top)] else f"-err-{'+'.join(levels)}"
    cal_tag = tag  # the calibration does not depend on the fit's coordinates
    tag += "-log" if coords == "log" else ""
    tag += "-drift" if session == "drift" else ""
    return cal_tag, tag


@dataclass
class LesionInputs:
    """One benchmark lesion before its fit (SYNTHETIC): the world's solve, the session's camera, the
    difference image recovered from its frames (with per-pixel noise), the network's estimate, and
    the seconds the recovery and the network took."""

    world: dict
    camera: object
    recovered: object
    network: object
    seconds: float


def lesion_inputs(i, theta, seed, sensor, cal, model, idm, out, truth_mesh, truth_sizing, session="drift", frames=30):
    """Lesion ``i`` (truth ``theta``) of the benchmark in ``out``: its world solve (read from or added
    to ``OUT/solves``), ``frames`` lesion and ``frames`` background frames from the session's camera
    (own noise seeds per lesion), the FEM-equivalent difference image by the calibration ``cal`` and
    the start network ``model``."""
    from elastimap.camera.deflection import difference_image
    from elastimap.camera.infer import estimate_fem_images
    from elastimap.camera.optics import render_pair

    d, h, E = (float(v) for v in theta)
    w = truth_solve(d, h, E, truth_mesh, os.path.join(out, "solves"), truth_sizing)
    cam = session_sensor(sensor, np.random.default_rng([seed, 2, i])) if session == "drift" else sensor
    F, B = render_pair(cam, w["image_raw"], w["image"], 0.5, frames, np.random.default_rng([seed, 1, i]))
    ref, pixel = cal.reference_image()
    t = time.perf_counter()
    di = difference_image(F, B, sensor, ref, pixel, scale=float(cal.deflection["scale"]))
    (net,) = estimate_fem_images(di.image[None], model, [str(i)], idm, sigma=di.sigma[None])
    return LesionInputs(w, cam, di, net, time.perf_counter() - t)


@main.command("run")
@click.option("--model", "model_dir", required=True, help="Image model (the network that gives the start).")
@click.option("--n", "n", default=120, show_default=True, type=int, help="Held-out lesions (as in 'lesions').")
@click.option("--seed", default=TRUTH_SEED, show_default=True, type=int, help="Seed of the lesion design and camera.")
@click.option("--truth-mesh", default="default", show_default=True)
@TRUTH_SIZING
@INSIDE
@OUTSIDE
@click.option("--fit-mesh", default="coarse", show_default=True, help="Mesh level of the fit's forward map.")
@click.option(
    "--error-mesh",
    default=None,
    help="Level(s) the fit's model error is measured against, comma-separated (each difference adds "
    "its own term; default: the neighbouring coarser level).",
)
@click.option(
    "--correct-mesh",
    default=None,
    help="A finer level whose defect corrects the fit's map at the start of each pass (fit_image's "
    "forward_fine); the model error is then measured against that level's neighbour unless --error-mesh.",
)
@click.option(
    "--correct-sizing",
    type=click.Choice(SIZINGS),
    default="fixed",
    show_default=True,
    help="Element sizing of the --correct-mesh level and of the level(s) its model error is measured against "
    "(by_d adds '-by_d' to the folders' tags).",
)
@click.option("--geometry", default=None, help="Fit's forward map: morph (default where available) or remesh.")
@click.option("--frames", default=30, show_default=True, type=int, help="Lesion and background frames per lesion.")
@click.option(
    "--coords",
    type=click.Choice(COORDS),
    default="contrast",
    show_default=True,
    help="The fit's coordinate of E (identify.refine.FitCoords); 'log' (ln E) adds '-log' to the fits' folder.",
)
@click.option(
    "--session",
    type=click.Choice(SESSIONS),
    default="nominal",
    show_default=True,
    help="The camera that takes each lesion's frames: nominal = the calibration's sensor; drift = its LED "
    "powers and vignetting drawn afresh per lesion (session_sensor), inverted with the nominal model "
    "(adds '-drift' to the fits' folder).",
)
@click.option(
    "--max-passes",
    default=2,
    show_default=True,
    type=click.IntRange(1, 10),
    help="The fit's passes (corrected ones with --correct-mesh); other than 2 adds '-p<N>' to the fits' folder.",
)
@click.option(
    "--fine-mode",
    type=click.Choice(FINE_MODES),
    default="correct",
    show_default=True,
    help="How the passes after the first use --correct-mesh: defect correction of the fit's map, or a fit "
    "of that level itself ('direct' adds '-direct' to the fits' folder).",
)
@shard_option("K/N: this process fits lesions i with i % N == K.")
@click.option("--limit", default=0, type=int, help="Stop after this many new fits (0: all).")
@click.option("--out", required=True)
def run_cmd(
    model_dir,
    n,
    seed,
    truth_mesh,
    truth_sizing,
    inside,
    outside,
    fit_mesh,
    error_mesh,
    correct_mesh,
    correct_sizing,
    geometry,
    frames,
    coords,
    session,
    max_passes,
    fine_mode,
    shard,
    limit,
    out,
):
    """Frames -> network -> physics fit for every held-out lesion (resumable, one JSON per lesion)."""
    import json

    from elastimap.camera.infer import load_identifiability, load_model, refine_estimates
    from elastimap.camera.optics import SensorModel
    from elastimap.errors import UserError
    from elastimap.identify.forward_maps import (
        BELOW_LEVELS,
        check_correct,
        default_geometry,
        default_intervals,
        forward_map,
        neighbour_level,
    )

    k, nsh = shard
    geometry = geometry or default_geometry()
    try:
        check_correct(fit_mesh, correct_mesh)  # both levels, the correcting one finer
    except UserError as exc:
        raise UserError("--fit-mesh" if exc.param == "mesh" else "--correct-mesh", exc.message) from None
    top = correct_mesh or fit_mesh  # the level the fit's (corrected) map stands for
    levels = [v.strip() for v in (error_mesh or neighbour_level(top)).split(",")]
    if any(v not in MESH_LEVELS or v == top for v in levels) or len(set(levels)) != len(levels):
        raise UserError(
            "--error-mesh",
            f"distinct levels of {', '.join(MESH_LEVELS)} other than {top} (got {error_mesh!r})",
        )
    alt_level = "+".join(levels)
    cal_tag, tag = run_tags(geometry, fit_mesh, correct_mesh, levels, coords, session, correct_sizing)
    tag += f"-p{max_passes}" if max_passes != 2 else ""
    tag += "-direct" if fine_mode == "direct" and correct_mesh else ""
    fits = os.path.join(out, f"fits-{tag}")
    truth = _design(n, seed, inside, outside)
    _check_same_design(fits, truth)  # before any work: never add lesions of another design
    os.makedirs(fits, exist_ok=True)
    acc: dict = {}
    t = time.perf_counter()
    below = fit_mesh in BELOW_LEVELS  # one bin rule for all the fit's maps (identify.refine.reference_below)
    fwd = _Timed(forward_map(fit_mesh, geometry, below=below), acc, "fit_level")
    top_sizing = correct_sizing if correct_mesh else "fixed"  # the sizing of the map the fit stands for
    fwd_alt = [_Timed(forward_map(v, geometry, sizing=top_sizing, below=below), acc, "alt_level") for v in levels]
    fwd_fine = (
        _Timed(forward_map(correct_mesh, geometry, sizing=correct_sizing, below=below), acc, "fine_level")
        if correct_mesh
        else None
    )
    sized = {k: "" if v == "fixed" else f" sized {v}" for k, v in (("fine", correct_sizing), ("alt", top_sizing))}
    how = "then fitted on" if fine_mode == "direct" else "defect-corrected by"
    fit_label = f"{geometry}, {fit_mesh} mesh" + (f", {how} {correct_mesh}{sized['fine']}" if correct_mesh else "")
    fit_label += f"; model error vs {alt_level}{sized['alt']}; E coordinate {coords}"
    fit_label += "; references: the d-bin below" if below and geometry == "morph" else ""
    # the calibrated interval only for the fit it was calibrated on (identify.intervals.CALIBRATED_FOR):
    # (default_intervals: levels, morphed maps) with the fixed sizing, the default model-error level
    # and passes, defect correction -- the benchmark's switches that infer does not have
    calibrated_fit = (
        correct_sizing == "fixed"
        and levels == [neighbour_level(top)]
        and coords == "contrast"
        and max_passes == 2
        and fine_mode == "correct"
    )
    intervals = default_intervals(fit_mesh, correct_mesh, geometry) if calibrated_fit else "gauss"
    fit_label += f"; {intervals} intervals"
    # the calibration's FEM side: the map the fit stands for (the finer one when it corrects)
    cal = calibrate(out, truth_mesh, fwd_fine or fwd, frames, seed, cal_tag, truth_sizing)
    setup = time.perf_counter() - t
    model = load_model(model_dir)
    idm = load_identifiability("default")
    sensor = SensorModel(seed=seed)
    done = 0
    for i in range(k, n, nsh):
        path = os.path.join(fits, f"lesion-{i:04d}.json")
        if os.path.exists(path):
            continue
        d, h, E = truth[i]
        one = lesion_inputs(i, truth[i], seed, sensor, cal, model, idm, out, truth_mesh, truth_sizing, session, frames)
        w, cam, di, net, t_net = one.world, one.camera, one.recovered, one.network, one.seconds
        before = dict(acc)
        c0 = time.process_time()
        (fit,) = refine_estimates(
            [copy.deepcopy(net)],
            None,
            forward=fwd,
            forward_alt=fwd_alt,
            forward_fine=fwd_fine,
            coords=coords,
            max_passes=max_passes,
            fine=fine_mode,
            intervals=intervals,
        )
        cpu_fit = time.process_time() - c0
        spent = {key: acc.get(key, 0) - before.get(key, 0) for key in acc}
        rec = {
            "synthetic": True,
            "i": i,
            "truth": [float(d), float(h), float(E)],
            "design": _design_record(n, seed, inside, outside),
            "world": world_label(truth_mesh, truth_sizing) + ", tied, quarter",
            "fit_map": fit_label,
            "frames": frames,
            "camera": "nominal"
            if session == "nominal"
            else {"led_power": list(cam.led_power), "vignetting": cam.vignetting},
            "image_peak_mm": float(w["image"].max()),
            "recovered_z_rms": float(np.sqrt(np.mean(((di.image - w["image"]) / di.sigma) ** 2))),
            "network": net.to_dict(),
            "fit": fit.to_dict(),
            "seconds_camera_and_network": t_net,
            "seconds_fit": float(fit.fit.seconds) if fit.fit is not None else 0.0,
            "cpu_seconds_fit": cpu_fit,
            "fit_message": fit.fit.message if fit.fit is not None else "",
            # the fit's Gauss–Newton interval (θ̂ ± 1.96 sd clipped to the box) beside the reported one
            "fit_interval_gauss": {
                "lo": [float(v) for v in fit.fit.lo_gauss],
                "hi": [float(v) for v in fit.fit.hi_gauss],
            }
            if fit.fit is not None and fit.fit.lo_gauss is not None
            else None,
            # the Gauss–Newton relative sds (d, h; ln E) and the reported interval's scales
            # (identify.intervals): the fit's sd_q above is the Gauss–Newton one times the scale
            "fit_relstd_gauss": [float(v) for v in fit.fit.relstd] if fit.fit is not None else None,
            "fit_interval_scale": [float(v) for v in fit.fit.scale] if fit.fit is not None else None,
            "seconds_fit_level_solves": spent.get("fit_level", 0.0),
            "n_fit_level_solves": spent.get("fit_level_n", 0),
            "seconds_alt_level_solves": spent.get("alt_level", 0.0),
            "n_alt_level_solves": spent.get("alt_level_n", 0),
            "seconds_fine_level_solves": spent.get("fine_level", 0.0),
            "n_fine_level_solves": spent.get("fine_level_n", 0),
            "setup_seconds_this_process": setup,
        }
        tmp = path + ".tmp"
        with open(tmp, "w") as fh:
            json.dump(rec, fh, indent=1)
        os.replace(tmp, path)
        f = rec["fit"]
        click.echo(
            f"lesion {i}: truth {d:.2f}/{h:.2f}/{E:.1f}  net {net.d:.2f}/{net.h:.2f}/{net.E:.1f}  "
            f"fit {f['d']:.2f}/{f['h']:.2f}/{f['E']:.1f}  chi2 {f.get('fit_chi2_red', float('nan')):.2f}  "
            f"{rec['seconds_fit']:.1f} s ({rec['n_fit_level_solves']}+{rec['n_alt_level_solves']}"
            f"+{rec['n_fine_level_solves']} solves)",
            err=True,
        )
        done += 1
        if limit and done >= limit:
            break


REGION_SETS = ("frames", "camera", "image")


def identifiable_at(truth: np.ndarray, mset: str = "frames") -> np.ndarray:
    """(n, 3) bool: the shipped identifiability map (set ``mset``, 10 %) calls d, h, E identifiable at
    the truth.  ``frames``: what inference from frames uses (the larger of the camera and image
    bounds); ``camera``: the nominal camera at the map's frame count (the benchmark's camera);
    ``image``: 1 % of the peak per pixel (the regions of the tables before 2026-11-25)."""
    from elastimap.identify.idmap import IdentifiabilityMap

    r, _ = IdentifiabilityMap.load().bound(truth, mset)
    return r <= 0.10


def summarise(recs: list[dict], region_set: str = "frames") -> dict:
    """Per estimator: MRE where identifiable, coverage inside/outside, seconds; from the lesion records."""
    truth = np.array([r["truth"] for r in recs])
    reg = identifiable_at(truth, region_set)
    sig = np.array(["no_signal" not in r["network"]["flags"] for r in recs])
    conv = np.array([STILL_MOVING not in r.get("fit_message", "") for r in recs])
    out = {"n": len(recs), "identifiable": {q: int(reg[:, j].sum()) for j, q in enumerate("dhE")}}
    for name in ("network", "fit"):
        est = np.array([[r[name][q] for q in "dhE"] for r in recs])
        lo = np.array([[r[name][f"{q}_lo"] for q in "dhE"] for r in recs])
        hi = np.array([[r[name][f"{q}_hi"] for q in "dhE"] for r in recs])
        rel = np.abs(est - truth) / truth
        cov = (lo <= truth) & (truth <= hi)
        row = {}
        for j, q in enumerate("dhE"):
            i_in, i_out = reg[:, j], ~reg[:, j]
            i_err = i_in & sig  # no_signal lesions report nothing: left out of the errors, kept in coverage
            row[q] = {
                "mre_identifiable": float(rel[i_err, j].mean()) if i_err.any() else None,
                "median_re_identifiable": float(np.median(rel[i_err, j])) if i_err.any() else None,
                "n_error": int(i_err.sum()),
                "mre_all": float(rel[:, j].mean()),
                "coverage_inside": float(cov[i_in, j].mean()) if i_in.any() else None,
                "coverage_outside": float(cov[i_out, j].mean()) if i_out.any() else None,
                "n_inside": int(i_in.sum()),
                "n_outside": int(i_out.sum()),
            }
            # where the estimator itself prints q as a number (identifiable by its own sd, possible,
            # a signal): what a user is told to trust, decided from the frames, not from the truth
            rep = np.array([bool(r[name].get(f"{q}_reportable", False)) for r in recs])
            row[q].update(
                mre_reported=float(rel[rep, j].mean()) if rep.any() else None,
                median_re_reported=float(np.median(rel[rep, j])) if rep.any() else None,
                coverage_reported=float(cov[rep, j].mean()) if rep.any() else None,
                n_reported=int(rep.sum()),
            )
            if name == "fit":  # the fits among them whose last pass settled (FitResult.converged)
                rc = rep & conv
                row[q].update(
                    mre_reported_converged=float(rel[rc, j].mean()) if rc.any() else None,
                    n_reported_converged=int(rc.sum()),
                )
        out[name] = row
    sec = np.array([r["seconds_fit"] for r in recs])
    out["seconds_fit"] = {"mean": float(sec.mean()), "median": float(np.median(sec)), "max": float(sec.max())}
    # the fit's cost over the lesions a fit ran for (a lesion without a signal costs none; before
    # 2026-11-27 these means were over all lesions)
    ran = [r for r in recs if r.get("n_fit_level_solves", 0) > 0] or recs
    cpu = np.array([r.get("cpu_seconds_fit", np.nan) for r in ran])
    out["cpu_seconds_fit"] = {
        "mean": float(np.nanmean(cpu)),
        "median": float(np.nanmedian(cpu)),
        "p90": float(np.nanpercentile(cpu, 90)),
        "n": len(ran),
    }
    out["seconds_network"] = float(np.mean([r["seconds_camera_and_network"] for r in recs]))
    for key in ("seconds_fit_level_solves", "seconds_alt_level_solves", "n_fit_level_solves", "n_alt_level_solves"):
        out[key] = float(np.mean([r[key] for r in ran]))
    for key in ("seconds_fine_level_solves", "n_fine_level_solves"):  # fits that correct by a finer level
        out[key] = float(np.mean([r.get(key, 0.0) for r in ran]))
    if all("fit_interval_gauss" in r for r in recs):  # records since 3bfcd81: the Gauss–Newton interval too
        # None where no fit ran (no signal): the reported interval, the network's, stands for both
        gauss = [
            r["fit_interval_gauss"] or {k: [r["fit"][f"{q}_{k}"] for q in "dhE"] for k in ("lo", "hi")} for r in recs
        ]
        glo, ghi = np.array([g["lo"] for g in gauss]), np.array([g["hi"] for g in gauss])
        gcov = (glo <= truth) & (truth <= ghi)
        out["fit_gauss_coverage"] = {
            q: {
                "inside": float(gcov[reg[:, j], j].mean()) if reg[:, j].any() else None,
                "outside": float(gcov[~reg[:, j], j].mean()) if (~reg[:, j]).any() else None,
            }
            for j, q in enumerate("dhE")
        }
    out["not_converged"] = int((~conv).sum())
    out["no_signal"] = int(sum("no_signal" in r["fit"]["flags"] for r in recs))
    out["model_mismatch"] = int(sum("model_mismatch" in r["fit"]["flags"] for r in recs))
    out["chi2_red_median"] = float(np.nanmedian([r["fit"].get("fit_chi2_red", np.nan) for r in recs]))
    return out


def _pct(v):
    return "—" if v is None else f"{100 * v:.1f} %"


def table(sm: dict) -> str:
    lines = [
        "| estimator | E MRE where identifiable (n) | d MRE where identifiable (n) | h MRE where identifiable (n) | "
        "95 % coverage inside d / h / E | 95 % coverage outside d / h / E (n) | s per lesion |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, label in (("network", "frames -> image network"), ("fit", "frames -> network -> ML fit")):
        r = sm[name]
        sec = (
            f"{sm['seconds_network']:.2f}"
            if name == "network"
            else f"{sm['seconds_fit']['mean']:.1f} (median {sm['seconds_fit']['median']:.1f}, max {sm['seconds_fit']['max']:.1f})"
        )
        lines.append(
            f"| {label} | {_pct(r['E']['mre_identifiable'])} ({r['E']['n_error']}) | "
            f"{_pct(r['d']['mre_identifiable'])} ({r['d']['n_error']}) | {_pct(r['h']['mre_identifiable'])} ({r['h']['n_error']}) | "
            + " / ".join(_pct(r[q]["coverage_inside"]) for q in "dhE")
            + " | "
            + " / ".join(_pct(r[q]["coverage_outside"]) for q in "dhE")
            + f" ({r['d']['n_outside']} / {r['h']['n_outside']} / {r['E']['n_outside']}) | {sec} |"
        )
    lines += [
        "",
        "Where the estimator itself reports the quantity as a number (its own interval within the "
        "identifiability threshold, possible, a signal; decided from the frames, not the truth):",
        "",
        "| estimator | E MRE / median (n) | coverage E | d MRE / median (n) | coverage d | h MRE / median (n) | coverage h |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, label in (("network", "frames -> image network"), ("fit", "frames -> network -> ML fit")):
        r = sm[name]
        lines.append(
            f"| {label} | "
            + " | ".join(
                f"{_pct(r[q]['mre_reported'])} / {_pct(r[q]['median_re_reported'])} ({r[q]['n_reported']}) | "
                f"{_pct(r[q]['coverage_reported'])}"
                for q in "Edh"
            )
            + " |"
        )
    r = sm["fit"]
    g = sm.get("fit_gauss_coverage")
    if g:
        lines += [
            "",
            "The fit's Gauss–Newton interval (θ̂ ± 1.96 sd clipped to the box), beside the reported one: coverage "
            "inside d / h / E "
            + " / ".join(_pct(g[q]["inside"]) for q in "dhE")
            + ", outside "
            + " / ".join(_pct(g[q]["outside"]) for q in "dhE")
            + ".",
        ]
    lines += [
        "",
        f"Fits that ended still moving (the passes ran out): {sm['not_converged']} of {sm['n']}.  Among the fit's "
        "reported quantities, those whose fit converged: "
        + ", ".join(f"{q} {_pct(r[q]['mre_reported_converged'])} ({r[q]['n_reported_converged']})" for q in "Edh")
        + ".",
    ]
    return "\n".join(lines)


def plot(recs: list[dict], path: str, region_set: str = "frames") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    truth = np.array([r["truth"] for r in recs])
    reg = identifiable_at(truth, region_set)
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.6))
    for j, (q, unit) in enumerate((("d", "mm"), ("h", "mm"), ("E", "kPa"))):
        ax = axes[j]
        net = np.array([r["network"][q] for r in recs])
        fit = np.array([r["fit"][q] for r in recs])
        lo = np.array([r["fit"][f"{q}_lo"] for r in recs])
        hi = np.array([r["fit"][f"{q}_hi"] for r in recs])
        ax.scatter(truth[:, j], net, s=10, c="0.7", label="image network")
        for m, c, lab in (
            (reg[:, j], "C0", f"fit, {q} identifiable"),
            (~reg[:, j], "C3", f"fit, {q} not identifiable"),
        ):
            ax.errorbar(
                truth[m, j],
                fit[m],
                yerr=[np.clip(fit[m] - lo[m], 0, None), np.clip(hi[m] - fit[m], 0, None)],
                fmt="o",
                ms=3,
                c=c,
                lw=0.6,
                label=lab,
            )
        a, b = truth[:, j].min(), truth[:, j].max()
        ax.plot([a, b], [a, b], "k--", lw=0.8)
        if q == "E":
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_ylim(5, 400)
        else:
            ax.set_ylim(0.5 * a, 1.3 * b)
        ax.set_xlabel(f"true {q} ({unit})")
        ax.set_ylabel(f"estimated {q} ({unit})")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    where = _drawn(recs[0].get("design"))
    where = f" {where}" if where else ""
    fig.suptitle(f"SYNTHETIC camera frames, {len(recs)} held-out lesions{where}: estimate vs truth (95 % intervals)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


@main.command("report")
@click.option("--out", required=True, help="The benchmark folder.")
@click.option("--fits", "fits_name", default=None, help="The fits folder inside OUT (default: the only one).")
@click.option(
    "--region-set",
    type=click.Choice(REGION_SETS),
    default="frames",
    show_default=True,
    help="The map's set that decides where d, h, E are identifiable: frames = what inference from frames "
    "uses (the larger of camera and image), camera = the nominal camera's frames alone, "
    "image = 1 % of the peak per pixel (earlier tables).",
)
@click.option(
    "--common-with",
    "common",
    default=None,
    type=click.Path(exists=True, file_okay=False),
    help="Another fits folder (any benchmark folder): score only the lesions both hold, so that two fits "
    "are compared on the same lesions (files get '-common-<its name>').",
)
def report_cmd(out, fits_name, region_set, common):
    """Table (printed and OUT/benchmark.md), OUT/benchmark.json and OUT/benchmark.png (``-FITS`` and
    ``-SET`` added to the names when OUT holds several fits folders or the regions are not ``frames``)."""
    import glob
    import json

    from elastimap.errors import UserError

    names = sorted(os.path.basename(p) for p in glob.glob(os.path.join(out, "fits-*")))
    if fits_name is None:
        if len(names) != 1:
            raise UserError("--fits", f"{out} holds {len(names)} fits folders ({', '.join(names)}); name one")
        fits_name = names[0]
    files = sorted(glob.glob(os.path.join(out, fits_name, "lesion-*.json")))
    if not files:
        raise UserError("--out", f"{os.path.join(out, fits_name)}: no lesion fits yet (run the 'run' stage)")
    if common is not None:
        other = {os.path.basename(f) for f in glob.glob(os.path.join(common, "lesion-*.json"))}
        files = [f for f in files if os.path.basename(f) in other]
        if not files:
            raise UserError("--common-with", f"{common} holds none of the lesions of {os.path.join(out, fits_name)}")
    recs = [json.load(open(f)) for f in files]
    designs = {json.dumps(r.get("design"), sort_keys=True) for r in recs}
    if len(designs) != 1:
        raise UserError("--out", f"{os.path.join(out, fits_name)} mixes lesion designs ({', '.join(sorted(designs))})")
    design = recs[0].get("design") or {}
    sm = summarise(recs, region_set)
    sm["region_set"] = region_set
    sm["inside"] = design.get("inside")
    sm["outside"] = design.get("outside")
    r0 = recs[0]
    drawn = _drawn(design)
    drawn = f"{drawn} (region-stratified, not a sample of the design)" if drawn else "over the whole design box"
    head = (
        f"SYNTHETIC camera frames ({r0['frames']} lesion + {r0['frames']} background frames per lesion; camera: "
        f"{'nominal' if r0.get('camera', 'nominal') == 'nominal' else 'LED powers and vignetting drawn per lesion'}), "
        f"{len(recs)} held-out lesions {drawn}; world: {r0['world']}; fit: {r0['fit_map']}; "
        f"regions: the map's {region_set!r} set at the truth (10 %)"
    )
    foot = (
        f"fit CPU time per fitted lesion ({sm['cpu_seconds_fit'].get('n', sm['n'])} of {sm['n']}; one core, process "
        f"time): mean {sm['cpu_seconds_fit']['mean']:.1f} s, median {sm['cpu_seconds_fit']['median']:.1f} s, "
        f"p90 {sm['cpu_seconds_fit'].get('p90', float('nan')):.1f} s (the table's seconds are wall time on the shared "
        "machine, over all lesions); "
        f"fit: {sm['n_fit_level_solves']:.1f} solves at the fit's level ({sm['seconds_fit_level_solves']:.1f} s) + "
        f"{sm['n_alt_level_solves']:.1f} at the model-error level ({sm['seconds_alt_level_solves']:.1f} s) "
        + (
            f"+ {sm['n_fine_level_solves']:.1f} at the correcting level ({sm['seconds_fine_level_solves']:.1f} s) "
            if sm.get("n_fine_level_solves")
            else ""
        )
        + "per lesion "
        f"on average; median reduced chi2 {sm['chi2_red_median']:.2f}; no_signal {sm['no_signal']} (left out of the "
        f"errors, kept in the coverage), "
        f"model_mismatch {sm['model_mismatch']}"
    )
    md = head + "\n\n" + table(sm) + "\n\n" + foot + "\n"
    # one fits folder: OUT/benchmark[-SET].*; several: the folder's name too, so that none overwrites another
    stem = (
        "benchmark"
        + ("" if len(names) == 1 else f"-{fits_name}")
        + ("" if region_set == "frames" else f"-{region_set}")
        + ("" if common is None else f"-common-{os.path.basename(os.path.normpath(common))}")
    )
    with open(os.path.join(out, f"{stem}.md"), "w") as fh:
        fh.write(md)
    with open(os.path.join(out, f"{stem}.json"), "w") as fh:
        json.dump({"synthetic": True, "summary": sm, "lesions": recs}, fh, indent=1)
    plot(recs, os.path.join(out, f"{stem}.png"), region_set)
    click.echo(md)


PRESS_MOVES = ((0.3, 0.0), (0.0, 0.3), (-0.8, 0.5), (1.0, -1.0))  # (Δd, Δh) mm from the pin


@main.command("press")
@click.option("--n", "n", default=5, show_default=True, type=int, help="Lesions (the first n of the design) to pin at.")
@click.option("--design-n", default=120, show_default=True, type=int, help="Lesions in the design (as in 'lesions').")
@click.option("--seed", default=TRUTH_SEED, show_default=True, type=int, help="Seed of the lesion design.")
@click.option("--fit-mesh", default="coarse", show_default=True, help="Mesh level of the fit's forward map.")
def press_cmd(n, design_n, seed, fit_mesh):
    """How far the pinned map's first-order reference press is from the re-solved one.

    At each of the first N lesions (pinned there) and (d, h) moved by PRESS_MOVES, the max |Δ| over
    the image (mm) of: the linearised-press image minus the re-solved one, against the map's own
    discretisation error (this level minus the neighbouring level, both re-solved).  Prints a table;
    writes nothing."""
    from elastimap.errors import UserError
    from elastimap.identify.forward_maps import forward_map, neighbour_level
    from elastimap.solver.params import depth_range

    if not 1 <= n <= design_n:
        raise UserError("--n", f"must be in [1, --design-n = {design_n}] (got {n})")
    f = forward_map(fit_mesh, "morph").morphed
    g = forward_map(neighbour_level(fit_mesh), "morph").morphed
    click.echo(
        "| pin d/h/E | at d/h | peak (mm) | linearised − re-solved | model error (level difference) | ratio | CPU s re-solved / linearised |"
    )
    click.echo("|---|---|---|---|---|---|---|")
    for d0, h0, E in draw_lesions(design_n, seed)[:n]:
        ref, ref_g = f.reference_for(d0, h0), g.reference_for(d0, h0)
        f.solve(d0, h0, E, reference=ref, linearise_at=(d0, h0))  # the expansion, once per pin
        for dd, dh in PRESS_MOVES:
            d, h = d0 + dd, h0 + dh
            lo, hi = depth_range(d)
            if not (2.0 <= d <= 15.0 and lo <= h <= hi):
                continue
            c = time.process_time()
            a = f.solve(d, h, E, reference=ref).image.astype(float)
            c1 = time.process_time()
            b = f.solve(d, h, E, reference=ref, linearise_at=(d0, h0)).image.astype(float)
            c2 = time.process_time()
            m = g.solve(d, h, E, reference=ref_g).image.astype(float)
            lin, err = np.abs(b - a).max(), np.abs(a - m).max()
            click.echo(
                f"| {d0:.2f}/{h0:.2f}/{E:.0f} | {d:.2f}/{h:.2f} | {np.abs(a).max():.2e} | {lin:.1e} | {err:.1e} | "
                f"{lin / err:.3f} | {c1 - c:.2f} / {c2 - c1:.2f} |"
            )


if __name__ == "__main__":
    from elastimap.cli_util import run

    sys.exit(run(main, prog_name="workflows/frames_benchmark.py"))
