"""Camera-side command line: ``elastimap camera {synth,features,calibrate,infer,detect}``.

Also installed as ``camera`` (the same group), and ``calibrate`` / ``infer`` are the very
``camera calibrate`` / ``camera infer`` command objects under a name of their own;
``python -m elastimap.camera.cli`` works too.  User errors end as one ``error: ...``
line and exit code 2 (:func:`elastimap.cli_util.run`); warnings about frames
(saturation, blank, colour) print as ``warning: ...`` lines.
"""

from __future__ import annotations

import json
import os
import sys
import warnings

import click
import numpy as np

from elastimap.cli_util import CONTEXT_SETTINGS, mesh_option, run
from elastimap.errors import UserError


def _show_warning(message, category, filename, lineno, file=None, line=None):
    click.echo(f"warning: {message}", err=True)


warnings.showwarning = _show_warning


def _description(path: str | None):
    """The sensor description of ``--sensor`` (:mod:`elastimap.sensor`: TOML, or an output's JSON
    record); None without ``--sensor`` or for a JSON object of camera parameters only (the camera
    files of earlier versions: the paper's mechanics with that camera)."""
    from elastimap.sensor import load

    if not path or _camera_only(path):
        return None
    return load(path)


def _camera_only(path: str) -> dict | None:
    """The JSON object of ``path`` when it holds SensorModel parameters only, else None."""
    from .optics import SensorModel

    if not str(path).lower().endswith(".json"):
        return None
    try:
        with open(path) as fh:
            base = json.load(fh)
    except FileNotFoundError:
        raise UserError("sensor", f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError("sensor", f"{path}: cannot read ({exc})") from None
    except json.JSONDecodeError as exc:
        raise UserError("sensor", f"{path}: not valid JSON ({exc})") from None
    if not isinstance(base, dict):
        raise UserError("sensor", f"{path}: must hold a JSON object (a sensor description or SensorModel parameters)")
    known = {f.name for f in __import__("dataclasses").fields(SensorModel)}
    return base if set(base) <= known else None


def _sensor(sensor_json: str | None, **overrides):
    """The camera of ``--sensor`` (a sensor description's, or a JSON object of SensorModel parameters),
    with the camera flags given (``overrides``) applied."""
    from .optics import SensorModel

    base = {}
    if sensor_json:
        base = _camera_only(sensor_json)
        if base is None:
            base = SensorModel.of(_description(sensor_json)).to_dict()
    base = dict(base)
    given = {k: v for k, v in overrides.items() if v is not None}
    base.update(given)
    try:
        return SensorModel.from_dict(base)
    except UserError as exc:
        if sensor_json and exc.param not in given:  # the value came from the file: name the file
            raise UserError("sensor", f"{sensor_json}: {exc.param}: {exc.message}") from None
        raise


def sensor_options(f):
    for opt in reversed(
        [
            click.option(
                "--sensor",
                "sensor_json",
                type=click.Path(dir_okay=False),
                help="Sensor description (TOML; docs/howto/your-own-sensor.md): its camera, and for the "
                "solves its probe, slab and loading; or a JSON object of SensorModel parameters (camera only).",
            ),
            click.option("--seed", type=int, default=None, help="Noise seed (default 0)."),
            click.option(
                "--noise-scale", type=float, default=None, help="Multiply shot + read noise (0 = noise-free)."
            ),
            click.option("--bits", type=click.Choice(["8", "16"]), default=None, help="Bit depth of frames."),
            click.option(
                "--binning", type=int, default=None, help="Software binning of the 1392x1042 sensor (default 10)."
            ),
        ]
    ):
        f = opt(f)
    return f


def feature_options(f):
    for opt in reversed(
        [
            click.option(
                "--o3-threshold",
                "threshold",
                type=float,
                default=None,
                help="O3 threshold on the camera difference image, fraction of full scale (default 0.0012).",
            ),
            click.option(
                "--smooth-px", type=float, default=None, help="Gaussian denoising sigma, camera pixels (default 1.5)."
            ),
            click.option(
                "--combine",
                type=click.Choice(["mean-image", "mean-features"]),
                default=None,
                help="Combine a lesion's frames: features of the mean image, or the mean of each frame's "
                "features (default mean-image).",
            ),
        ]
    ):
        f = opt(f)
    return f


def _settings(threshold=None, smooth_px=None, combine=None):
    from .features import FeatureSettings

    kw = {k: v for k, v in dict(threshold=threshold, smooth_px=smooth_px, combine=combine).items() if v is not None}
    return FeatureSettings(**kw).validate()


def _model_kw(seed, noise_scale, bits, binning):
    return dict(seed=seed, noise_scale=noise_scale, bits=None if bits is None else int(bits), binning=binning)


@click.group(context_settings=CONTEXT_SETTINGS)
def cli():
    """Camera side of elastimap: SYNTHETIC TIR camera, camera features, calibration, inference, detection."""


# -------------------------------------------------------------------- synth
@cli.command(context_settings=CONTEXT_SETTINGS)
@click.option("--d", "d", type=float, required=True, help="Inclusion diameter, mm.")
@click.option("--h", "h", type=float, required=True, help="Centre depth below the surface, mm.")
@click.option("--E", "E", type=float, required=True, help="Inclusion modulus, kPa.")
@click.option("--tissue-E", type=float, default=None, help="Tissue modulus, kPa [default: the sensor's, 5].")
@click.option("--delta", type=float, default=None, help="Indentation, mm [default: the sensor's, 3].")
@mesh_option()
@click.option("--frames", type=int, default=30, show_default=True, help="Camera frames per press.")
@click.option("--out", type=click.Path(file_okay=False), required=True, help="Folder for the frame files.")
@click.option("--name", default=None, help="File-name stem (default d<d>_h<h>_E<E>).")
@click.option(
    "--format", "fmt", type=click.Choice(["png", "tiff"]), default="png", show_default=True, help="Frame file format."
)
@sensor_options
def synth(d, h, E, tissue_e, delta, mesh, frames, out, name, fmt, sensor_json, seed, noise_scale, bits, binning):
    """Render SYNTHETIC camera frames of one inclusion and its background press (runs the FEM)."""
    from elastimap.outputs import check_out_dir
    from elastimap.sensor import Sensor

    from .calibration import default_fem
    from .frames import write_frames
    from .optics import render_pair

    model = _sensor(sensor_json, **_model_kw(seed, noise_scale, bits, binning))
    desc = _description(sensor_json)
    delta = (desc or Sensor()).loading.delta if delta is None else delta
    tissue_e = (desc or Sensor()).tissue.E if tissue_e is None else tissue_e
    from .deflection import MAX_FRAMES

    if not 1 <= frames <= MAX_FRAMES:
        raise UserError("frames", f"must be in [1, {MAX_FRAMES}] (got {frames})")
    if name is not None:
        from elastimap.tables import check_name

        check_name(name, "--name", "--name")  # it names the frame files: checked before the solve
    check_out_dir(out, "--out", allow_existing=True)
    res = default_fem(mesh, delta, desc)(d, h, E, tissue_E=tissue_e)
    F, B = render_pair(model, res.image_raw, res.image, res.pixel, frames)
    stem = name or f"d{d:g}_h{h:g}_E{E:g}"
    meta = {
        "d": d,
        "h": h,
        "E": E,
        "tissue_E": tissue_e,
        "delta": delta,
        "mesh": mesh,
        "fem_O1": res.O1,
        "fem_O2": res.O2,
        "fem_O3": res.O3,
        "sensor": model.to_dict(),
        **({"sensor_description": desc.to_dict(), "sensor_hash": desc.hash()} if desc else {}),
    }
    pl = write_frames(F, out, f"synthetic_{stem}", fmt, dict(meta, frame="lesion"))
    pb = write_frames(B, out, f"synthetic_{stem}_background", fmt, dict(meta, frame="background"))
    from elastimap.outputs import write_text

    doc = dict(meta, synthetic=True, lesion_frames=pl, background_frames=pb)
    write_text(os.path.join(out, f"synthetic_{stem}.json"), json.dumps(doc, indent=2), "--out")
    click.echo(
        f"{model.describe()}\nwrote {len(pl)} lesion + {len(pb)} background SYNTHETIC frames to {out}/ "
        f"(FEM O1={res.O1:.4g} mm O2={res.O2:.4g} mm O3={res.O3:.4g} mm^2)"
    )


# ----------------------------------------------------------------- features
@cli.command(context_settings=CONTEXT_SETTINGS)
@click.option("--images", multiple=True, required=True, help="Lesion frames (files or globs; repeatable).")
@click.option("--background", multiple=True, required=True, help="Background frames (files or globs).")
@click.option(
    "--sensor",
    "sensor_json",
    type=click.Path(dir_okay=False),
    help="Sensor description (TOML) or SensorModel JSON: the camera's geometry.",
)
@feature_options
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
def features(images, background, sensor_json, threshold, smooth_px, combine, as_json):
    """Camera features O1 (FS), O2 (FS mm^2), O3 (mm^2) of one lesion's frames."""
    from .features import features_from_files
    from .frames import expand

    cf = features_from_files(
        expand(list(images)),
        expand(list(background), param="background"),
        _sensor(sensor_json),
        _settings(threshold, smooth_px, combine),
    )
    if as_json:
        click.echo(json.dumps(cf.to_dict(), indent=2))
    else:
        click.echo(
            f"O1 = {cf.O1:.6g} FS  O2 = {cf.O2:.6g} FS mm^2  O3 = {cf.O3:.6g} mm^2  "
            f"({cf.n_frames} frames, {cf.n_background} background)"
        )


# ---------------------------------------------------------------- calibrate
@cli.command(context_settings=CONTEXT_SETTINGS)
@click.option(
    "--phantoms",
    type=click.Path(dir_okay=False),
    default=None,
    help="Phantom spec CSV (name,d,h,E[,tissue_E,tissue_thickness]); default dataset/phantoms.csv.",
)
@click.option(
    "--camera-csv",
    type=click.Path(dir_okay=False),
    default=None,
    help="CSV name,images,background of YOUR phantom images; without it the camera is SYNTHETIC.",
)
@click.option(
    "--allow-outside",
    is_flag=True,
    help="Let --camera-csv name frames outside its own folder (absolute paths, '..').",
)
@click.option(
    "--fem-features",
    type=click.Path(),
    default=None,
    help="Take FEM features from a CSV, a sweep's folder or Parquet file (name or tag 'phantom:<name>', "
    "O1,O2,O3) instead of solving.",
)
@mesh_option()
@click.option(
    "--delta", type=float, default=None, help="Indentation of the phantom presses, mm [default: the sensor's, 3]."
)
@click.option("--frames", type=int, default=30, show_default=True, help="Camera frames per synthetic press.")
@click.option(
    "--write-frames", type=click.Path(file_okay=False), default=None, help="Also save the synthetic frames here."
)
@click.option(
    "--format", "fmt", type=click.Choice(["png", "tiff"]), default="png", help="Format of --write-frames' files."
)
@click.option(
    "--refine-level",
    default="auto",
    show_default=True,
    metavar="LEVEL|auto|none",
    help="Learn the model-form error (docs/model-form.md) for the infer --refine fit standing for this mesh "
    "level, from the phantoms' frames at their known (d, h, E): auto = fine (the default --refine, coarse "
    "corrected by fine), tiny with --mesh tiny; none = do not learn it (--refine then fits the closed world).",
)
@click.option(
    "--report-loo",
    is_flag=True,
    help="Also fit each phantom from its frames as infer --refine does, with the model-form error learnt "
    "from the others, and report (and store) the 95 % intervals' leave-one-phantom-out coverage "
    "(about 30-60 s CPU a phantom).",
)
@click.option(
    "--press-uncertainty/--no-press-uncertainty",
    default=True,
    show_default=True,
    help="Carry the flat field's press uncertainty into infer --refine (and --report-loo): the spread of "
    "elastimap's own models of the background press (contact interface, neighbouring mesh level; two extra "
    "solves) where the phantoms do not see it, as a low-rank error of the recovered image (docs/camera.md, "
    "'The flat field's press uncertainty').  --no-press-uncertainty: the calibration before it.",
)
@click.option("--out", type=click.Path(dir_okay=False), required=True, help="Calibration JSON to write.")
@click.option(
    "--plot", type=click.Path(dir_okay=False), default=None, help="PNG of the three fits (default <out>.png)."
)
@sensor_options
@feature_options
def calibrate(
    phantoms,
    camera_csv,
    allow_outside,
    fem_features,
    mesh,
    delta,
    frames,
    write_frames,
    fmt,
    refine_level,
    report_loo,
    press_uncertainty,
    out,
    plot,
    sensor_json,
    seed,
    noise_scale,
    bits,
    binning,
    threshold,
    smooth_px,
    combine,
):
    """Fit O_FEM = a O_cam + b per feature on the nine calibration phantoms (paper 3.3); solve the
    deflection calibration camera frames need (image models, --refine) and learn the model-form error
    the --refine fit carries (docs/model-form.md, 'How the fit carries it')."""
    from elastimap.dataset.schema import PHANTOMS_CSV
    from elastimap.sensor import Sensor

    from . import calibration as C

    model = _sensor(sensor_json, **_model_kw(seed, noise_scale, bits, binning))
    desc = _description(sensor_json)
    delta = (desc or Sensor()).loading.delta if delta is None else delta
    settings = _settings(threshold, smooth_px, combine)
    ph, level, fem_given, png = _calibrate_inputs(
        phantoms, camera_csv, fem_features, sensor_json, frames, refine_level, mesh, report_loo, out, plot, write_frames
    )
    synthetic = camera_csv is None
    fem_fn = C.default_fem(mesh, delta, desc)
    if synthetic:
        fem, cam, results, pairs = _simulated_phantoms(ph, fem_fn, model, settings, frames, write_frames, fmt)
    else:
        fem, cam, results, pairs = _measured_phantoms(ph, fem_fn, model, settings, camera_csv, allow_outside)
    if fem_given is not None:
        fem = fem_given
    defl = C.deflection_calibration(results, pairs, model)
    if press_uncertainty:
        defl["press_sd"] = _press_sd(ph, results, mesh, delta, desc)
    disc = None if level is None else _learn_model_form(ph, pairs, defl, level, model, desc, report_loo)
    run = {
        "mesh": mesh,
        "delta": delta,
        "frames": frames,
        "phantoms_file": str(phantoms or PHANTOMS_CSV),
        "camera_csv": camera_csv,
        "fem_features": fem_features,
        "refine_level": level,
        **({"sensor_description": desc.to_dict(), "sensor_hash": desc.hash()} if desc else {}),
    }
    cal = C.fit_calibration(ph, fem, cam, settings.to_dict(), model.to_dict(), synthetic, run, defl, disc)
    _write_calibration(cal, out, png)


def _calibrate_inputs(
    phantoms, camera_csv, fem_features, sensor_json, frames, refine_level, mesh, report_loo, out, plot, write_frames
):
    """``calibrate``'s inputs read and every output location checked before anything is solved or
    written: (the phantoms' table, the model-form error's mesh level or None, the FEM features of
    --fem-features or None, the figure's path)."""
    from elastimap.dataset.phantoms import read_phantoms
    from elastimap.outputs import check_out_dir, check_out_file, figure_suffixes

    from . import calibration as C
    from .deflection import MAX_FRAMES, MIN_FRAMES

    if not MIN_FRAMES <= frames <= MAX_FRAMES:  # the deflection calibration measures the noise from the frames' scatter
        raise UserError("--frames", f"must be in [{MIN_FRAMES}, {MAX_FRAMES}] (got {frames})")
    ph = read_phantoms(phantoms, min_rows=3, why="to fit a calibration line")
    level = _refine_level(refine_level, mesh)
    if report_loo and level is None:
        raise UserError("--report-loo", "needs the model-form error (--refine-level not none)")
    fem_given = C.fem_features_from_csv(fem_features, ph) if fem_features else None
    keep = {"--phantoms": phantoms, "--camera-csv": camera_csv, "--fem-features": fem_features, "--sensor": sensor_json}
    check_out_file(out, "--out", inputs=keep)
    png = plot or os.path.splitext(out)[0] + ".png"
    if os.path.abspath(png) == os.path.abspath(out):
        raise UserError("--plot", f"{png} is also --out; give the figure another name")
    check_out_file(png, "--plot", suffixes=figure_suffixes(), inputs=keep)
    if write_frames:
        check_out_dir(write_frames, "--write-frames", allow_existing=True)
    return ph, level, fem_given, png


def _press_sd(ph, results, mesh: str, delta: float, desc) -> list:
    """The flat field's press uncertainty (docs/camera.md, 'The flat field's press uncertainty'):
    the spread (mm) of elastimap's own models of the background press (contact interface,
    neighbouring mesh level; two extra solves at the first phantom, ``delta`` mm) where the
    phantoms' images do not see it (:func:`elastimap.camera.deflection.uninformed`)."""
    from . import calibration as C
    from .deflection import PRESS_POWER, uninformed

    click.echo("solving the press's alternatives (contact, neighbouring level) ...", err=True)
    th0 = [float(ph.iloc[0][k]) for k in ("d", "h", "E")]
    sd = C.press_uncertainty(th0, results[0], mesh, delta, desc)
    return uninformed(sd, [r.image for r in results], PRESS_POWER).tolist()


def _write_calibration(cal, out: str, png: str) -> None:
    """Write the calibration JSON (--out) and its figure (--plot), then report them."""
    from elastimap.outputs import write_or_fallback

    from . import calibration as C

    write_or_fallback(cal.save, out, "--out")
    os.makedirs(os.path.dirname(os.path.abspath(png)), exist_ok=True)
    write_or_fallback(lambda f: C.plot_calibration(cal, f), png, "--plot")
    click.echo(cal.report())
    click.echo(f"wrote {out} and {png}")


def _simulated_phantoms(ph, fem_fn, model, settings, frames: int, write_frames, fmt):
    """``calibrate`` without --camera-csv: the phantoms' FEM solves and their SYNTHETIC camera frames.
    Returns the FEM features, the camera features, the solves and the (lesion, background) frames."""
    from . import calibration as C

    def progress(name, f, c):
        click.echo(
            f"  {name:14s} FEM {f[0]:.4g} {f[1]:.4g} {f[2]:.4g}   camera {c[0]:.4g} {c[1]:.4g} {c[2]:.4g}", err=True
        )

    pairs = []
    fem, cam, results = C.simulate_phantoms(
        ph, fem_fn, model, settings, frames, model.seed, write_frames, fmt, progress, frames_out=pairs
    )
    return fem, cam, results, pairs


def _measured_phantoms(ph, fem_fn, model, settings, camera_csv: str, allow_outside):
    """``calibrate --camera-csv``: the lab's frames of the phantoms (features and frame stacks) and the
    FEM solves at their known (d, h, E), which the FEM-equivalent difference images (image models,
    --refine) need also where the FEM features come from a sweep (--fem-features)."""
    from . import calibration as C
    from .deflection import MIN_FRAMES

    pairs = []
    cam = C.camera_features_from_csv(camera_csv, ph, model, settings, frames_out=pairs, allow_outside=allow_outside)
    few = [str(n) for n, (F, B) in zip(ph["name"], pairs) if min(len(F), len(B)) < MIN_FRAMES]
    if few:  # the deflection calibration after the solves needs them: say so before
        raise UserError("--camera-csv", f"{camera_csv}: fewer than {MIN_FRAMES} frames for {', '.join(few[:5])}")
    results = [fem_fn(float(x["d"]), float(x["h"]), float(x["E"])) for _, x in ph.iterrows()]
    return np.array([[r.O1, r.O2, r.O3] for r in results]), cam, results, pairs


def _learn_model_form(ph, pairs, defl: dict, level: str, model, desc, report_loo: bool) -> dict:
    """``calibrate``'s model-form record (:func:`elastimap.camera.calibration.learn_discrepancy`) for the
    --refine fit at ``level``, with the leave-one-phantom-out fits printed when ``report_loo``."""
    from . import calibration as C

    click.echo(f"learning the model-form error for the --refine fit at level {level} ...", err=True)
    disc = C.learn_discrepancy(ph, pairs, defl, level, model, description=desc)
    if report_loo:

        def said(name, row):
            click.echo(
                f"  {name:14s} fit {row['theta'][0]:.3g}/{row['theta'][1]:.3g}/{row['theta'][2]:.3g}  "
                f"covered d/h/E {'/'.join('yes' if c else 'no' for c in row['covered'])}",
                err=True,
            )

        disc["fits"] = C.loo_fits(disc, ph, pairs, defl, model, said, description=desc)
    return disc


# -------------------------------------------------------------------- infer
@cli.command(context_settings=CONTEXT_SETTINGS)
@click.option(
    "--model",
    "model_dir",
    type=click.Path(),
    required=True,
    help="Trained model directory: a feature ensemble (elastimap train) or an image model "
    "(elastimap study image_model --save-model DIR).",
)
@click.option(
    "--calibration",
    type=click.Path(dir_okay=False),
    default=None,
    help="FEM<->camera calibration (calibrate); needed for camera features and frames.",
)
@click.option("--features", "feats", type=float, nargs=3, default=None, help="Camera features O1 O2 O3.")
@click.option("--images", multiple=True, help="Lesion frames (files or globs; repeatable).")
@click.option("--background", multiple=True, help="Background frames for --images.")
@click.option(
    "--csv",
    "csv_path",
    type=click.Path(dir_okay=False),
    default=None,
    help="Batch: CSV with id and O1,O2,O3, images,background (frame globs) or fem_image (.npy); docs/camera.md.",
)
@click.option(
    "--fem-image",
    "fem_image",
    type=click.Path(dir_okay=False),
    default=None,
    help="Image model only: .npy FEM difference image(s), mm, shape (ny, nx) or (n, ny, nx) on the "
    "sweep's grid (no calibration needed).",
)
@click.option(
    "--identifiability",
    default="default",
    show_default=True,
    help="Identifiability map (crb_grid.npz of elastimap study crbmap), 'default' (shipped, "
    "default 512-sample sweep) or 'none'.",
)
@click.option(
    "--crb-limit",
    "threshold",
    default=0.10,
    show_default=True,
    type=float,
    help="Cramér–Rao relative std above which an output is flagged non-identifiable.",
)
@click.option(
    "--refine",
    is_flag=True,
    help="Image models (--fem-image, --images or --csv): refine each estimate by the maximum-likelihood fit of "
    "the forward map (elastimap.identify.fit.fit_image: runs the solver, about 20-30 forward solves per "
    "lesion); 95 % intervals from the Gauss-Newton covariance, for the default --mesh coarse corrected by fine "
    "scaled per class of each parameter's relative sd (and by whether the estimated inclusion's bottom lies "
    "within 3 mm of the slab's base) as calibrated on SYNTHETIC benchmark lesions "
    "(elastimap.identify.intervals; docs/camera.md, 'Inference').  From frames, every pixel is weighted by "
    "its own noise, measured from the frames' scatter, plus the forward map's error measured between two "
    "mesh levels.  With a --calibration that carries the lab's model-form error (camera calibrate), the "
    "intervals and identifiability flags also hold it (docs/model-form.md, 'How the fit carries it').",
)
@click.option(
    "--image-noise",
    default=0.01,
    show_default=True,
    type=float,
    help="--refine with --fem-image: the pixel noise relative to the image's peak (frames measure their own).",
)
@mesh_option(
    default="coarse",
    help="--refine: mesh level of the forward map; its error is measured against the neighbouring level of "
    "the level the fit stands for (with --refine-correct, that level's).",
)
@click.option(
    "--refine-correct",
    "correct",
    default="auto",
    show_default=True,
    metavar="LEVEL|auto|none",
    help="--refine: a finer mesh level (e.g. fine) whose solve corrects the forward map's defect at the start "
    "of each pass after the first; the fit then stands for that level and its error is measured against "
    "that level's neighbour.  Removes most of the coarse map's bias in d and E (docs/camera.md, 'Inference') at "
    "one or two solves of that level per lesion.  auto: fine for --mesh coarse (the benchmarked "
    "configuration), none for the other levels; none: the map alone.",
)
@click.option(
    "--allow-outside", is_flag=True, help="Let --csv name files outside its own folder (absolute paths, '..')."
)
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
@click.option("--out", type=click.Path(dir_okay=False), default=None, help="Also write .csv or .json here.")
@click.option(
    "--sensor",
    "sensor_path",
    type=click.Path(dir_okay=False),
    default=None,
    help="The sensor the lesion was imaged with (TOML; docs/howto/your-own-sensor.md); refused when the model or "
    "the calibration records another [default: theirs].",
)
def infer(
    model_dir,
    calibration,
    feats,
    images,
    background,
    csv_path,
    fem_image,
    identifiability,
    threshold,
    refine,
    image_noise,
    mesh,
    correct,
    allow_outside,
    as_json,
    out,
    sensor_path,
):
    """Estimate (d, h, E) with intervals; out-of-range inputs and non-identifiable outputs are flagged.

    An output the identifiability map calls non-identifiable at the estimate (Cramér–Rao relative
    std above --crb-limit) is printed as its interval, not as a number.  From camera frames with an
    image model the bound is the larger of the map's camera set (the nominal camera's noise, scaled
    by the frames' own scatter) and its 1 % image set (output column crb_set: frames), otherwise
    the 1 % set.
    """
    from .infer import load_identifiability, load_model

    _check_infer_inputs(feats, images, csv_path, fem_image, threshold, identifiability, refine, image_noise)
    correct = _refine_correct(refine, mesh, correct)
    if fem_image is not None and not os.path.isfile(fem_image):
        raise UserError("--fem-image", f"{fem_image}: no such file")
    if background and not images:
        raise UserError("--background", "goes with --images (the lesion frames)")
    if out:
        from elastimap.outputs import check_out_file

        keep = {"--model": model_dir, "--calibration": calibration, "--csv": csv_path, "--fem-image": fem_image}
        check_out_file(out, "--out", suffixes=(".csv", ".json"), inputs={**keep, "--sensor": sensor_path})
    idm = load_identifiability(None if identifiability == "none" else identifiability)
    model = load_model(model_dir)
    if refine and fem_image is not None and model.input_kind != "image":
        raise UserError("--refine", "--fem-image needs an image model (elastimap study image_model --save-model DIR)")
    from elastimap.sensor import load as load_sensor

    from .calibration import Calibration

    cal = Calibration.load(calibration) if calibration is not None else None
    sensor = _check_sensor(load_sensor(sensor_path) if sensor_path else None, model, cal)
    sensor_hash = None if sensor is None else sensor.hash()
    ests = _estimates(model, idm, threshold, refine, cal, feats, images, background, csv_path, fem_image, allow_outside)
    if refine:
        ests = _refined(ests, cal, mesh, correct, image_noise, threshold, sensor)
    from elastimap.provenance import stamp

    prov = stamp()
    versions = ", ".join(f"{k} {v}" for k, v in prov["versions"].items())
    rows = [
        {**e.to_dict(), "sensor_hash": sensor_hash, "code_version": prov["code_version"], "versions": versions}
        for e in ests
    ]
    if out:
        _write_rows(rows, out)
    if as_json:
        click.echo(json.dumps(rows, indent=2))
    else:
        _echo_rows(rows)
    if cal is not None and fem_image is None and cal.synthetic:
        click.echo("note: the calibration was made with the SYNTHETIC camera", err=True)


def _check_infer_inputs(feats, images, csv_path, fem_image, threshold, identifiability, refine, image_noise):
    """``infer``'s one-line refusals of its input kind and settings, before anything is read."""
    given = sum(x for x in (feats is not None, bool(images), csv_path is not None, fem_image is not None))
    if given != 1:
        raise UserError(
            "input",
            "give exactly one of --features O1 O2 O3, --images ... --background ..., --csv FILE, --fem-image FILE.npy",
        )
    if not 0 < threshold < 10:
        raise UserError("--crb-limit", f"must be in (0, 10) (got {threshold:g})")
    if not identifiability.strip():
        raise UserError("--identifiability", "must be a crb_grid.npz file, 'default' or 'none' (got '')")
    if refine and feats is not None:
        raise UserError("--refine", "needs an image (--fem-image, --images or --csv) and an image model, not features")
    if refine and not 0 < image_noise < 1:
        raise UserError("--image-noise", f"must be in (0, 1) (got {image_noise:g})")


def _refined(ests, cal, mesh: str, correct, image_noise: float, threshold: float, sensor):
    """``infer --refine``: each estimate refined by the physics fit (docs/camera.md, 'Physics fit
    (--refine)'), carrying the calibration's model-form error where it has one."""
    from tqdm import tqdm

    from . import calibration as C
    from .infer import refine_estimates, sensor_of

    form = _model_form(cal, mesh, correct)  # also for --fem-image given with --calibration
    with tqdm(total=len(ests), desc="refine (FEM fit)", unit="lesion", disable=len(ests) < 2) as bar:
        return refine_estimates(
            ests,
            None,
            image_noise=image_noise,
            mesh=mesh,
            correct=correct,
            threshold=threshold,
            progress=lambda i, n: bar.update(1),
            sensor=sensor,
            discrepancy=form[0] if form else None,
            pixel=form[2] if form else None,
            press=C.press_term(cal.deflection, sensor_of(cal)) if cal is not None else None,
        )


def _echo_rows(rows) -> None:
    """``infer``'s table: one line a lesion, a quantity printed as its interval where not reportable."""
    for r in rows:
        click.echo(
            f"{r['id']}: "
            + "   ".join(_quantity(r, q, u) for q, u in (("d", "mm"), ("h", "mm"), ("E", "kPa")))
            + "   "
            + ("ok" if r["ok"] else f"FLAGGED: {r['flags']}")
        )


def _check_sensor(sensor, model, cal):
    """The sensor the estimates stand for: ``--sensor``'s, else the calibration's, else the model's
    (None when none records one; ``--refine``'s maps press with it).  The model (trained on FEM
    features) and the calibration must stand for the same probe, slab, loading and interface as
    ``--sensor`` (and as each other)."""
    from elastimap.sensor import CameraSpec, Sensor

    from .optics import SensorModel

    def mechanics(s):  # the sensor without its camera and name: what the FEM sees
        return s.replace(name="-", camera=CameraSpec(footprint_mm=s.probe.footprint)).hash()

    recorded = {}
    meta = getattr(model, "meta", None) or {}
    if meta.get("sensor"):
        recorded["the model"] = Sensor.from_dict(meta["sensor"])
    if cal is not None:
        d = cal.meta.get("sensor_description")
        camera = Sensor().replace(camera=SensorModel.from_dict(cal.sensor).spec()) if cal.sensor else Sensor()
        recorded["the calibration"] = Sensor.from_dict(d) if d else camera
    if sensor is not None:
        for what, s in recorded.items():
            if mechanics(s) != mechanics(sensor):
                raise UserError(
                    "sensor",
                    f"{what} was made with another sensor ({s.name!r}, hash {s.hash()}) than {sensor.name!r} "
                    f"(hash {sensor.hash()}): its probe, slab, loading or interface differ",
                )
        chosen = sensor
    else:
        if len({mechanics(s) for s in recorded.values()}) > 1:
            raise UserError(
                "calibration",
                "the model and the calibration were made with different sensors ("
                + ", ".join(f"{w}: {s.name!r}, hash {s.hash()}" for w, s in recorded.items())
                + ")",
            )
        chosen = recorded.get("the calibration") or recorded.get("the model")
    return chosen


def _model_form(cal, mesh: str, correct: str | None):
    """The calibration's model-form term for the --refine fit at ``mesh`` corrected by ``correct``:
    ``(Discrepancy, level, pixel)`` or None (no calibration, or one without it: the closed world); a
    term learnt for another level than the fit stands for is refused."""
    form = cal.model_form() if cal is not None else None
    if form is not None and form[1] != (correct or mesh):
        raise UserError(
            "--mesh",
            f"the calibration's model-form error was learnt for the fit at level {form[1]}, this --refine fit "
            f"stands for {correct or mesh} (recalibrate with --refine-level {correct or mesh})",
        )
    return form


def _refine_level(refine_level: str, mesh: str) -> str | None:
    """``calibrate --refine-level`` checked before any work: the mesh level whose --refine fit the
    model-form error is learnt for, or None."""
    from elastimap.solver.params import MESH_LEVELS

    if refine_level == "none":
        return None
    if refine_level == "auto":
        return "tiny" if mesh == "tiny" else "fine"
    if refine_level not in MESH_LEVELS:
        raise UserError(
            "--refine-level", f"must be auto, none or one of {', '.join(MESH_LEVELS)} (got {refine_level!r})"
        )
    return refine_level


def _refine_correct(refine: bool, mesh: str, correct: str) -> str | None:
    """``--refine-correct`` checked before any work: the finer level that corrects the fit's map, or None."""
    if correct not in ("auto", "none"):
        from elastimap.identify.forward_maps import check_correct

        if not refine:
            raise UserError("--refine-correct", "only applies with --refine")
        try:
            check_correct(mesh, correct)
        except UserError as exc:
            raise UserError(
                "--refine-correct", "must be auto, none or " + exc.message.removeprefix("must be ")
            ) from None
        return correct
    if refine:
        from elastimap.identify.forward_maps import default_correct

        return default_correct(mesh) if correct == "auto" else None
    return None


def _estimates(model, idm, threshold, refine, cal, feats, images, background, csv_path, fem_image, allow_outside=False):
    """The estimates of the one input given (``infer``'s options); ``cal`` the loaded calibration or None."""
    from .frames import expand
    from .infer import estimate, estimate_fem_images, estimate_images, estimate_lesions_csv, fem_image_stack

    if fem_image is not None:
        try:
            arr = np.load(fem_image, allow_pickle=False)
        except Exception as exc:
            raise UserError("--fem-image", f"{fem_image}: not a .npy array ({exc})") from None
        arr = fem_image_stack(arr, model, "--fem-image", fem_image)
        return estimate_fem_images(arr, model, identifiability=idm, threshold=threshold)
    if cal is None and not csv_path:
        raise UserError("--calibration", "camera features and frames need the FEM<->camera calibration file")
    if images:
        if not background:
            raise UserError("background", "--images needs --background frames (the same press without the lesion)")
        im, bg = expand(list(images)), expand(list(background), param="background")
        return [estimate_images(im, bg, cal, model, "1", idm, threshold, keep_image=refine)]
    if csv_path:
        return estimate_lesions_csv(
            csv_path, cal, model, idm, threshold, keep_image=refine, allow_outside=allow_outside
        )
    return estimate(np.array([feats]), cal, model, ["1"], idm, threshold)


def _write_rows(rows: list[dict], out: str) -> None:
    """``--out``: the estimates as JSON (``.json``) or CSV."""
    from elastimap.outputs import write_or_fallback

    def _write(path):
        if out.endswith(".json"):
            with open(path, "w") as fh:
                json.dump(rows, fh, indent=2)
        else:
            import pandas as pd

            pd.DataFrame(rows).to_csv(path, index=False)

    write_or_fallback(_write, out, "--out")


def _quantity(r: dict, q: str, unit: str) -> str:
    lo, hi = r[f"{q}_lo"], r[f"{q}_hi"]
    if not r[f"{q}_reportable"]:
        why = "not identifiable here" if not r[f"{q}_identifiable"] else "no reliable estimate"
        return f"{q}: {why}, {lo:.3g}-{hi:.3g} {unit}" if np.isfinite(lo) and np.isfinite(hi) else f"{q}: {why}"
    s = f"{q} = {r[q]:.3g} ± {r[f'{q}_sd']:.2g} {unit}"
    return s + (f" [{lo:.3g}, {hi:.3g}]" if np.isfinite(lo) else "")


# ------------------------------------------------------------------- detect
@cli.command(context_settings=CONTEXT_SETTINGS)
@mesh_option()
@click.option("--repeats", type=int, default=1, show_default=True, help="Scans per inclusion (and clean scans).")
@click.option("--clutter-mm", type=float, default=None, help="Tissue heterogeneity sd, mm (default 0.002).")
@click.option(
    "--press-jitter", type=float, default=None, help="Relative sd of the press depth between scans (default 0.05)."
)
@click.option("--out", type=click.Path(file_okay=False), required=True, help="Folder for the ROC table and figure.")
@click.option("--noise-scales", default=None, help="Comma list: also report AUC at these noise scales.")
@sensor_options
def detect(mesh, repeats, clutter_mm, press_jitter, out, noise_scales, sensor_json, seed, noise_scale, bits, binning):
    """SYNTHETIC detection study (paper 5.3): sensitivity, specificity, ROC, AUC with bootstrap CI."""
    from elastimap.outputs import check_out_dir

    from .calibration import default_fem
    from .detection import DETECTION_INCLUSIONS, PAPER, DetectionSettings, plot_roc, run_detection

    model = _sensor(sensor_json, **_model_kw(seed, noise_scale, bits, binning))
    kw = {k: v for k, v in dict(clutter_mm=clutter_mm, press_jitter=press_jitter).items() if v is not None}
    if repeats < 1:
        raise UserError("--repeats", f"must be >= 1 (got {repeats})")
    try:
        extra = [float(x) for x in noise_scales.split(",")] if noise_scales else []
    except ValueError:
        raise UserError("--noise-scales", f"expected numbers like 0.5,2 (got {noise_scales!r})") from None
    if any(not (np.isfinite(x) and x >= 0) for x in extra):
        raise UserError("--noise-scales", f"must be finite numbers >= 0 (got {noise_scales!r})")
    check_out_dir(out, "--out", allow_existing=True)  # before the solves; created only when results exist
    s = DetectionSettings(repeats=repeats, seed=model.seed, **kw)
    fem = default_fem(mesh)
    results = [fem(d, h, E) for d, h, E in DETECTION_INCLUSIONS]
    os.makedirs(out, exist_ok=True)
    scales = [model.noise_scale] + extra
    table = []
    for ns in scales:
        r = run_detection(results, model.replace(noise_scale=ns), s)
        table.append(r)
        tag = f"noise{ns:g}"
        plot_roc(r, os.path.join(out, f"synthetic_roc_{tag}.png"))
        with open(os.path.join(out, f"synthetic_detection_{tag}.json"), "w") as fh:
            json.dump(r, fh, indent=2)
    click.echo(
        f"SYNTHETIC detection, {table[0]['n_pos']} inclusion + {table[0]['n_neg']} clean scans, "
        f"clutter {s.clutter_mm:g} mm, press jitter {s.press_jitter:g}, mesh {mesh}"
    )
    click.echo(f"{'noise x':>8} {'sens':>7} {'spec':>7} {'AUC':>6}  95% CI")
    for r in table:
        click.echo(
            f"{r['noise_scale']:8g} {100 * r['sensitivity']:6.1f}% {100 * r['specificity']:6.1f}% "
            f"{r['auc']:6.3f}  [{r['auc_ci95'][0]:.3f}, {r['auc_ci95'][1]:.3f}]"
        )
    click.echo(
        f"{'paper':>8} {100 * PAPER['sensitivity']:6.1f}% {100 * PAPER['specificity']:6.1f}% "
        f"{PAPER['auc']:6.3f}  (8 + 8 scans, MammaCare phantom)"
    )
    click.echo(f"wrote {out}/")


def calibrate_main():
    run(calibrate, prog_name="calibrate")


def infer_main():
    run(infer, prog_name="infer")


def main(argv=None):
    run(cli, argv, prog_name="camera")


if __name__ == "__main__":
    run(cli, prog_name="python -m elastimap.camera.cli")
    sys.exit(0)
