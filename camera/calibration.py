"""FEM <-> camera calibration (paper section 3.3).

The FEM measures probe deformation (mm); the camera measures scattered light.
Nine calibration inclusions (three phantoms: size, depth, hardness; three
inclusions each; background 5 kPa, 20 mm tall; ``dataset/phantoms.csv``) are
both simulated (FEM features) and imaged (camera features), and each feature
gets its own straight line fitted by least squares::

    O_FEM^k = a_k * O_cam^k + b_k        k = 1, 2, 3

The calibration file (JSON) stores a, b, R^2, the residuals, the ranges of
both feature sets over the nine phantoms (inputs outside them are flagged at
inference), the camera-feature settings and, for synthetic calibrations, the
sensor model, so that inference computes camera features the same way.

For image models it also stores the *deflection calibration* (:func:`deflection_calibration`):
the FEM reference press (no inclusion) that flat-fields the background frames, and the
least-squares factor between the phantoms' difference images recovered from their frames
(:mod:`elastimap.camera.deflection`) and their FEM difference images, with each phantom's relative
rms residual (how well the camera's inverse response reproduces the FEM images).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from elastimap.dataset.phantoms import is_phantom, phantom_name
from elastimap.dataset.schema import FEATURES, UNITS
from elastimap.errors import UserError

FEM_UNITS = {k: UNITS[k] for k in FEATURES}
CALIBRATION_VERSION = 1


@dataclass
class LineFit:
    slope: float
    intercept: float
    r2: float
    residuals: list[float]  # O_FEM - (a O_cam + b), per phantom, FEM units
    rmse: float

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def fit_line(x_cam: np.ndarray, y_fem: np.ndarray, name: str = "feature") -> LineFit:
    """Least-squares y = a x + b with R^2 and residuals."""
    x = np.asarray(x_cam, dtype=float)
    y = np.asarray(y_fem, dtype=float)
    if x.shape != y.shape or x.ndim != 1 or x.size < 2:
        raise UserError(name, "needs matching 1-D camera and FEM values for at least 2 phantoms")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise UserError(name, "camera or FEM features contain NaN/inf")
    if np.ptp(x) == 0:
        raise UserError(name, "camera features are identical for all phantoms: cannot fit a line")
    a, b = np.polyfit(x, y, 1)
    res = y - (a * x + b)
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - float(np.sum(res**2)) / ss_tot if ss_tot > 0 else float("nan")
    return LineFit(float(a), float(b), r2, [float(r) for r in res], float(np.sqrt(np.mean(res**2))))


@dataclass
class Calibration:
    fits: dict[str, LineFit]
    names: list[str]
    phantoms: list[dict]  # name, d, h, E of each calibration inclusion
    fem: np.ndarray  # (n, 3) FEM features
    cam: np.ndarray  # (n, 3) camera features
    feature_settings: dict
    sensor: dict | None = None  # the synthetic sensor model (None for real images)
    synthetic: bool = True
    meta: dict = field(default_factory=dict)
    deflection: dict | None = None  # see deflection_calibration (None: image models cannot use frames)
    discrepancy: dict | None = None  # see learn_discrepancy (None: --refine fits the closed world)

    # ranges over the calibration set
    @property
    def cam_range(self) -> np.ndarray:
        return np.vstack([self.cam.min(axis=0), self.cam.max(axis=0)])

    @property
    def fem_range(self) -> np.ndarray:
        return np.vstack([self.fem.min(axis=0), self.fem.max(axis=0)])

    @property
    def slopes(self) -> np.ndarray:
        return np.array([self.fits[k].slope for k in FEATURES])

    @property
    def intercepts(self) -> np.ndarray:
        return np.array([self.fits[k].intercept for k in FEATURES])

    def apply(self, cam: np.ndarray) -> np.ndarray:
        """Camera features (n, 3) or (3,) -> calibrated FEM features, same shape."""
        c = np.asarray(cam, dtype=float)
        return c * self.slopes + self.intercepts

    def outside(self, cam: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Boolean (n, 3): camera feature outside the calibration range (widened by ``margin`` x span)."""
        c = np.atleast_2d(np.asarray(cam, dtype=float))
        lo, hi = self.cam_range
        span = hi - lo
        return (c < lo - margin * span) | (c > hi + margin * span)

    # ------------------------------------------------------------------ io
    def to_dict(self) -> dict:
        return {
            "kind": "elastimap.camera.calibration",
            "version": CALIBRATION_VERSION,
            "synthetic": self.synthetic,
            "model": "O_FEM = slope * O_cam + intercept, per feature",
            "units": {"fem": FEM_UNITS, "camera": {"O1": "FS", "O2": "FS mm^2", "O3": "mm^2"}},
            "fits": {k: self.fits[k].to_dict() for k in FEATURES},
            "phantoms": [
                dict(
                    p,
                    **{f"fem_{k}": float(self.fem[i, j]) for j, k in enumerate(FEATURES)},
                    **{f"cam_{k}": float(self.cam[i, j]) for j, k in enumerate(FEATURES)},
                )
                for i, p in enumerate(self.phantoms)
            ],
            "cam_range": self.cam_range.tolist(),
            "fem_range": self.fem_range.tolist(),
            "feature_settings": self.feature_settings,
            "sensor": self.sensor,
            "meta": self.meta,
            "deflection": self.deflection,
            "discrepancy": self.discrepancy,
        }

    def save(self, path: str | os.PathLike) -> None:
        """Write the calibration JSON whole (:func:`elastimap.outputs.write_text`: an existing file
        is replaced only by a complete new one)."""
        from elastimap.outputs import write_text

        Path(path).parent.mkdir(parents=True, exist_ok=True)
        write_text(path, json.dumps(self.to_dict(), indent=2) + "\n", "out")

    @classmethod
    def load(cls, path: str | os.PathLike) -> Calibration:
        p = str(path)
        if not os.path.exists(p):
            raise UserError("calibration", f"{p}: no such file")
        try:
            with open(p) as fh:
                d = json.load(fh)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise UserError("calibration", f"{p}: not a valid JSON file ({exc})") from None
        if not isinstance(d, dict) or d.get("kind") != "elastimap.camera.calibration":
            raise UserError("calibration", f"{p}: not an elastimap camera calibration file")
        if d.get("version") != CALIBRATION_VERSION:
            raise UserError(
                "calibration",
                f"{p}: calibration version {d.get('version')} not supported (expected {CALIBRATION_VERSION})",
            )
        try:
            fits = {k: LineFit(**d["fits"][k]) for k in FEATURES}
            ph = d["phantoms"]
            fem = np.array([[r[f"fem_{k}"] for k in FEATURES] for r in ph], dtype=float)
            cam = np.array([[r[f"cam_{k}"] for k in FEATURES] for r in ph], dtype=float)
            phantoms = [{k: r[k] for k in r if not k.startswith(("fem_", "cam_"))} for r in ph]
            names = [str(r["name"]) for r in phantoms]
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise UserError("calibration", f"{p}: malformed calibration file ({type(exc).__name__}: {exc})") from None
        _check_loaded(p, fits, fem, cam, d)
        return cls(
            fits,
            names,
            phantoms,
            fem,
            cam,
            d.get("feature_settings", {}),
            d.get("sensor"),
            bool(d.get("synthetic", False)),
            d.get("meta", {}),
            d.get("deflection"),
            d.get("discrepancy"),
        )

    def report(self) -> str:
        lines = [
            f"calibration ({'SYNTHETIC camera' if self.synthetic else 'camera images'}), "
            f"{len(self.names)} phantoms: O_FEM = a * O_cam + b"
        ]
        for k in FEATURES:
            f = self.fits[k]
            lines.append(
                f"  {k}: a = {f.slope:.6g}  b = {f.intercept:.6g} {FEM_UNITS[k]}  R^2 = {f.r2:.5f}  "
                f"rmse = {f.rmse:.3g} {FEM_UNITS[k]}"
            )
        lines.append("  residuals (FEM units):")
        for i, n in enumerate(self.names):
            lines.append("    " + f"{n:14s}" + "  ".join(f"{k}={self.fits[k].residuals[i]:+.3g}" for k in FEATURES))
        if self.deflection:
            rel = self.deflection["rel_rms"]
            lines.append(
                f"  difference images from frames (inverse response): scale {self.deflection['scale']:.4f}, "
                f"relative rms vs FEM {100 * min(rel):.2g}-{100 * max(rel):.2g} % over the phantoms"
            )
            if self.deflection.get("press_sd") is not None:
                lines.append(
                    "  flat field's press uncertainty (sd, µm by distance from the axis): "
                    + press_bands(np.asarray(self.deflection["press_sd"], float), float(self.deflection["pixel"]))
                )
        if self.discrepancy:
            lines.extend(discrepancy_report(self.discrepancy))
        return "\n".join(lines)

    def model_form(self):
        """``(Discrepancy, level, pixel mm)`` of the model-form term learnt from the phantoms
        (:func:`learn_discrepancy`), or None."""
        if not self.discrepancy:
            return None
        from elastimap.identify.discrepancy import Discrepancy

        z = self.discrepancy
        return Discrepancy.from_dict(z["term"]), str(z["level"]), float(z["pixel"])

    def reference_image(self) -> tuple[np.ndarray, float]:
        """The FEM reference press (mm) and its pixel side (mm), for :mod:`elastimap.camera.deflection`."""
        if not self.deflection:
            raise UserError(
                "calibration",
                "this calibration has no deflection calibration (made by an older "
                "version or without FEM solves): recalibrate to use camera frames "
                "with an image model or --refine",
            )
        return np.asarray(self.deflection["reference"], float), float(self.deflection["pixel"])


