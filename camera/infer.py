"""Inference: camera features or frames -> calibrated FEM features -> (d, h, E).

Python API (imports no solver and no DOLFINx)::

    from elastimap.camera.infer import load_model, estimate, estimate_images
    from elastimap.camera.calibration import Calibration
    cal = Calibration.load("cal.json")
    model = load_model("models/run1")               # any elastimap.training.model.InverseModel
    est = estimate([[O1, O2, O3]], cal, model)      # camera features (see elastimap.camera.features)
    est[0].d, est[0].d_sd, est[0].flags

Uncertainty: the ensemble's members (the networks of the training repeats)
each predict (d, h, E); the estimate is their mean and the uncertainty their
standard deviation (``*_sd``), plus the 10-90 % member range.  Inputs are
never silently extrapolated: every estimate carries ``flags``:

* ``outside_calibration:Ok`` - camera feature k outside the range spanned by
  the nine calibration phantoms (the linear map is extrapolated);
* ``outside_training:<input>`` - an input of the model outside its training range
  (:meth:`elastimap.training.model.InverseModel.outside_training`: the calibrated FEM feature
  ``Ok`` for a feature model, ``image`` for an image model);
* ``no_signal`` - O1 at or below zero, or (from frames) no pixel of the difference image
  :data:`DETECT_SIGMA` standard errors above zero: no inclusion visible, nothing is reportable,
  and the interval ``[q_lo, q_hi]`` is the whole design box (:func:`design_box_interval`): the
  model's number for an image it cannot see is an extrapolation, and its interval there held the
  centre depth of 1 of the 13 such lesions of the SYNTHETIC benchmark's seeds 2027–2038
  (docs/camera.md, 'Inference');
* ``non_identifiable:q`` - at the estimate, the Cramér–Rao bound of the
  identifiability map (:mod:`elastimap.identify.idmap`; by default the one shipped,
  measured on the default 512-sample sweep) says ``q`` cannot be determined
  within 10 % from this measurement (three features for the feature MLP,
  the whole image for an image model).  Such a ``q`` is reported as its
  interval ``[q_lo, q_hi]`` (at least the bound's 95 % interval, clipped to
  the training range), never as a confident number;
* ``outside_identifiability_map`` - the estimate lies outside the map's box;
* ``impossible:q`` - the estimate of ``q`` is not a possible inclusion (d, h or E at or below
  zero, or a centre depth h outside ``elastimap.solver.params.depth_range(d)``: the inclusion
  would cross the surface or the base);
* ``outside_interval:q`` - the estimate of ``q`` lies outside its own interval ``[lo, hi]``
  (e.g. below the training range to which the interval is clipped);
* ``saturated`` - camera pixels beyond the response's saturation (frames of an image model);
* ``at_design_edge:q`` - the physics fit (``--refine``) ended with ``q`` on the design box's edge
  (d, E at the box's limits or within 1 % of them, h at the admissible depth range's;
  :func:`elastimap.identify.fit.on_edge`): the likelihood's maximum is not
  inside the box, so the estimate is the box's edge and the Gauss–Newton interval, which assumes an
  interior maximum, holds for none of the coupled parameters.  Then no quantity is reportable.

A ``q`` that is non-identifiable, impossible or outside its interval is not *reportable*
(``q_reportable`` false), nor is any after a fit that ended on the design box's edge: the command
line prints its interval (or nothing), never the number.

Every estimate carries ``lo``/``hi``: the bound's approximate 95 % interval
widened to the ensemble's 10-90 % range (a bound: real errors can be larger).

Image models (``elastimap study image_model --save-model DIR``) take a FEM
difference image (:func:`estimate_fem_images`) or camera frames (:func:`estimate_images`),
which become the FEM-equivalent difference image and its per-pixel standard error by the
inverse sensor response (:func:`difference_of_frames`, :mod:`elastimap.camera.deflection`).
:func:`refine_estimates` fits the FEM to that image, weighting each pixel by its own noise.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from elastimap.dataset.schema import FEATURES, TARGETS, UNITS
from elastimap.errors import UserError

from .calibration import Calibration

DETECT_SIGMA = 5.0  # from frames: the inclusion is visible when some pixel is this many standard errors up
TARGET_UNITS = {k: UNITS[k] for k in TARGETS}


@dataclass
class Estimate:
    id: str
    cam: np.ndarray  # camera features (3,)
    fem: np.ndarray  # calibrated FEM features (3,)
    mean: np.ndarray  # (d, h, E) ensemble mean
    sd: np.ndarray  # ensemble standard deviation
    p10: np.ndarray
    p90: np.ndarray
    n_members: int
    flags: list[str] = field(default_factory=list)
    lo: np.ndarray | None = None  # interval (see the module docstring)
    hi: np.ndarray | None = None
    #: relative std of d, h (std of ln E): the map's Cramér–Rao bound, or the fit's (refine_estimates)
    crb: np.ndarray | None = None
    crb_set: str = ""  # the identifiability map's measurement set ``crb`` is from
    input: str = "features"  # features | image | frames | ... +fem_refined
    image: np.ndarray | None = None  # the difference image estimated from (mm, FEM grid; image models)
    sigma: np.ndarray | None = None  # its per-pixel standard error (mm; from frames), else None
    fit: object | None = None  # elastimap.identify.fit.FitResult after refine_estimates

    d = property(lambda s: float(s.mean[0]))
    h = property(lambda s: float(s.mean[1]))
    E = property(lambda s: float(s.mean[2]))
    d_sd = property(lambda s: float(s.sd[0]))
    h_sd = property(lambda s: float(s.sd[1]))
    E_sd = property(lambda s: float(s.sd[2]))

    @property
    def ok(self) -> bool:
        return not self.flags

    def reportable(self, q: str) -> bool:
        """``q`` may be printed as a number: a visible inclusion, identifiable, possible, inside its
        own interval, and not from a fit that ended on the design box's edge."""
        if "no_signal" in self.flags or any(f.startswith("at_design_edge:") for f in self.flags):
            return False
        return not any(f"{k}:{q}" in self.flags for k in ("non_identifiable", "impossible", "outside_interval"))

    def to_dict(self) -> dict:
        out: dict = {"id": self.id}
        for j, k in enumerate(TARGETS):
            out[k] = float(self.mean[j])
            out[f"{k}_sd"] = float(self.sd[j])
            out[f"{k}_p10"] = float(self.p10[j])
            out[f"{k}_p90"] = float(self.p90[j])
            out[f"{k}_lo"] = float(self.lo[j]) if self.lo is not None else math.nan
            out[f"{k}_hi"] = float(self.hi[j]) if self.hi is not None else math.nan
            out[f"{k}_crb_rel"] = float(self.crb[j]) if self.crb is not None else math.nan
            out[f"{k}_identifiable"] = f"non_identifiable:{k}" not in self.flags
            out[f"{k}_reportable"] = self.reportable(k)
        for j, k in enumerate(FEATURES):
            out[f"cam_{k}"] = float(self.cam[j])
        for j, k in enumerate(FEATURES):
            out[f"fem_{k}"] = float(self.fem[j])
        if self.image is not None:
            j = int(np.argmax(self.image))
            out["image_peak_mm"] = float(self.image.ravel()[j])
            out["image_peak_sigma_mm"] = float(self.sigma.ravel()[j]) if self.sigma is not None else math.nan
        if self.fit is not None:
            out["fit_chi2_red"] = float(self.fit.chi2_red)
            out["fit_model_error"] = float(self.fit.model_error)
            out["fit_solves"] = int(self.fit.n_solves + self.fit.n_alt)
            out["fit_seconds"] = float(self.fit.seconds)
            out["fit_converged"] = bool(self.fit.converged)
            out["fit_moving"] = ";".join(self.fit.moving)
            out["fit_model_form"] = bool(getattr(self.fit, "model_form", False))  # carried the lab's term
        out["crb_set"] = self.crb_set
        out["input"] = self.input
        out["n_members"] = self.n_members
        out["flags"] = ";".join(self.flags)
        out["ok"] = self.ok
        return out


