"""The benchmark's ``network`` stage (the start network), ``run`` stage (calibration, then per lesion
frames -> difference image -> image network -> physics fit, one JSON record each) and the
``press`` check of the fit's map (see :mod:`elastimap.workflows.benchmarks.frames`)."""

from __future__ import annotations

import copy
import os
import time
from dataclasses import dataclass

import click
import numpy as np

from elastimap.cli_util import shard_option
from elastimap.dataset.phantoms import read_phantoms
from elastimap.identify.coords import COORDS
from elastimap.identify.fit import FINE_MODES
from elastimap.solver.params import MESH_LEVELS, SIZINGS

from .lesions import (
    INSIDE,
    OUTSIDE,
    SESSIONS,
    TRUTH_SEED,
    TRUTH_SIZING,
    design_record,
    draw_lesions,
    lesion_design,
    session_sensor,
    truth_solve,
    world_label,
)


@click.command("network")
@click.option("--sweep", "sweep_dir", required=True, help="Sweep folder with stored images (its design rows are used).")
@click.option("--repeats", default=4, show_default=True, type=int, help="Ensemble members.")
@click.option("--epochs", default=300, show_default=True, type=int, help="Training epochs per member.")
@click.option("--seed", default=0, show_default=True, type=int, help="Seed of the initialisations and image noise.")
@click.option("--out", required=True, help="Benchmark folder: the network lands in OUT/image-model.")
def network_cmd(sweep_dir, repeats, epochs, seed, out):
    """Train the start network (the recipe in docs/camera.md, 'Inference'): SCG ensemble of the image model,
    hidden 12-6 tansig, ln(peak) + 9 shape-PCA scores, 1 % image noise, target ln E."""
    from elastimap.errors import UserError
    from elastimap.identify.image_model import fit_image_model
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
    ph = read_phantoms()
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


@click.command("run")
@click.option("--model", "model_dir", required=True, help="Image model (the network that gives the start).")
@click.option("--n", "n", default=120, show_default=True, type=int, help="Held-out lesions (as in 'lesions').")
@click.option("--seed", default=TRUTH_SEED, show_default=True, type=int, help="Seed of the lesion design and camera.")
@click.option("--truth-mesh", default="default", show_default=True, help="Mesh level of the world's remeshing solver.")
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
    help="The fit's coordinate of E (identify.coords.FitCoords); 'log' (ln E) adds '-log' to the fits' folder.",
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
@click.option("--out", required=True, help="The benchmark folder (fits land in OUT/fits-<tag>).")
def run_cmd(model_dir, n, seed, truth_mesh, truth_sizing, inside, outside, frames, shard, limit, out, **fit):
    """Frames -> network -> physics fit for every held-out lesion (resumable, one JSON per lesion)."""
    from elastimap.camera.infer import load_identifiability, load_model
    from elastimap.camera.optics import SensorModel

    k, nsh = shard
    setup = FitSetup.from_options(**fit)
    cal_tag, tag = setup.tags()
    fits = os.path.join(out, f"fits-{tag}")
    truth = lesion_design(n, seed, inside, outside)
    _check_same_design(fits, truth)  # before any work: never add lesions of another design
    os.makedirs(fits, exist_ok=True)
    acc: dict = {}
    t = time.perf_counter()
    maps = setup.maps(acc)
    # the calibration's FEM side: the map the fit stands for (the finer one when it corrects)
    cal = calibrate(out, truth_mesh, maps[2] or maps[0], frames, seed, cal_tag, truth_sizing)
    setup_s = time.perf_counter() - t
    model = load_model(model_dir)
    idm = load_identifiability("default")
    sensor = SensorModel(seed=seed)
    common = {
        "design": design_record(n, seed, inside, outside),
        "world": world_label(truth_mesh, truth_sizing) + ", tied, quarter",
        "fit_map": setup.label(),
        "frames": frames,
    }
    done = 0
    for i in range(k, n, nsh):
        path = os.path.join(fits, f"lesion-{i:04d}.json")
        if os.path.exists(path):
            continue
        one = lesion_inputs(
            i, truth[i], seed, sensor, cal, model, idm, out, truth_mesh, truth_sizing, setup.session, frames
        )
        rec = {"synthetic": True, "i": i, "truth": [float(v) for v in truth[i]], **common}
        rec.update(fit_lesion(one, setup, maps, acc))
        rec["setup_seconds_this_process"] = setup_s
        _write_record(path, rec)
        done += 1
        if limit and done >= limit:
            break