def _check_loaded(p: str, fits: dict, fem: np.ndarray, cam: np.ndarray, d: dict) -> None:
    """What a calibration file must hold beyond its keys: finite, non-zero slopes, finite
    intercepts and phantom features, and settings of the right types (else the fault showed up
    later, blamed on the features given to ``infer``)."""

    def bad(what: str):
        return UserError("calibration", f"{p}: damaged calibration file ({what})")

    for k, f in fits.items():
        for name in ("slope", "intercept"):
            v = getattr(f, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise bad(f"{k} {name} is {v!r}, not a finite number")
        if f.slope == 0:
            raise bad(f"{k} slope is 0")
    if fem.ndim != 2 or fem.shape != cam.shape or len(fem) < 2:
        raise bad(f"phantom feature tables of shapes {fem.shape} and {cam.shape}")
    if not (np.all(np.isfinite(fem)) and np.all(np.isfinite(cam))):
        raise bad("non-finite phantom features")
    if not isinstance(d.get("feature_settings", {}), dict):
        raise bad("feature_settings is not a JSON object")
    if d.get("sensor") is not None and not isinstance(d["sensor"], dict):
        raise bad("sensor is not a JSON object")
    if d.get("deflection") is not None and not isinstance(d["deflection"], dict):
        raise bad("deflection is not a JSON object")
    z = d.get("discrepancy")
    if z is not None:
        if not isinstance(z, dict) or not {"term", "level", "pixel"} <= set(z):
            raise bad("discrepancy is not a model-form record (term, level, pixel)")
        from elastimap.identify.discrepancy import Discrepancy

        try:
            Discrepancy.from_dict(z["term"])
        except UserError as exc:
            raise bad(exc.message) from None


def deflection_calibration(results, pairs, sensor=None) -> dict:
    """The deflection calibration from the phantoms' FEM results and their (lesion, background)
    frame stacks: the reference press (mean of the phantoms' ``image_raw - image``; they share
    tissue and press), the factor ``scale`` with FEM image ≈ scale x recovered image over all nine,
    and the per-phantom relative rms residual after it."""
    from .deflection import difference_image, fit_scale
    from .optics import SensorModel, background_deflection

    sensor = sensor or SensorModel()
    if len(results) != len(pairs) or not results:
        raise UserError("calibration", "need the FEM result and the frames of every phantom")
    refs = np.array([background_deflection(r.image_raw, r.image) for r in results])
    ref = refs.mean(axis=0)
    spread = float(np.max(np.abs(refs - ref)) / max(np.max(np.abs(ref)), 1e-300))
    # the nine share one press; remeshing alone moves the FEM's reference by a few % of its maximum
    # (4.5 % on the tiny mesh, at the probe's edge peaks), a different tissue or press by far more
    if spread > 0.2:
        raise UserError(
            "calibration",
            f"the phantoms' reference presses differ by {100 * spread:.2g} % "
            "(different tissue or press): one deflection calibration needs one press",
        )
    pixel = float(results[0].pixel)
    rec = [difference_image(F, B, sensor, ref, pixel).image for F, B in pairs]
    k, rel = fit_scale(rec, [np.asarray(r.image, float) for r in results])
    return {
        "model": "FEM difference image = scale x inverse-response image (elastimap.camera.deflection)",
        "reference": ref.tolist(),
        "pixel": pixel,
        "shape": list(ref.shape),
        "scale": k,
        "rel_rms": rel,
        "reference_spread": spread,
    }


def press_uncertainty(theta, reference_result, mesh: str, delta: float | None = None, sensor=None) -> np.ndarray:
    """The flat field's press sd ``σ_s`` (mm, FEM grid; :func:`elastimap.camera.deflection.press_spread`):
    how far elastimap's own other models of the background press lie from the calibration's -- the same
    phantom (``theta``: d, h, E) solved with the unilateral **contact** interface at ``mesh`` and tied at
    the **neighbouring level** (finer, else coarser), against ``reference_result`` (its tied solve at
    ``mesh``).  A stated prior of the press's model-form error, from elastimap's own evidence, not a
    measurement of the world's press (docs/camera.md, 'The flat field's press uncertainty').  Two
    solves."""
    from elastimap.sensor import Sensor
    from elastimap.solver import solve  # noqa: PLC0415 - keeps DOLFINx out of import time
    from elastimap.solver.params import Discretisation, Inclusion, coarser, finer, from_sensor

    from .deflection import press_spread
    from .optics import background_deflection

    sensor = sensor or Sensor()
    if delta is not None:
        sensor = sensor.replace(loading=dataclasses.replace(sensor.loading, delta=delta))
    d, h, E = (float(v) for v in theta)
    inc = Inclusion(d=d, h=h, E=E, nu=sensor.tissue.nu)
    alts = []
    for disc in (Discretisation(mesh=mesh, interface="contact"), Discretisation(mesh=finer(mesh) or coarser(mesh))):
        r = solve(from_sensor(sensor, inc, disc))
        alts.append(background_deflection(r.image_raw, r.image))
    ref = background_deflection(reference_result.image_raw, reference_result.image)
    return press_spread(ref, alts, float(reference_result.pixel))


def recovered_images(pairs, deflection: dict, sensor=None) -> list:
    """The phantoms' FEM-equivalent difference images from their (lesion, background) frame stacks
    through the deflection calibration (:class:`elastimap.camera.deflection.DeflectionImage` each)."""
    from .deflection import difference_image
    from .optics import SensorModel

    sensor = sensor or SensorModel()
    ref = np.asarray(deflection["reference"], float)
    return [
        difference_image(F, B, sensor, ref, float(deflection["pixel"]), scale=float(deflection["scale"]))
        for F, B in pairs
    ]


def learn_discrepancy(
    phantoms, pairs, deflection: dict, level: str, sensor=None, forward=None, description=None
) -> dict:
    """The model-form error of the lab's phantoms (:func:`elastimap.identify.discrepancy.calibrate`):
    each phantom's difference image recovered from its frames (:func:`recovered_images`) minus the
    fit's forward image at its known (d, h, E) on mesh ``level`` (the level ``infer --refine`` stands
    for: its morphed map, :func:`elastimap.identify.forward_maps.fit_maps`; ``forward`` replaces it),
    with the leave-one-phantom-out check.  Phantoms on another slab (``tissue_E``, ``tissue_thickness``
    columns) than the fit's are left out.  Returns the calibration file's ``discrepancy`` record:
    ``term`` (:meth:`~elastimap.identify.discrepancy.Discrepancy.to_dict`), ``level``, ``pixel`` (mm),
    ``names`` (the phantoms used), ``loo`` (per phantom: held-out χ² per pixel, modes' z, covered) and
    ``beyond`` (terms beyond 3 x their prior scale: an effect, not a model-form difference).
    ``sensor`` is the camera (:class:`~elastimap.camera.optics.SensorModel`), ``description`` the lab's
    sensor (:class:`elastimap.sensor.Sensor`; None: the paper's) whose mechanics the map presses with."""
    from elastimap.identify import discrepancy as dy

    if forward is None:
        from elastimap.identify.forward_maps import BELOW_LEVELS, sensor_template, shared_map

        forward = shared_map(level, below=level in BELOW_LEVELS, template=sensor_template(description))
    own = [i for i, (_, r) in enumerate(phantoms.iterrows()) if _default_slab(r)]
    if len(own) < 2:
        raise UserError("phantoms", "learning the model-form error needs at least 2 phantoms on the default slab")
    rec = recovered_images([pairs[i] for i in own], deflection, sensor)
    rows = [phantoms.iloc[i] for i in own]
    thetas = [(float(r["d"]), float(r["h"]), float(r["E"])) for r in rows]
    disc, loo = dy.calibrate(
        [r.image for r in rec],
        [r.sigma for r in rec],
        thetas,
        forward,
        float(deflection["pixel"]),
        source=f"{len(own)} calibration phantoms (camera calibrate)",
    )
    return {
        "model": "I = m(theta) + Phi beta + remainder + noise (elastimap.identify.discrepancy)",
        "term": disc.to_dict(),
        "level": level,
        "pixel": float(deflection["pixel"]),
        "names": [str(r["name"]) for r in rows],
        "loo": [
            {"name": str(r["name"]), "chi2_px": h.chi2_px, "z": h.z.tolist(), "covered": h.covered.tolist()}
            for r, h in zip(rows, loo)
        ],
        "beyond": disc.beyond(),
    }


def press_bands(sd: np.ndarray, pixel: float, edges=(0, 3, 6, 9, 12, 18)) -> str:
    """``σ_s`` (mm on a grid of ``pixel`` mm) as its rms in bands of the distance from the axis (µm), and its maximum."""
    from .deflection import radius_grid

    r = radius_grid(sd.shape, pixel)
    parts = [
        f"{a:g}-{b:g} mm {1e3 * np.sqrt(np.mean(sd[(r >= a) & (r < b)] ** 2)):.2g}"
        for a, b in zip(edges[:-1], edges[1:], strict=True)
    ]
    return ", ".join(parts) + f"; max {1e3 * sd.max():.2g}"


def press_term(deflection: dict | None, sensor=None):
    """The fit's press-uncertainty term of a deflection record (:class:`elastimap.camera.deflection.PressTerm`;
    None where the record holds no ``press_sd``: the fit is then as before)."""
    from .deflection import PressTerm
    from .optics import SensorModel

    return PressTerm.of(deflection, sensor or SensorModel())


def refine_levels(level: str) -> tuple[str, str | None]:
    """``(--mesh, --refine-correct)`` of the ``infer --refine`` fit that stands for mesh ``level``: `coarse`
    corrected by `fine` for `fine` (the default fit), else ``level`` alone."""
    from elastimap.identify.forward_maps import DEFAULT_CORRECT

    for mesh, correct in DEFAULT_CORRECT.items():
        if correct == level:
            return mesh, correct
    return level, None


def loo_fits(record: dict, phantoms, pairs, deflection: dict, sensor=None, progress=None, description=None) -> dict:
    """Leave-one-phantom-out check of the fit that carries the model-form term: each phantom of
    ``record`` (:func:`learn_discrepancy`) fitted from its frames as ``infer --refine`` does, with the
    discrepancy learnt from the other phantoms, from a start that knows nothing of it (the other
    phantoms' mean d and h, their geometric-mean E; the fit's E scan searches from there).  Returns
    ``{"n", "covered" (d, h, E), "reported" (d, h, E), "rows"}``; a parameter counts as reported when
    the fit calls it identifiable (relative sd ≤ 10 %) and no parameter is on the design box's edge (as
    ``infer`` prints it)."""
    from elastimap.identify import discrepancy as dy
    from elastimap.identify.fit import fit_on_maps
    from elastimap.identify.forward_maps import fit_maps

    names = record["names"]
    idx = [list(phantoms["name"].astype(str)).index(n) for n in names]
    rec = recovered_images([pairs[i] for i in idx], deflection, sensor)
    thetas = np.array([[float(phantoms.iloc[i][k]) for k in ("d", "h", "E")] for i in idx])
    mesh, correct = refine_levels(record["level"])
    maps = fit_maps(mesh, correct, sensor=description)
    f = maps.forward_fine or maps.forward
    pixel = float(record["pixel"])
    press = press_term(deflection, sensor)
    models, depths = dy.forward_images(f, thetas)
    which = tuple(record["term"]["modes"])
    if dy.DEPTH not in which:
        depths = None
    rows, n = [], len(idx)
    for i in range(n):
        rest = [j for j in range(n) if j != i]
        disc = dy.learn(
            [rec[j].image - models[j].reshape(rec[j].image.shape) for j in rest],
            [models[j].reshape(rec[j].image.shape) for j in rest],
            [rec[j].sigma for j in rest],
            pixel,
            which=which,
            depths=None if depths is None else [depths[j] for j in rest],
        )
        start = np.array(
            [thetas[rest, 0].mean(), thetas[rest, 1].mean(), float(np.exp(np.log(thetas[rest, 2]).mean()))]
        )
        r = fit_on_maps(rec[i].image, rec[i].sigma, start, maps, discrepancy=disc, pixel=pixel, shared=press)
        cov = [bool(r.lo[j] <= thetas[i, j] <= r.hi[j]) for j in range(3)]
        rep = [bool(r.relstd[j] <= 0.10 and not r.at_bound) for j in range(3)]  # as infer prints them
        rows.append(
            {
                "name": names[i],
                "truth": thetas[i].tolist(),
                "theta": r.theta.tolist(),
                "lo": r.lo.tolist(),
                "hi": r.hi.tolist(),
                "covered": cov,
                "reported": rep,
                "at_bound": r.at_bound,
                "seconds": r.seconds,
            }
        )
        if progress:
            progress(names[i], rows[-1])
    return {
        "n": n,
        "covered": [int(sum(r["covered"][j] for r in rows)) for j in range(3)],
        "reported": [int(sum(r["reported"][j] for r in rows)) for j in range(3)],
        "rows": rows,
    }


def _default_slab(r) -> bool:
    """Whether a phantom row lies on the default slab (no ``tissue_E``/``tissue_thickness`` of its own)."""
    from elastimap.solver.params import Tissue

    t = Tissue()
    for col, v in (("tissue_E", t.E), ("tissue_thickness", t.thickness)):
        if col in r and np.isfinite(r[col]) and abs(float(r[col]) - v) > 1e-9:
            return False
    return True


def discrepancy_report(z: dict) -> list[str]:
    """Lines of the calibration report for a ``discrepancy`` record (:func:`learn_discrepancy`)."""
    t = z["term"]
    lines = [
        f"  model-form error (level {z['level']}, {t['n_phantoms']} phantoms): "
        + ", ".join(
            f"{m} mean {100 * mu:+.2g} % sd {100 * s:.2g} %" for m, mu, s in zip(t["modes"], t["mean"], t["tau"])
        )
        + f", remainder {100 * t['rho']:.2g} % (corr. {t['ell']:g} mm)"
    ]
    if z.get("loo"):
        cov = np.array([r["covered"] for r in z["loo"]], bool)
        chi = [r["chi2_px"] for r in z["loo"]]
        lines.append(
            "    leave-one-phantom-out: modes covered "
            + ", ".join(f"{m} {int(c.sum())}/{len(c)}" for m, c in zip(t["modes"], cov.T))
            + f", held-out chi2/px {min(chi):.2f}-{max(chi):.2f}"
        )
    if z.get("fits"):
        f = z["fits"]
        lines.append(
            f"    leave-one-phantom-out fits (--report-loo): 95 % intervals hold d {f['covered'][0]}/{f['n']}, "
            f"h {f['covered'][1]}/{f['n']}, E {f['covered'][2]}/{f['n']}; printed as a number d/h/E "
            f"{f['reported'][0]}/{f['reported'][1]}/{f['reported'][2]}"
        )
    if z.get("beyond"):
        lines.append(
            f"    WARNING: {', '.join(z['beyond'])} beyond 3 x the model-form prior: the phantoms differ from "
            "elastimap by more than a model-form difference (run gap diagnose; docs/model-form.md)"
        )
    return lines


def fit_calibration(
    phantoms,
    fem: np.ndarray,
    cam: np.ndarray,
    feature_settings: dict,
    sensor: dict | None = None,
    synthetic: bool = True,
    meta: dict | None = None,
    deflection: dict | None = None,
    discrepancy: dict | None = None,
) -> Calibration:
    fem = np.asarray(fem, dtype=float)
    cam = np.asarray(cam, dtype=float)
    n = len(phantoms)
    if fem.shape != (n, 3) or cam.shape != (n, 3):
        raise UserError(
            "calibration", f"need (n, 3) FEM and camera features for the {n} phantoms (got {fem.shape} and {cam.shape})"
        )
    fits = {k: fit_line(cam[:, j], fem[:, j], k) for j, k in enumerate(FEATURES)}
    recs = [
        {"name": str(r["name"]), "d": float(r["d"]), "h": float(r["h"]), "E": float(r["E"])}
        for _, r in phantoms.iterrows()
    ]
    m = {"created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")}
    try:
        from elastimap.provenance import stamp

        m.update(stamp())
    except Exception:
        pass
    m.update(meta or {})
    return Calibration(
        fits, [r["name"] for r in recs], recs, fem, cam, feature_settings, sensor, synthetic, m, deflection, discrepancy
    )