def load_identifiability(identifiability="default"):
    """``"default"`` (the shipped map), a path, an :class:`elastimap.identify.idmap.IdentifiabilityMap`, or None."""
    if identifiability is None:
        return None
    from elastimap.identify.idmap import IdentifiabilityMap

    if isinstance(identifiability, IdentifiabilityMap):
        return identifiability
    return IdentifiabilityMap.load(None if identifiability == "default" else identifiability)


def _plausibility(ests: list[Estimate]) -> list[Estimate]:
    """Add ``impossible:q`` and ``outside_interval:q`` (see the module docstring)."""
    from elastimap.solver.params import depth_range  # pure python, no DOLFINx

    for e in ests:
        e.flags = [f for f in e.flags if not f.startswith(("impossible:", "outside_interval:"))]
        d, h, E = (float(v) for v in e.mean)
        bad = {"d": not d > 0, "h": not h > 0, "E": not E > 0}
        if d > 0 and h > 0:
            try:
                lo, hi = depth_range(d)
                bad["h"] = bad["h"] or not lo <= h <= hi
            except Exception:  # no admissible depth at all for this d
                bad["d"] = bad["h"] = True
        for j, q in enumerate(TARGETS):
            if bad[q]:
                e.flags.append(f"impossible:{q}")
            elif (
                e.lo is not None
                and np.isfinite(e.lo[j])
                and np.isfinite(e.hi[j])
                and not e.lo[j] <= e.mean[j] <= e.hi[j]
            ):
                e.flags.append(f"outside_interval:{q}")
    return ests