@dataclass
class FitSetup:
    """How ``run`` fits each lesion: the forward maps (levels, sizing, geometry), the fit's coordinate
    of E, its passes and intervals, and the camera session; its tags name the output folders."""

    geometry: str
    fit_mesh: str
    correct_mesh: str | None
    levels: list[str]  # the level(s) the model error is measured against
    correct_sizing: str
    coords: str
    session: str
    max_passes: int
    fine_mode: str

    @classmethod
    def from_options(
        cls, fit_mesh, error_mesh, correct_mesh, correct_sizing, geometry, coords, session, max_passes, fine_mode
    ) -> FitSetup:
        """Check the command's options (one line naming the flag, before any work)."""
        from elastimap.errors import UserError
        from elastimap.identify.forward_maps import check_correct, default_geometry, neighbour_level

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
        geometry = geometry or default_geometry()
        return cls(geometry, fit_mesh, correct_mesh, levels, correct_sizing, coords, session, max_passes, fine_mode)

    def tags(self) -> tuple[str, str]:
        """(calibration tag, fits tag): :func:`run_tags` plus the passes and the fine mode."""
        cal_tag, tag = run_tags(
            self.geometry, self.fit_mesh, self.correct_mesh, self.levels, self.coords, self.session, self.correct_sizing
        )
        tag += f"-p{self.max_passes}" if self.max_passes != 2 else ""
        tag += "-direct" if self.fine_mode == "direct" and self.correct_mesh else ""
        return cal_tag, tag

    @property
    def below(self) -> bool:
        """One bin rule for all the fit's maps (identify.forward_maps.reference_below)."""
        from elastimap.identify.forward_maps import BELOW_LEVELS

        return self.fit_mesh in BELOW_LEVELS

    @property
    def top_sizing(self) -> str:
        """The sizing of the map the fit stands for."""
        return self.correct_sizing if self.correct_mesh else "fixed"

    @property
    def intervals(self) -> str:
        """The calibrated interval only for the fit it was calibrated on (identify.intervals.CALIBRATED_FOR):
        (default_intervals: levels, morphed maps) with the fixed sizing, the default model-error level
        and passes, defect correction -- the benchmark's switches that infer does not have."""
        from elastimap.identify.forward_maps import default_intervals, neighbour_level

        calibrated_fit = (
            self.correct_sizing == "fixed"
            and self.levels == [neighbour_level(self.correct_mesh or self.fit_mesh)]
            and self.coords == "contrast"
            and self.max_passes == 2
            and self.fine_mode == "correct"
        )
        return default_intervals(self.fit_mesh, self.correct_mesh, self.geometry) if calibrated_fit else "gauss"

    def maps(self, acc: dict):
        """(forward, [model-error maps], correcting map or None), each timed into ``acc``."""
        from elastimap.identify.forward_maps import forward_map

        g, below = self.geometry, self.below
        fwd = _Timed(forward_map(self.fit_mesh, g, below=below), acc, "fit_level")
        alt = [_Timed(forward_map(v, g, sizing=self.top_sizing, below=below), acc, "alt_level") for v in self.levels]
        fine = None
        if self.correct_mesh:
            fine = _Timed(forward_map(self.correct_mesh, g, sizing=self.correct_sizing, below=below), acc, "fine_level")
        return fwd, alt, fine

    def label(self) -> str:
        """The records' ``fit_map``: what the fit ran on, in words."""
        sized = {
            k: "" if v == "fixed" else f" sized {v}"
            for k, v in (("fine", self.correct_sizing), ("alt", self.top_sizing))
        }
        how = "then fitted on" if self.fine_mode == "direct" else "defect-corrected by"
        s = f"{self.geometry}, {self.fit_mesh} mesh"
        s += f", {how} {self.correct_mesh}{sized['fine']}" if self.correct_mesh else ""
        s += f"; model error vs {'+'.join(self.levels)}{sized['alt']}; E coordinate {self.coords}"
        s += "; references: the d-bin below" if self.below and self.geometry == "morph" else ""
        return s + f"; {self.intervals} intervals"