def plot_calibration(cal: Calibration, path: str | os.PathLike) -> None:
    """PNG of the three fits (camera feature vs FEM feature, with the fitted line)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    cam_units = {"O1": "FS", "O2": "FS mm²", "O3": "mm²"}
    fem_units = {k: u.replace("^2", "²") for k, u in FEM_UNITS.items()}
    for j, (k, ax) in enumerate(zip(FEATURES, axes)):
        f = cal.fits[k]
        x, y = cal.cam[:, j], cal.fem[:, j]
        ax.scatter(x, y, c="C0", zorder=3)
        for xi, yi, n in zip(x, y, cal.names):
            ax.annotate(n, (xi, yi), fontsize=7, xytext=(3, 3), textcoords="offset points")
        xs = np.linspace(x.min(), x.max(), 50)
        ax.plot(xs, f.slope * xs + f.intercept, "C1-", label=f"a={f.slope:.4g}, b={f.intercept:.3g}\nR²={f.r2:.4f}")
        ax.set_xlabel(f"camera {k} ({cam_units[k]})")
        ax.set_ylabel(f"FEM {k} ({fem_units[k]})")
        ax.legend(fontsize=8, loc="upper left")
        ax.grid(alpha=0.3)
    title = "FEM ↔ camera calibration, nine phantoms"
    if cal.synthetic:
        title = "SYNTHETIC camera — " + title
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------- simulation
def default_fem(mesh: str = "coarse", delta: float = 3.0, sensor=None):
    """A function (d, h, E, tissue_E, thickness) -> SolveResult using the DOLFINx solver (imported lazily),
    on the sensor ``sensor`` (:class:`elastimap.sensor.Sensor`; None: the paper's) with plate travel
    ``delta`` (None: the sensor's) and the phantom's slab modulus and thickness (default: the sensor's)."""
    from elastimap.sensor import Sensor

    sensor = sensor or Sensor()

    def fem(d: float, h: float, E: float, tissue_E: float | None = None, thickness: float | None = None):
        from elastimap.solver import solve  # noqa: PLC0415 - keeps DOLFINx out of import time
        from elastimap.solver.params import Discretisation, Inclusion, from_sensor

        t = sensor.tissue
        slab = dataclasses.replace(t, E=t.E if tissue_E is None else tissue_E, thickness=thickness or t.thickness)
        load = sensor.loading if delta is None else dataclasses.replace(sensor.loading, delta=delta)
        s = sensor.replace(tissue=slab, loading=load)
        return solve(from_sensor(s, Inclusion(d=d, h=h, E=E, nu=t.nu), Discretisation(mesh=mesh)))

    return fem


def simulate_phantoms(
    phantoms,
    fem_fn,
    sensor=None,
    settings=None,
    frames: int = 30,
    seed: int = 0,
    write_dir: str | os.PathLike | None = None,
    fmt: str = "png",
    progress=None,
    frames_out: list | None = None,
):
    """FEM features and SYNTHETIC camera features of each phantom.

    ``fem_fn(d, h, E, tissue_E, thickness)`` returns an object with ``image``,
    ``image_raw``, ``pixel``, ``O1``, ``O2``, ``O3`` (a SolveResult).  With
    ``write_dir`` the frames are also written there as images; ``frames_out`` (a list) receives
    each phantom's (lesion, background) frame stacks.
    Returns (fem (n,3), cam (n,3), results list).
    """
    from .features import FeatureSettings, camera_features
    from .frames import write_frames
    from .optics import SensorModel, render_pair

    sensor = (sensor or SensorModel()).validate()
    settings = settings or FeatureSettings()
    rng = np.random.default_rng(seed)
    fem, cam, results = [], [], []
    for _, r in phantoms.iterrows():
        kw = {}
        if "tissue_E" in r and np.isfinite(r["tissue_E"]):
            kw["tissue_E"] = float(r["tissue_E"])
        if "tissue_thickness" in r and np.isfinite(r["tissue_thickness"]):
            kw["thickness"] = float(r["tissue_thickness"])
        res = fem_fn(float(r["d"]), float(r["h"]), float(r["E"]), **kw)
        F, B = render_pair(sensor, res.image_raw, res.image, res.pixel, frames, rng)
        if frames_out is not None:
            frames_out.append((F, B))
        if write_dir is not None:
            meta = {
                "phantom": str(r["name"]),
                "d": float(r["d"]),
                "h": float(r["h"]),
                "E": float(r["E"]),
                "sensor": sensor.to_dict(),
            }
            write_frames(F, write_dir, f"synthetic_{r['name']}", fmt, dict(meta, frame="lesion"))
            write_frames(B, write_dir, f"synthetic_{r['name']}_background", fmt, dict(meta, frame="background"))
        cf = camera_features(F, B, sensor.full_scale, sensor.window, sensor.pixel_mm, settings)
        fem.append([res.O1, res.O2, res.O3])
        cam.append(cf.values)
        results.append(res)
        if progress:
            progress(str(r["name"]), fem[-1], cam[-1])
    return np.array(fem), np.array(cam), results


def camera_features_from_csv(
    path: str | os.PathLike,
    phantoms,
    sensor=None,
    settings=None,
    frames_out: list | None = None,
    allow_outside: bool = False,
):
    """Camera features of the phantoms from the user's images.

    The CSV has columns ``name`` (matching the phantom spec), ``images`` and
    ``background`` (each a ';'-separated list of files or glob patterns,
    relative to the CSV's folder and inside it unless ``allow_outside``).  Returns (n, 3) in the phantom order; ``frames_out`` (a list)
    receives each phantom's (lesion, background) frame stacks (DN).
    """
    from elastimap.tables import read_csv

    from .features import features_from_files
    from .frames import expand

    p = Path(path)
    df = read_csv(p, "camera-csv", required=("name", "images", "background"))
    df["name"] = df["name"].astype(str)
    rows = {r["name"]: r for _, r in df.iterrows()}

    def files(r, col: str) -> list[str]:
        try:
            found = expand(str(r[col]), p.parent, param="camera-csv", allow_outside=allow_outside)
            for f in found:
                if not os.path.isfile(f):
                    raise UserError("camera-csv", f"{f}: no such file")
            return found
        except UserError as exc:
            raise UserError("camera-csv", f"{p}, {r['name']!r}, column {col}: {exc.message}") from None

    listed = []
    for name in phantoms["name"]:  # every phantom's files first: a bad name costs nothing
        if name not in rows:
            raise UserError("camera-csv", f"{p}: no images for phantom {name!r}")
        listed.append((files(rows[name], "images"), files(rows[name], "background")))
    out = []
    for imgs, bg in listed:
        out.append(features_from_files(imgs, bg, sensor, settings, ("camera-csv", "camera-csv")).values)
        if frames_out is not None:
            from .frames import read_stack
            from .optics import SensorModel

            m = sensor or SensorModel()
            frames_out.append(
                (
                    read_stack(imgs, m.shape, m.window, "camera-csv", bits=m.bits)[0],
                    read_stack(bg, m.shape, m.window, "camera-csv", bits=m.bits)[0],
                )
            )
    return np.array(out)


def fem_features_from_csv(path: str | os.PathLike, phantoms) -> np.ndarray:
    """FEM features of the phantoms from a CSV (name, O1, O2, O3), e.g. from the sweep's phantom rows."""
    from elastimap.tables import numbers, read_csv

    p = Path(path)
    if not p.exists():
        raise UserError("fem-features", f"{p}: no such file")
    if p.is_dir() or p.suffix == ".parquet":
        # a sample dataset (a sweep's folder or one of its files): the one reader, with its schema check
        from elastimap.dataset.io import read_samples

        try:
            df = read_samples(p, columns=["tag", *FEATURES])
        except UserError as exc:
            raise UserError("fem-features", exc.message) from None
        df = df[is_phantom(df["tag"])].copy()
        df["name"] = [phantom_name(t) for t in df["tag"]]
    else:
        df = read_csv(p, "fem-features", required=("name", *FEATURES))
    for c in ("name", *FEATURES):
        if c not in df.columns:
            raise UserError("fem-features", f"{p}: missing column {c!r}")
    df["name"] = df["name"].astype(str)
    df = df[df["name"].isin(set(phantoms["name"]))].reset_index(drop=True)
    for k in FEATURES:
        df[k] = numbers(df, k, "fem-features", str(p))
    rows = {r["name"]: r for _, r in df.iterrows()}
    out = []
    for name in phantoms["name"]:
        if name not in rows:
            raise UserError("fem-features", f"{p}: no FEM features for phantom {name!r}")
        out.append([float(rows[name][k]) for k in FEATURES])
    return np.array(out)