def design_box_interval() -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) over (d mm, h mm, E kPa) of the whole design box: d and E over
    :data:`~elastimap.solver.params.DESIGN_BOX`, h over every admissible centre depth of those d
    (``depth_range`` of the smallest d, the default slab): what a ``no_signal`` lesion may be."""
    from elastimap.solver.params import DESIGN_BOX, depth_range  # pure python, no DOLFINx

    (d0, d1), (E0, E1) = DESIGN_BOX["d"], DESIGN_BOX["E"]
    h0, h1 = depth_range(d0)
    return np.array([d0, h0, E0]), np.array([d1, h1, E1])


def _no_signal_box(ests: list[Estimate]) -> list[Estimate]:
    """A ``no_signal`` estimate's interval is the design box (see the module docstring)."""
    lo, hi = design_box_interval()
    for e in ests:
        if "no_signal" in e.flags:
            e.lo, e.hi = lo.copy(), hi.copy()
    return ests


def _assess(ests: list[Estimate], model, idmap, mset: str, threshold: float, scale: float = 1.0) -> list[Estimate]:
    """Intervals, ``non_identifiable`` and plausibility flags from the identifiability map's
    measurement set ``mset`` (the model's ``input_kind``, or ``FRAMES``)."""
    if idmap is None:
        return _plausibility(_no_signal_box(ests))
    mean = np.array([e.mean for e in ests])
    a = idmap.assess(
        mean,
        mset,
        threshold,
        p10=np.array([e.p10 for e in ests]),
        p90=np.array([e.p90 for e in ests]),
        target_range=model.target_range,
        scale=scale,
    )
    for i, e in enumerate(ests):
        e.lo, e.hi, e.crb, e.crb_set = a.lo[i], a.hi[i], a.r[i], mset
        e.flags.extend(a.flags[i])
    return _plausibility(_no_signal_box(ests))


def _members(Y: np.ndarray, n: int):
    Y = np.asarray(Y, dtype=float)
    if Y.ndim == 2:
        Y = Y[None]
    if Y.shape[1:] != (n, 3):
        raise RuntimeError(f"model.predict returned shape {Y.shape}, expected (members, {n}, 3)")
    mean = Y.mean(axis=0)
    sd = Y.std(axis=0, ddof=1) if Y.shape[0] > 1 else np.full((n, 3), math.nan)
    return Y, mean, sd, np.percentile(Y, 10, axis=0), np.percentile(Y, 90, axis=0)


#: The refusal when a model is given the other kind of input, by the input it was given.
_WRONG_INPUT = {
    "features": "this is an image model: give an image (--fem-image or camera frames), not features",
    "image": "a feature model takes features or camera frames, not a FEM image; use an image model "
    "(elastimap study image_model --save-model DIR)",
}


def _check_input(model, given: str) -> None:
    """Refuse ``model`` (an :class:`elastimap.training.model.InverseModel`) unless it takes ``given``."""
    if getattr(model, "input_kind", None) != given:
        raise UserError("model", _WRONG_INPUT[given])


def fem_image_stack(arr, model, param: str, name: str) -> np.ndarray:
    """``arr`` read from ``name`` as ``(n, ny, nx)`` (or ``(n, ny*nx)``) finite FEM difference images
    on the image model's grid; anything else is a :class:`UserError` naming ``param``."""
    _check_input(model, "image")
    a = np.asarray(arr)
    if a.dtype.kind not in "iuf":
        raise UserError(param, f"{name}: expected a numeric image array (got dtype {a.dtype})")
    shape = tuple(model.shape) if getattr(model, "shape", None) is not None else None
    if shape is not None and a.shape == shape:
        a = a[None]
    fits = a.ndim == 3 and (shape is None or a.shape[1:] == shape)
    fits = fits or (shape is not None and a.ndim == 2 and a.shape[1] == shape[0] * shape[1])
    if not fits or a.shape[0] == 0 or a.size == 0:
        want = f"{shape[0]} x {shape[1]} (or a stack n x {shape[0]} x {shape[1]})" if shape else "(n, ny, nx)"
        raise UserError(param, f"{name}: expected the model's image shape {want} (got shape {a.shape})")
    if not np.isfinite(a).all():
        raise UserError(param, f"{name}: contains NaN or inf")
    return a.astype(float)


def _ids(ids, n: int, what: str) -> list[str]:
    ids = [str(i + 1) for i in range(n)] if ids is None else [str(i) for i in ids]
    if len(ids) != n:
        raise UserError("ids", f"{len(ids)} ids for {n} {what}")
    return ids