def fit_lesion(one: LesionInputs, setup: FitSetup, maps, acc: dict) -> dict:
    """The physics fit of one lesion from its network estimate: the record's fit fields."""
    from elastimap.camera.infer import refine_estimates

    fwd, fwd_alt, fwd_fine = maps
    w, cam, di, net = one.world, one.camera, one.recovered, one.network
    before = dict(acc)
    c0 = time.process_time()
    (fit,) = refine_estimates(
        [copy.deepcopy(net)],
        None,
        forward=fwd,
        forward_alt=fwd_alt,
        forward_fine=fwd_fine,
        coords=setup.coords,
        max_passes=setup.max_passes,
        fine=setup.fine_mode,
        intervals=setup.intervals,
    )
    cpu_fit = time.process_time() - c0
    spent = {key: acc.get(key, 0) - before.get(key, 0) for key in acc}
    r = fit.fit
    return {
        "camera": "nominal"
        if setup.session == "nominal"
        else {"led_power": list(cam.led_power), "vignetting": cam.vignetting},
        "image_peak_mm": float(w["image"].max()),
        "recovered_z_rms": float(np.sqrt(np.mean(((di.image - w["image"]) / di.sigma) ** 2))),
        "network": net.to_dict(),
        "fit": fit.to_dict(),
        "seconds_camera_and_network": one.seconds,
        "seconds_fit": float(r.seconds) if r is not None else 0.0,
        "cpu_seconds_fit": cpu_fit,
        "fit_message": r.message if r is not None else "",
        # the fit's Gauss–Newton interval (θ̂ ± 1.96 sd clipped to the box) beside the reported one
        "fit_interval_gauss": {"lo": [float(v) for v in r.lo_gauss], "hi": [float(v) for v in r.hi_gauss]}
        if r is not None and r.lo_gauss is not None
        else None,
        # the Gauss–Newton relative sds (d, h; ln E) and the reported interval's scales
        # (identify.intervals): the fit's sd_q above is the Gauss–Newton one times the scale
        "fit_relstd_gauss": [float(v) for v in r.relstd] if r is not None else None,
        "fit_interval_scale": [float(v) for v in r.scale] if r is not None else None,
        "seconds_fit_level_solves": spent.get("fit_level", 0.0),
        "n_fit_level_solves": spent.get("fit_level_n", 0),
        "seconds_alt_level_solves": spent.get("alt_level", 0.0),
        "n_alt_level_solves": spent.get("alt_level_n", 0),
        "seconds_fine_level_solves": spent.get("fine_level", 0.0),
        "n_fine_level_solves": spent.get("fine_level_n", 0),
    }


def _write_record(path: str, rec: dict) -> None:
    """One lesion's JSON record, written atomically, and its line on stderr."""
    import json

    tmp = path + ".tmp"
    with open(tmp, "w") as fh:
        json.dump(rec, fh, indent=1)
    os.replace(tmp, path)
    (d, h, E), net, f = rec["truth"], rec["network"], rec["fit"]
    click.echo(
        f"lesion {rec['i']}: truth {d:.2f}/{h:.2f}/{E:.1f}  net {net['d']:.2f}/{net['h']:.2f}/{net['E']:.1f}  "
        f"fit {f['d']:.2f}/{f['h']:.2f}/{f['E']:.1f}  chi2 {f.get('fit_chi2_red', float('nan')):.2f}  "
        f"{rec['seconds_fit']:.1f} s ({rec['n_fit_level_solves']}+{rec['n_alt_level_solves']}"
        f"+{rec['n_fine_level_solves']} solves)",
        err=True,
    )


PRESS_MOVES = ((0.3, 0.0), (0.0, 0.3), (-0.8, 0.5), (1.0, -1.0))  # (Δd, Δh) mm from the pin


@click.command("press")
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