def _predict(
    model, X: np.ndarray, ids: list[str], cam, fem, flags, no_signal, input="features", images=None, sigma=None
) -> list[Estimate]:
    """The one path of every inverse model: its members' predictions of the model inputs ``X``
    -> one :class:`Estimate` per row, with the given ``flags`` (per row), ``outside_training:<input>``
    for inputs outside the model's training range and ``no_signal`` first where ``no_signal[i]``.
    ``images``/``sigma`` (per row, or None): the difference image the estimate keeps and its noise."""
    n = len(ids)
    Y, mean, sd, p10, p90 = _members(model.predict(X), n)
    outside = model.outside_training(X)
    ests = []
    for i in range(n):
        f = list(flags[i]) + [f"outside_training:{k}" for k in outside[i]]
        if no_signal[i]:
            f.insert(0, "no_signal")
        e = Estimate(ids[i], cam[i], fem[i], mean[i], sd[i], p10[i], p90[i], Y.shape[0], f, input=input)
        e.image = None if images is None else images[i]
        e.sigma = None if sigma is None else sigma[i]
        ests.append(e)
    return ests


def estimate(
    cam_features,
    calibration: Calibration,
    model,
    ids: list[str] | None = None,
    identifiability="default",
    threshold: float = 0.10,
) -> list[Estimate]:
    """(n, 3) camera features -> list of :class:`Estimate` by a feature model (an
    :class:`~elastimap.training.model.InverseModel` whose ``input_kind`` is ``"features"``).

    ``identifiability``: see :func:`load_identifiability`; its ``features`` set is used."""
    cam = np.atleast_2d(np.asarray(cam_features, dtype=float))
    if cam.ndim != 2 or cam.shape[1] != 3:
        raise UserError("features", f"need three camera features O1 O2 O3 per lesion (got shape {cam.shape})")
    if not np.all(np.isfinite(cam)):
        raise UserError("features", "camera features must be finite numbers")
    ids = _ids(ids, cam.shape[0], "lesions")
    _check_input(model, "features")
    idmap = load_identifiability(identifiability)
    fem = calibration.apply(cam)
    out_cal = calibration.outside(cam)
    flags = [[f"outside_calibration:{k}" for j, k in enumerate(FEATURES) if row[j]] for row in out_cal]
    ests = _predict(model, fem, ids, cam, fem, flags, cam[:, 0] <= 0)
    return _assess(ests, model, idmap, model.input_kind, threshold)


def load_model(directory: str | os.PathLike):
    """The :class:`~elastimap.training.model.InverseModel` a directory holds: an image model
    (:mod:`elastimap.identify.image_model`, which adds its PCA file) or a feature ensemble
    (:class:`elastimap.training.model.Ensemble`); any damage is one :class:`UserError`."""
    from elastimap.identify.image_model import PCA_FILE, ImageModel
    from elastimap.training.model import Ensemble

    d = str(directory)
    if not os.path.isdir(d):
        raise UserError("model", f"{d}: no such model directory")
    return (ImageModel if os.path.isfile(os.path.join(d, PCA_FILE)) else Ensemble).load(d)


def estimate_fem_images(
    images,
    model,
    ids: list[str] | None = None,
    identifiability="default",
    threshold: float = 0.10,
    cam_features=None,
    flags=None,
    sigma=None,
) -> list[Estimate]:
    """(n, ny, nx) (or (n, ny*nx)) FEM difference images (mm) -> list of :class:`Estimate` (image model).

    ``cam``/``fem`` of each estimate hold the camera features (NaN for simulated input) and the
    image's own FEM features O1..O3; ``sigma`` (like ``images``, mm) their per-pixel standard errors
    where measured (from frames; kept for the refinement).  ``identifiability``: the map's ``image``
    set (1 % of the peak per pixel), or, with ``sigma`` and a map that has a ``camera`` set, the
    larger of that set scaled by the frames' noise
    (:meth:`elastimap.identify.idmap.IdentifiabilityMap.camera_scale`) and the ``image`` set
    (``crb_set`` "frames", :data:`elastimap.identify.idmap.FRAMES`)."""
    from elastimap.solver.image import features as image_features

    _check_input(model, "image")
    if model.force:
        raise UserError(
            "model",
            "this image model also needs the plate force; inference from images alone "
            "needs a model trained without --force",
        )
    imgs = np.asarray(images, dtype=float)
    if model.shape is not None and imgs.ndim == 2 and imgs.shape == tuple(model.shape):
        imgs = imgs[None]
    imgs = imgs.reshape(imgs.shape[0], -1) if imgs.ndim >= 2 else np.atleast_2d(imgs)
    n = imgs.shape[0]
    ids = _ids(ids, n, "images")
    idmap = load_identifiability(identifiability)
    if model.shape is not None and model.pixel:  # each image's own O1..O3, as the sweep's
        fem = np.array([image_features(im.reshape(model.shape), model.pixel) for im in imgs], dtype=float)
    else:
        fem = np.full((n, 3), math.nan)
    cam = np.asarray(cam_features, float) if cam_features is not None else np.full((n, 3), math.nan)
    sg = None if sigma is None else np.asarray(sigma, float).reshape(n, -1)
    no_signal = [
        not np.abs(imgs[i]).max() > 0 or (sg is not None and not np.max(imgs[i] / sg[i]) >= DETECT_SIGMA)
        for i in range(n)
    ]
    flags = flags if flags is not None else [[] for _ in range(n)]
    ests = _predict(model, imgs, ids, cam, fem, flags, no_signal, "image", imgs.copy(), sg)
    from elastimap.identify.idmap import FRAMES

    if sigma is not None and idmap is not None and "camera" in idmap.relstd and idmap.camera_sigma is not None:
        # measured per-pixel noise (frames): the camera set scaled by this camera's noise, never
        # below the 1 % image set (the forward model's own error; region.FRAMES)
        if idmap.camera_sigma.size == imgs.shape[1]:
            for e in ests:
                _assess([e], model, idmap, FRAMES, threshold, idmap.camera_scale(e.sigma, e.image))
            return ests
    return _assess(ests, model, idmap, model.input_kind, threshold)


def refine_estimates(
    ests: list[Estimate],
    images=None,
    image_noise: float = 0.01,
    mesh: str = "coarse",
    threshold: float = 0.10,
    chi2_limit: float = 3.0,
    progress=None,
    forward=None,
    forward_alt=None,
    geometry: str | None = None,
    forward_fine=None,
    correct: str | None = None,
    coords: str = "contrast",
    max_passes: int = 2,
    fine: str = "correct",
    intervals: str | None = None,
    sensor=None,
    discrepancy=None,
    pixel: float | None = None,
    press=None,
) -> list[Estimate]:
    """Refine image-model estimates by the maximum-likelihood fit of the forward map
    (:func:`elastimap.identify.fit.fit_image`).

    ``images`` as given to :func:`estimate_fem_images` (FEM difference images, mm, on the model's
    grid; default: each estimate's own ``image``).  Pixel noise: where the frames measured it
    (:func:`difference_of_frames`) each pixel's own standard error, else ``image_noise`` x the
    image's peak (``--fem-image``); to it the fit adds the forward map's own error, measured as the
    difference of two mesh levels at the estimate (no assumed floor).  Forward map:
    ``forward``/``forward_alt`` (``(d, h, E) -> image``) or, by default, the solver's map at
    ``mesh`` and its neighbouring level (:func:`elastimap.identify.forward_maps.forward_map`, mesh
    morphing where available; runs DOLFINx); ``forward_fine``, or by default with ``correct`` (a mesh
    level finer than ``mesh``) the solver's map at that level: its defect corrects the map at the start
    of every pass after the first, and the model error is then measured between ``correct`` and its
    neighbouring level (:func:`elastimap.identify.fit.fit_image`).  ``coords``: the fit's coordinate
    of E (:class:`elastimap.identify.coords.FitCoords`); ``max_passes``: the fit's passes (corrected
    ones with a finer level; :func:`~elastimap.identify.fit.fit_image`); ``fine``: how those passes
    use the finer level, ``"correct"`` (defect correction) or ``"direct"`` (they fit it).  ``intervals``:
    the fit's 95 % intervals (:func:`~elastimap.identify.fit.fit_image`); None: the calibrated ones
    where all the maps are the solver's (:func:`~elastimap.identify.forward_maps.fit_maps`) at the calibrated
    levels (:func:`~elastimap.identify.forward_maps.default_intervals`), else the Gauss–Newton ones.
    ``sensor`` (:class:`elastimap.sensor.Sensor`; None: the paper's): the solver's maps press with its
    mechanics (:func:`~elastimap.identify.forward_maps.fit_maps`).  ``progress(i, n)`` after each lesion.
    ``discrepancy``: the model-form error the fit carries
    (:class:`elastimap.identify.discrepancy.Discrepancy`, learnt by ``camera calibrate`` from the lab's
    phantoms, :meth:`~elastimap.camera.calibration.Calibration.model_form`) on images of ``pixel`` mm: the fit's estimate stays its
    own (but for h, shifted by the term's depth mode, :func:`elastimap.identify.fit.depth_shift`), its
    covariance is the marginal one with the term integrated out, and an E on the design edge gets the
    valley's interval (docs/model-form.md, 'How the fit carries it'); None: the closed world
    (noise and discretisation only).  ``press``: the flat field's press uncertainty
    (:class:`elastimap.camera.deflection.PressTerm`, from the calibration; None: none), a low-rank error
    of the recovered image the fit weighs its pixels by (docs/camera.md, 'The flat field's press
    uncertainty').

    Each estimate's mean becomes the fitted (d, h, E), ``lo``/``hi`` its 95 % interval and ``sd``/``crb``
    the standard deviation that interval stands for (relative for ``crb``): the Gauss–Newton one times
    the interval's scale (:attr:`~elastimap.identify.fit.FitResult.relstd_calibrated`; the scale is 1
    for the Gauss–Newton interval); ``non_identifiable:q`` is re-decided from it (``> threshold``), and
    ``model_mismatch`` added when the fit leaves a reduced chi² above ``chi2_limit`` (the forward
    model cannot reproduce the image at the stated noise), ``at_design_edge:q`` for each parameter
    the fit ended on the design box's edge with (then nothing is reportable); ``input`` gains
    ``+fem_refined``."""
    if not 0 < image_noise < 1:
        raise UserError("image_noise", f"must be in (0, 1) (got {image_noise:g})")
    imgs = _images_to_refine(ests, images)
    forward, forward_alt, forward_fine, intervals = _refine_maps(
        mesh, correct, geometry, sensor, forward, forward_alt, forward_fine, intervals
    )
    fit_options = dict(
        forward_alt=forward_alt,
        forward_fine=forward_fine,
        coords=coords,
        max_passes=max_passes,
        fine=fine,
        intervals=intervals,
        discrepancy=discrepancy,
        pixel=pixel,
        shared=press,
    )
    for i, (e, img) in enumerate(zip(ests, imgs)):
        if "no_signal" not in e.flags:
            _take_fit(e, _fit_estimate(e, img, image_noise, forward, fit_options), threshold, chi2_limit)
        if progress:
            progress(i + 1, len(ests))
    return ests


def _refine_maps(mesh, correct, geometry, sensor, forward, forward_alt, forward_fine, intervals):
    """The fit's (forward, forward_alt, forward_fine, intervals) of :func:`refine_estimates`: the
    maps given, the solver's (:func:`elastimap.identify.forward_maps.fit_maps` at ``mesh``, its
    neighbouring level and ``correct``) where ``forward`` is not, and the intervals given, else
    the calibrated ones only where all the maps are the solver's at the calibrated levels
    ("gauss" when any map was given).  ``correct`` is checked first (a :class:`UserError`)."""
    from elastimap.identify.forward_maps import check_correct, fit_maps

    check_correct(mesh, correct)
    given = forward is not None or forward_alt is not None or forward_fine is not None
    if forward is None:
        maps = fit_maps(mesh, correct, geometry, sensor)
        forward = maps.forward
        forward_alt = maps.forward_alt if forward_alt is None else forward_alt
        forward_fine = maps.forward_fine if forward_fine is None else forward_fine
    if intervals is None:  # calibrated only for the solver's own maps at the calibrated levels
        intervals = "gauss" if given else maps.intervals
    return forward, forward_alt, forward_fine, intervals


def _fit_estimate(e: Estimate, img: np.ndarray, image_noise: float, forward, fit_options: dict):
    """The fit (:func:`elastimap.identify.fit.fit_image`) of image ``img`` (mm; square images
    as n x n) from estimate ``e``'s mean: the pixel noise is ``e.sigma`` where the frames
    measured it (mm), else ``image_noise`` x the image's peak |img|."""
    from elastimap.identify.fit import fit_image

    n = int(round(math.sqrt(img.size)))
    img2 = img.reshape(n, n) if n * n == img.size else img
    pk = np.abs(img).max()
    sig = np.asarray(e.sigma, float).reshape(img2.shape) if e.sigma is not None else image_noise * pk
    return fit_image(img2, sig, e.mean, forward, **fit_options)


def _images_to_refine(ests: list[Estimate], images) -> list[np.ndarray]:
    """The images the fit refines against: ``images`` (one per estimate) or each estimate's own."""
    if images is None:
        if any(e.image is None for e in ests):
            raise UserError("images", "an estimate carries no image to refine against")
        return [np.asarray(e.image, dtype=float) for e in ests]
    return list(np.asarray(images, dtype=float).reshape(len(ests), -1))


def _take_fit(e: Estimate, r, threshold: float, chi2_limit: float) -> None:
    """Estimate ``e`` becomes the fit ``r``'s: mean, interval, sd and relative sd, its
    identifiability and design-edge flags re-decided, ``model_mismatch`` when the reduced chi²
    exceeds ``chi2_limit``, ``+fem_refined`` in its input (see :func:`refine_estimates`)."""
    e.mean = r.theta
    e.crb = r.relstd_calibrated
    e.sd = r.sd * r.scale
    e.lo, e.hi = r.lo, r.hi
    e.flags = [f for f in e.flags if not f.startswith("non_identifiable:") and f != "outside_identifiability_map"]
    e.flags += [f"non_identifiable:{q}" for j, q in enumerate(TARGETS) if not e.crb[j] <= threshold]
    e.flags = [f for f in e.flags if not f.startswith("at_design_edge:")]
    e.flags += [f"at_design_edge:{q}" for q in r.at_bound]
    if r.chi2_red > chi2_limit:
        e.flags.append("model_mismatch")
    e.input = e.input + "+fem_refined"
    e.fit = r
    _plausibility([e])


def sensor_of(calibration: Calibration):
    """The camera geometry (and synthetic model) the calibration was made with."""
    from .optics import SensorModel

    return SensorModel.from_dict(calibration.sensor) if calibration.sensor else SensorModel()


def settings_of(calibration: Calibration):
    from .features import FeatureSettings

    return FeatureSettings.from_dict(calibration.feature_settings or {})


def features_of_images(images: list[str], background: list[str], calibration: Calibration):
    """Camera features of one lesion's frames, computed exactly as for the calibration."""
    from .features import features_from_files

    return features_from_files(images, background, sensor_of(calibration), settings_of(calibration))


def difference_of_frames(images: list[str], background: list[str], calibration: Calibration, model=None):
    """One lesion's frame files -> :class:`elastimap.camera.deflection.DeflectionImage`: the
    FEM-equivalent difference image (mm) on the calibration's FEM grid and its per-pixel standard
    error from the frames' scatter (inverse sensor response, flat field from the background
    frames, the calibration's scale).  ``model`` (an image model): its grid must be that grid."""
    from .deflection import difference_image
    from .frames import read_stack

    sensor = sensor_of(calibration)
    ref, pixel = calibration.reference_image()
    if model is not None:
        if model.shape is None or not model.pixel:
            raise UserError("model", "this image model does not record its image grid; re-save it with this version")
        if tuple(model.shape) != ref.shape or abs(float(model.pixel) - pixel) > 1e-9:
            raise UserError(
                "model",
                f"the image model's grid ({model.shape[0]}x{model.shape[1]} of {model.pixel:g} mm) "
                f"differs from the calibration's FEM grid ({ref.shape[0]}x{ref.shape[1]} of "
                f"{pixel:g} mm)",
            )
    F, fs1 = read_stack(images, sensor.shape, sensor.window, bits=sensor.bits)
    B, fs2 = read_stack(background, sensor.shape, sensor.window, "background", bits=sensor.bits)
    if fs1 != fs2:
        raise UserError("background", f"{background[0]}: bit depth differs from the lesion frames ({images[0]})")
    if fs1 != sensor.full_scale:
        raise UserError(
            "images",
            f"{images[0]}: frames of full scale {fs1}, the calibration's camera has "
            f"{sensor.bits} bits (full scale {sensor.full_scale})",
        )
    return difference_image(F, B, sensor, ref, pixel, scale=float(calibration.deflection["scale"]))


def estimate_images(
    images: list[str],
    background: list[str],
    calibration: Calibration,
    model,
    id: str = "1",
    identifiability="default",
    threshold: float = 0.10,
    keep_image: bool = False,
) -> Estimate:
    """One lesion's camera frames -> :class:`Estimate`, with a feature ensemble or an image model.

    Feature ensemble: camera features -> the calibration's lines -> the network (with
    ``keep_image`` the estimate also carries :func:`difference_of_frames`' image and noise, for
    :func:`refine_estimates`).  Image model: :func:`difference_of_frames` -> the network; the
    estimate keeps the image and its per-pixel noise for :func:`refine_estimates`."""
    cf = features_of_images(images, background, calibration)
    if model.input_kind == "features":
        e = estimate(cf.values[None], calibration, model, [id], identifiability, threshold)[0]
        if keep_image:
            di = difference_of_frames(images, background, calibration)
            e.image, e.sigma = di.image.ravel(), di.sigma.ravel()
            e.input = "frames"
            if di.saturated:
                e.flags.append("saturated")
        return e
    out_cal = calibration.outside(cf.values[None])[0]
    flags = [f"outside_calibration:{k}" for j, k in enumerate(FEATURES) if out_cal[j]]
    di = difference_of_frames(images, background, calibration, model)
    if di.saturated:
        flags.append("saturated")
    e = estimate_fem_images(
        di.image[None],
        model,
        [id],
        identifiability,
        threshold,
        cam_features=cf.values[None],
        flags=[flags],
        sigma=di.sigma[None],
    )[0]
    e.input = "frames"
    return e


def estimate_lesions_csv(
    path: str | os.PathLike,
    calibration: Calibration | None,
    model,
    identifiability="default",
    threshold: float = 0.10,
    progress=None,
    keep_image: bool = False,
    allow_outside: bool = False,
) -> list[Estimate]:
    """Batch of lesions from a CSV, for every model kind (format in :func:`read_lesions_table`);
    ``keep_image``: frames rows of a feature ensemble also keep their difference image (for
    :func:`refine_estimates`).

    Feature ensemble: ``O1,O2,O3`` or ``images,background``; image model: ``images,background``
    (each lesion's frames -> :func:`estimate_images`) or ``fem_image`` (a ``.npy`` FEM difference
    image, mm, no calibration needed).  ``progress(i, n)`` after each lesion."""
    ids, kind, rows = read_lesions_table(path, allow_outside)
    image_model = model.input_kind == "image"
    if kind == "features":
        if image_model:
            raise UserError(
                "csv",
                f"{path}: an image model needs columns images,background (camera frames) or "
                "fem_image, not camera features O1,O2,O3",
            )
        return estimate(rows, _need_cal(calibration), model, ids, identifiability, threshold)
    if kind == "fem_image":
        if not image_model:
            raise UserError("csv", f"{path}: fem_image rows need an image model")
        imgs = []
        for i, f in zip(ids, rows):
            try:
                arr = np.load(f, allow_pickle=False)
            except Exception as exc:
                raise UserError("csv", f"{path}: lesion {i}: {f} is not a .npy array ({exc})") from None
            imgs.append(fem_image_stack(arr, model, "csv", f"{path}: lesion {i}: {f}")[0])
        return estimate_fem_images(np.array(imgs, dtype=float), model, ids, identifiability, threshold)
    cal = _need_cal(calibration)
    if not image_model and not keep_image:
        cam = np.array([features_of_images(im, bg, cal).values for im, bg in rows])
        return estimate(cam, cal, model, ids, identifiability, threshold)
    idm = load_identifiability(identifiability)
    out = []
    for k, (i, (im, bg)) in enumerate(zip(ids, rows)):
        out.append(estimate_images(im, bg, cal, model, i, idm, threshold, keep_image=keep_image))
        if progress:
            progress(k + 1, len(rows))
    return out


def _need_cal(calibration):
    if calibration is None:
        raise UserError("calibration", "camera features and frames need the FEM<->camera calibration file")
    return calibration


def read_lesions_table(path: str | os.PathLike, allow_outside: bool = False):
    """The batch CSV: ``(ids, kind, rows)``; the files it names must lie in its folder unless
    ``allow_outside`` (``--allow-outside``).

    Columns: optional ``id`` (default 1, 2, ...) and one of

    * ``O1,O2,O3`` - camera features (feature ensembles) -> kind ``features``, rows (n, 3);
    * ``images,background`` - each a ';'-separated list of frame files or glob patterns, relative
      to the CSV's folder (every kind of model) -> kind ``frames``, rows [(image files, background files)];
    * ``fem_image`` - a ``.npy`` FEM difference image (mm, image models) -> kind ``fem_image``, rows [path].
    """
    import pandas as pd

    from elastimap.tables import read_csv

    from .frames import expand

    p = str(path)
    df = read_csv(p, "csv")
    if len(df) == 0:
        raise UserError("csv", f"{p}: no lesions")
    ids = [str(x) for x in df["id"]] if "id" in df.columns else [str(i + 1) for i in range(len(df))]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise UserError("csv", f"{p}: duplicate id(s) {', '.join(dup[:5])} (every lesion needs its own id)")
    base = os.path.dirname(os.path.abspath(p))
    if all(k in df.columns for k in FEATURES):
        vals = df[list(FEATURES)].apply(pd.to_numeric, errors="coerce").to_numpy(float)
        bad = ~np.all(np.isfinite(vals), axis=1)
        if bad.any():
            raise UserError("csv", f"{p}: non-numeric features for lesion(s) {[ids[i] for i in np.flatnonzero(bad)]}")
        return ids, "features", vals
    if "images" in df.columns and "background" in df.columns:
        rows = []
        for i, (_, r) in zip(ids, df.iterrows()):
            if pd.isna(r["images"]) or pd.isna(r["background"]):
                raise UserError("csv", f"{p}: lesion {i}: empty images or background")
            try:
                rows.append(
                    tuple(
                        expand(str(r[c]), base, param="csv", allow_outside=allow_outside)
                        for c in ("images", "background")
                    )
                )
            except UserError as exc:
                raise UserError("csv", f"{p}: lesion {i}: {exc.message}") from None
        return ids, "frames", rows
    if "fem_image" in df.columns:
        rows = []
        for i, f in zip(ids, df["fem_image"]):
            f = str(f)
            f = f if os.path.isabs(f) else os.path.join(base, f)
            if not allow_outside and not _inside(f, base):
                raise UserError(
                    "csv", f"{p}: lesion {i}: {f}: outside the folder {base} (give --allow-outside to allow it)"
                )
            if not os.path.isfile(f):
                raise UserError("csv", f"{p}: lesion {i}: {f}: no such file")
            rows.append(f)
        return ids, "fem_image", rows
    raise UserError("csv", f"{p}: needs columns O1,O2,O3 or images,background or fem_image (plus optional id)")


def _inside(path: str, folder: str) -> bool:
    real, root = os.path.realpath(path), os.path.realpath(folder)
    return real.startswith(root.rstrip(os.sep) + os.sep)


def read_lesions_csv(path: str | os.PathLike, calibration: Calibration) -> tuple[list[str], np.ndarray]:
    """Camera features of a batch CSV (``O1,O2,O3`` or ``images,background`` rows, see
    :func:`read_lesions_table`): ``(ids, (n, 3))``."""
    ids, kind, rows = read_lesions_table(path)
    if kind == "features":
        return ids, rows
    if kind == "frames":
        return ids, np.array([features_of_images(im, bg, calibration).values for im, bg in rows])
    raise UserError("csv", f"{path}: needs columns O1,O2,O3 or images,background (plus optional id)")
