"""The physics fit: maximum-likelihood (d, h, E) of a measured difference image through the forward model.

A trained network (image or feature model) gives a fast first estimate ``θ₀``; the fit removes the
network's error by fitting the forward model itself to the measured difference image ``I`` (mm,
``p`` pixels, e.g. recovered from camera frames by :mod:`elastimap.camera.deflection`) whose
pixels have standard errors ``σ_meas`` (mm, from the frames' own scatter).

:class:`ImageFit` is the fit, put together from separate pieces (as hIPPYlib's ``Model`` keeps
problem, prior and misfit apart from the optimisers), each declared in :class:`FitConfig`:

* **forward map** (:class:`FitModel`; the maps of :mod:`elastimap.identify.forward_maps`): ``m(θ)``
  (mm), ``θ = (d mm, h mm, E kPa)``, the solver on a mesh *morphed* to (d, h), smooth in (d, h, E).
  Each pass pins the morphed map's reference mesh where it starts (one smooth map per pass; the
  d-bin below, :func:`~elastimap.identify.forward_maps.reference_below`); a pinned map takes its
  reference press (the no-inclusion solve it subtracts) to first order in (d, h) about the pin.
  With a finer level ``m_f`` of the same map (``forward_fine``), pass 0 fits the coarse map alone
  and every later pass fits the defect-corrected map

      m̃(x) = m(x) + [m_f(x_s) − m(x_s)]      (x_s the pass's start)

  which equals the finer map at ``x_s`` and has the coarse map's derivative: the fixed point of the
  passes is the finer map's fit (``fine="direct"``: later passes fit ``m_f`` itself).
* **noise model** (:class:`PixelNoise`): independent Gaussian pixel errors with
  ``σ_i² = σ_meas,i² + σ_model,i²``.  The map's own discretisation error is measured, not assumed,
  as the difference of two mesh levels at the same θ, ``δ(θ) = m(θ) − m^alt(θ)`` (``forward_alt``,
  re-solving its reference press so that δ holds the linearisation's error too), with
  ``σ_model,i = sqrt(mean_{3x3 around i} δ²)`` (a local rms, so that a pixel where the two levels
  happen to cross does not claim a perfect model).  It is measured where each pass starts (with
  ``forward_fine`` only where the first corrected pass starts, held for the later passes) and again
  at the estimate for the covariance.  Optionally (``shared``, :class:`FitConfig`) a low-rank error
  ``U γ``, ``γ ~ N(0, I)``, shared by the whole image (the flat field's press uncertainty,
  :class:`elastimap.camera.deflection.PressTerm`; docs/camera.md, 'The flat field's press uncertainty'):
  the pixels' covariance is then ``diag σ² + U Uᵀ``, whitened by :class:`Whiten` in the passes and the
  covariance alike.
* **prior** (:class:`DesignPrior`): the design box, a box in the fit's coordinates
  ``x = (d, u, e)`` (:class:`~elastimap.identify.coords.FitCoords`: ``u`` the depth fraction,
  ``e = ln c(E)`` Eshelby's contrast, in which the d–E valley of equal images is nearly straight,
  or ``e = ln E``).
* **optimiser** (:class:`Optimiser`, :func:`broyden_pass`): start at ``θ₀`` or the best of
  ``e_scan`` values of E spread evenly in ``e`` at θ₀'s (d, h); then passes of
  :func:`scipy.optimize.least_squares` (trust-region reflective, bounds) of

      θ̂ = argmin_θ  ½ Σ_i ((m_i(θ) − I_i) / σ_i)²

  (the maximum-likelihood estimate for Gaussian pixel errors), each from a fresh Jacobian -- the
  map's exact derivative where it has one (:meth:`~elastimap.identify.forward_maps.ForwardMap.tangent`),
  else central differences with steps :data:`FD_STEPS` -- carried within the pass by Broyden's
  rank-one update ``J ← J + ((r₊ − r) − J Δx) Δxᵀ / |Δx|²``.  A step that lowers ½χ² by less than
  0.05 ends a pass; a pass that moves no parameter by more than 0.2 of its sd ends the fit.
* **interval** (:func:`interval95`): Gauss–Newton covariance at ``θ̂``,
  ``C_x = (JᵀJ)⁻¹ max(1, χ²_red) + Σ_k b_k b_kᵀ`` with ``b_k = (JᵀJ)⁻¹ Jᵀ (δ_k / σ)`` (a
  discretisation error moves every pixel together: a bias, propagated as a systematic shift; the
  Birge factor widens, never narrows), mapped to (d, h, ln E) by the delta method.  The 95 %
  interval is ``q ± 1.96 k sd`` for d and h and ``e ± 1.96 k sd_e`` mapped back for E, clipped to
  the box: ``intervals="gauss"`` ``k = 1``; ``"calibrated"`` ``k`` per class of the relative sd and
  stratum of the estimate (:mod:`elastimap.identify.intervals`, scales read from
  ``identify/maps/intervals.json``), for the configuration they were calibrated on
  (:func:`~elastimap.identify.forward_maps.default_intervals`).

* **model-form term** (``discrepancy``, :class:`~elastimap.identify.discrepancy.Discrepancy`, learnt by
  ``camera calibrate`` from the lab's calibration phantoms; docs/model-form.md, 'How the fit carries
  it'): the world differs from the map by ``δ = Φ β + a η`` (modes of the image, ``β ~ N(μ, C)``, and a
  correlated remainder).  The estimate is the closed world's (the passes above) -- the term adds no
  walk along the d–E valley and no correction of the mean (subtracting ``Φ μ`` moved d by 2–12 % the
  wrong way on the SYNTHETIC variant world, its mean over the phantoms not that of the lesion) -- and
  its covariance is the marginal one,

      C_x = [(J_a ᵀ J_a)⁻¹]_xx max(1, χ²_m / dof) + Σ_k b_k b_kᵀ,
      J_a = [ L_D⁻¹ J   L_D⁻¹ Φ ;  0   L_C⁻¹ ],   D = diag σ² + ρ² A K_ℓ A,   L_C L_Cᵀ = C

  (:class:`~elastimap.identify.discrepancy.Marginal`: the generalised least squares of the pixels under
  ``Σ = D + Φ C Φᵀ``, its modes built from the map's image at the estimate; ``χ²_m`` the marginal misfit
  there).  The interval is ``θ̂ ± 1.96 sd`` from it (``k = 1``: the calibrated scales are the closed
  world's), and a parameter whose relative sd exceeds the threshold is reported as its interval.  A term
  with the depth mode (``β_h`` a relative error of the depth, learnt from the phantoms) shifts ``ln ĥ`` by
  ``−μ_h`` and adds ``v_h`` to its variance (:func:`depth_shift`: the mode is the map's own ``h ∂m/∂h``, so
  it is Kennedy–O'Hagan's posterior for h and moves neither d nor E).  A fit
  that ends with E on the design box's edge reports the valley's interval (:func:`valley_interval`: E
  over the box, d along the valley of equal amplitude across it).  Why
  not the marginal optimum: the marginal misfit is flat along the valley (the amplitude mode absorbs
  what tells d from E), so a fit that minimises it walks wherever the map's shape error points --
  on the dev set to soft, larger inclusions, on the SYNTHETIC variant world (tiny map, coarse world
  2 % stiffer) a profile of it along the valley put 6 mm, 160 kPa at 7.7 mm, 10 kPa with a narrow
  interval (docs/model-form.md, 'Choosing the fit's formulation').

Measured accuracy and coverage: docs/camera.md, 'Inference'.  The fit itself tunes no factor; the
interval's scales are calibrated on seen benchmark seeds, never on the lesions a table scores.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares

from elastimap.dataset.schema import DESIGN_BOX, TARGETS, THICKNESS
from elastimap.errors import UserError
from elastimap.solver.params import Tissue

from .coords import FitCoords, h_range
from .discrepancy import Discrepancy, Marginal
from .forward_maps import fit_maps, image_of
from .intervals import Z95, scales_for

STILL_MOVING = "still moving"  # the message of a fit whose passes ran out (FitResult.converged)
FD_STEPS = (0.15, 0.15, 0.03)  # central-difference steps: d mm, h mm (at fixed d), ln E
FINE_MODES = ("correct", "direct")  # how the passes use a finer level (forward_fine)
#: the 95 % intervals: θ̂ ± 1.96 k sd with the calibrated scales k of :mod:`elastimap.identify.intervals`,
#: or θ̂ ± 1.96 sd (Gauss–Newton)
INTERVALS = ("calibrated", "gauss")


# ============================================================================ the declared configuration
@dataclass(frozen=True)
class DesignPrior:
    """The prior: θ uniform over the design box -- d in ``d_range`` (mm), h in its admissible range
    (:func:`~elastimap.identify.coords.h_range` of ``thickness``), E in ``E_range`` (kPa) -- in the
    fit's coordinates ``coords`` (``"contrast"`` or ``"log"``, :class:`FitCoords`); ``E_tissue``
    (kPa) the tissue modulus the contrast uses (None: the forward map's, else
    :class:`elastimap.solver.params.Tissue`'s)."""

    d_range: tuple[float, float] = DESIGN_BOX["d"]
    E_range: tuple[float, float] = DESIGN_BOX["E"]
    thickness: float = THICKNESS
    coords: str = "contrast"
    E_tissue: float | None = None

    def coordinates(self, forward) -> FitCoords:
        E_tissue = self.E_tissue
        if E_tissue is None:
            E_tissue = getattr(forward, "E_tissue", None) or Tissue().E
        return FitCoords(self.thickness, self.coords, float(E_tissue), float(self.E_range[0]))


@dataclass(frozen=True)
class Optimiser:
    """The minimiser's settings: central-difference steps ``fd`` (d mm, h mm, ln E), trial points
    per pass ``max_nfev``, passes ``max_passes`` (corrected ones with a finer level), ``e_scan``
    start values of E (0 or 1: no scan) and ``tangent`` (the map's exact derivative instead of
    central differences and Broyden updates; None: where the map has one)."""

    fd: tuple[float, float, float] = FD_STEPS
    max_nfev: int = 12
    max_passes: int = 2
    e_scan: int = 5
    tangent: bool | None = None


@dataclass(frozen=True)
class FitConfig:
    """What a fit is made of besides its maps: the prior, the optimiser, how passes after the first
    use a finer level (``fine``: :data:`FINE_MODES`) and the reported interval (``intervals``:
    :data:`INTERVALS`)."""

    prior: DesignPrior = field(default_factory=DesignPrior)
    optimiser: Optimiser = field(default_factory=Optimiser)
    fine: str = "correct"
    intervals: str = "gauss"
    #: the model-form error the fit carries (:class:`~elastimap.identify.discrepancy.Discrepancy`,
    #: learnt from the lab's calibration phantoms; None: the closed world) on images of ``pixel`` mm
    discrepancy: Discrepancy | None = None
    pixel: float | None = None
    #: a low-rank pixel error shared by the whole image (None: none): called with the map's image ``m``
    #: (mm, flat) it returns ``U`` ``(p, K)`` (mm), the error ``U γ`` with ``γ ~ N(0, I)``, so that the
    #: pixels' covariance is ``diag σ² + U Uᵀ`` in the passes and the covariance (:class:`Whiten`; e.g.
    #: :class:`elastimap.camera.deflection.PressTerm`, the flat field's press uncertainty)
    shared: Callable | None = None

    def __post_init__(self):
        if self.discrepancy is not None and not (self.pixel and math.isfinite(self.pixel) and self.pixel > 0):
            raise UserError(
                "pixel", f"a fit carrying a discrepancy needs the image's pixel side in mm (got {self.pixel})"
            )
        if self.fine not in FINE_MODES:
            raise UserError("fine", f"must be one of {', '.join(FINE_MODES)} (got {self.fine!r})")
        if self.intervals not in INTERVALS:
            raise UserError("intervals", f"must be one of {', '.join(INTERVALS)} (got {self.intervals!r})")

    @classmethod
    def of(
        cls,
        *,
        d_range=DESIGN_BOX["d"],
        E_range=DESIGN_BOX["E"],
        thickness: float = THICKNESS,
        fd=FD_STEPS,
        max_nfev: int = 12,
        max_passes: int = 2,
        e_scan: int = 5,
        tangent: bool | None = None,
        coords: str = "contrast",
        E_tissue: float | None = None,
        fine: str = "correct",
        intervals: str = "gauss",
        discrepancy: Discrepancy | None = None,
        pixel: float | None = None,
        shared: Callable | None = None,
    ) -> FitConfig:
        """The configuration from flat keywords (those of :func:`fit_image`)."""
        return cls(
            DesignPrior(tuple(d_range), tuple(E_range), thickness, coords, E_tissue),
            Optimiser(tuple(fd), max_nfev, max_passes, e_scan, tangent),
            fine,
            intervals,
            discrepancy,
            pixel,
            shared,
        )


# ============================================================================ the result
@dataclass
class FitResult:
    """The fitted (d mm, h mm, E kPa), its Gauss–Newton uncertainty and 95 % interval, and the cost."""

    theta: np.ndarray
    theta0: np.ndarray
    relstd: np.ndarray  # rel. std of d and h, std of ln E (Birge-widened Gauss–Newton covariance)
    lo: np.ndarray  # 95 % interval, clipped to the design box
    hi: np.ndarray
    chi2_red: float  # Σ r² / (p − 3) at theta with the final σ
    chi2_red0: float  # the same at theta0
    model_error: float  # rms σ_model / rms σ_meas over the pixels where the image is above 10 % of its peak
    n_solves: int  # forward-map evaluations at the fit's level
    n_alt: int  # evaluations at the other level (model error)
    seconds: float
    message: str
    at_bound: list[str] = field(default_factory=list)  # parameters that ended on the design box's edge
    n_fine: int = 0  # evaluations of the finer level (defect corrections, ``forward_fine``)
    #: parameters the last pass still moved by more than 0.2 of their sd (empty when converged)
    moving: list[str] = field(default_factory=list)
    #: the Gauss–Newton interval θ̂ ± 1.96 sd clipped to the box (E's in the fit's coordinate); ``lo``/``hi``
    #: are these with ``intervals="gauss"``, θ̂ ± 1.96 k sd with ``"calibrated"``
    lo_gauss: np.ndarray | None = None
    hi_gauss: np.ndarray | None = None
    #: the interval's scale k of (d, h, E) (``lo``/``hi`` = θ̂ ± 1.96 k sd): the calibrated one of
    #: :func:`elastimap.identify.intervals.scales_for` with ``intervals="calibrated"``, else ones
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))
    #: whether the fit carried the model-form term (:class:`FitConfig`'s ``discrepancy``): its covariance
    #: and χ² are then the marginal ones and ``scale`` is ones
    model_form: bool = False

    @property
    def relstd_calibrated(self) -> np.ndarray:
        """``relstd`` times the interval's scale: the relative sd the reported interval stands for
        (what decides whether a parameter is identifiable)."""
        return self.relstd * self.scale

    @property
    def sd(self) -> np.ndarray:
        """Absolute standard deviations (for E: first order, E x sd ln E)."""
        return self.relstd * self.theta

    @property
    def converged(self) -> bool:
        """Whether the last pass moved no parameter by more than 0.2 of its standard deviation (the
        fit's stopping rule); False: the passes ran out while it still moved, and the estimate and its
        interval are those of where it stopped."""
        return STILL_MOVING not in self.message


# ============================================================================ the pieces
def pinned_exact(f, d: float, h: float):
    """``f`` pinned at (d, h) with its reference press re-solved there (``pin_exact``), else
    ``pin``, else ``f`` itself."""
    p = getattr(f, "pin_exact", None) or getattr(f, "pin", None)
    return p(d, h) if p is not None else f


class FitModel:
    """The forward map as one fit sees it: ``m(x)`` at the fit coordinates ``x``, the map pinned at
    each pass's start (maps with ``pin(d, h)`` and a hashable ``key``), plus the pass's defect
    correction by the finer level; the other levels' images (``alts``, pinned by ``pin_exact``) and
    the level differences ``delta`` they give; every image cached and counted (``n_eval`` at the
    fit's level, ``n_fine`` at the finer, :attr:`n_alt` at the others)."""

    def __init__(self, forward, alts: list, finer, fine: str, tangent: bool, coords: FitCoords, n_pixels: int):
        self.forward, self.alts, self.finer, self.fine, self.tangent = forward, alts, finer, fine, tangent
        self.theta_of, self.n_pixels = coords.theta, n_pixels
        self.f, self.level, self.pinned_alts = forward, "fit", list(alts)
        self.correction: np.ndarray | float = 0.0
        self.delta: list[np.ndarray] = []
        self.cache: dict = {}
        self.jac_cache: dict = {}  # the exact derivatives (d, h, E) at the cached points, where used
        self.alt_cache: dict = {}
        self.n_eval = self.n_fine = 0

    @property
    def n_alt(self) -> int:
        return len(self.alt_cache)

    def pin(self, x, correct: bool = True, measure: bool = True) -> None:
        """Pin the maps' reference meshes at ``x``, so that one pass sees one smooth map, take
        (``correct``, with a finer level) the defect correction ``m_fine(x) − m(x)`` there and
        (``measure``) the model error, the differences ``m(x) − m_alt,k(x)``, held until measured
        again (without ``measure`` the last one stays)."""
        tt = self.theta_of
        d, h, _ = tt(x)
        direct = correct and self.finer is not None and self.fine == "direct"
        f = self.finer if direct else self.forward
        self.f, self.level = (f.pin(d, h) if hasattr(f, "pin") else f), ("fine" if direct else "fit")
        for i, fa in enumerate(self.alts):  # exact where it can be: the model error then measures the linearisation too
            self.pinned_alts[i] = pinned_exact(fa, d, h)
        self.correction = 0.0
        if correct and self.finer is not None and not direct:
            mf = self.flat(pinned_exact(self.finer, d, h)(*tt(x)), "finer")
            self.n_fine += 1
            self.correction = mf - self.pinned(x)
        if measure:
            self.measure(x)

    def measure(self, x) -> None:
        """The level differences ``m(x) − m_alt,k(x)`` at ``x`` (the model error)."""
        self.delta = [self(x) - a for a in self.alt_images(x)]

    def key(self, x, f, level: str = "fit"):
        return (level, getattr(f, "key", None), *np.round(np.asarray(x, float), 10))

    def flat(self, out, which: str) -> np.ndarray:
        v = image_of(out).ravel()
        if v.shape != (self.n_pixels,):
            raise RuntimeError(f"the {which} forward map returned {v.size} pixels, the image has {self.n_pixels}")
        return v

    def __call__(self, x, need_j: bool = True) -> np.ndarray:
        """The map the fit sees: the pinned map plus the pass's defect correction (zero without a
        finer level)."""
        return self.pinned(x, need_j) + self.correction

    def pinned(self, x, need_j: bool = True) -> np.ndarray:
        """The pinned map at ``x`` (and, with ``need_j``, its exact derivative where used)."""
        k = self.key(x, self.f, self.level)
        if k not in self.cache or (self.tangent and need_j and k not in self.jac_cache):
            if self.level == "fine":
                self.n_fine += 1
            else:
                self.n_eval += 1
            if self.tangent and need_j:
                out, jt = self.f.tangent(*self.theta_of(x))
                self.jac_cache[k] = np.asarray(jt, dtype=float).reshape(3, -1).T
            else:
                out = self.f(*self.theta_of(x))
            self.cache[k] = self.flat(out, "fit's")
        return self.cache[k]

    def jacobian(self, x) -> np.ndarray:
        """The pinned map's exact derivative ``(p, 3)`` = ∂m/∂(d, h, E) at ``x``."""
        self.pinned(x)
        return self.jac_cache[self.key(x, self.f, self.level)]

    def alt_images(self, x) -> list:
        """The other levels' images at ``x`` (cached per pinned map)."""
        out = []
        for i, fa in enumerate(self.pinned_alts):
            k = (i, *self.key(x, fa))
            if k not in self.alt_cache:
                self.alt_cache[k] = self.flat(fa(*self.theta_of(x)), "alternative")
            out.append(self.alt_cache[k])
        return out


def local_rms(diff: np.ndarray, shape) -> np.ndarray:
    """The rms of ``diff`` over the 3x3 pixels around each pixel (``shape`` the image's; None: |diff|)."""
    if shape is None:
        return np.abs(diff)
    return np.sqrt(ndimage.uniform_filter((diff * diff).reshape(shape), size=3, mode="nearest")).ravel()


@dataclass
class PixelNoise:
    """The noise model: independent Gaussian pixel errors, the measured ``s_meas`` (mm, flat) and
    the model error of the level differences, ``σ_model² = Σ_k local rms(δ_k)²``."""

    s_meas: np.ndarray
    shape: tuple[int, int] | None

    def sigma(self, delta: list) -> tuple[np.ndarray, np.ndarray]:
        """Total and model per-pixel σ for the level differences ``delta``."""
        if not delta:
            return self.s_meas, np.zeros_like(self.s_meas)
        sm = np.sqrt(sum(local_rms(dl, self.shape) ** 2 for dl in delta))
        return np.hypot(self.s_meas, sm), sm


class Whiten:
    """The whitening of pixel errors with covariance ``Σ = diag s² + U Uᵀ`` (``s`` mm ``(p,)``; ``U`` mm
    ``(p, K)`` or None): ``W(e)`` ``(p + K,)`` (or ``(p + K, n)`` for a matrix) with ``|W e|² = eᵀ Σ⁻¹ e``,
    the residual of ``min_γ |S⁻¹(e + U γ)|² + |γ|²`` at its minimum ``γ = −(I + UₛᵀUₛ)⁻¹ Uₛᵀ S⁻¹ e``
    (``Uₛ = S⁻¹ U``; Woodbury without forming Σ).  Linear in ``e``, so a Jacobian is whitened the
    same way and least squares on ``W(m(x) − I)`` is generalised least squares under Σ.  Without ``U``:
    ``e / s``."""

    def __init__(self, s, U=None):
        self.s = np.asarray(s, float)
        self.U = None if U is None or np.shape(U)[1] == 0 else np.asarray(U, float)
        if self.U is not None:
            self.Us = self.U / self.s[:, None]
            self.M = np.linalg.inv(np.eye(self.U.shape[1]) + self.Us.T @ self.Us)

    def __call__(self, e) -> np.ndarray:
        e = np.asarray(e, float)
        v = e / (self.s[:, None] if e.ndim == 2 else self.s)
        if self.U is None:
            return v
        g = -self.M @ (self.Us.T @ v)
        return np.concatenate([v + self.Us @ g, g])


def broyden_pass(resid: Callable, xs: np.ndarray, J0: np.ndarray, lb, ub, max_nfev: int):
    """One pass of the optimiser: :func:`scipy.optimize.least_squares` (trust-region reflective in
    the box ``[lb, ub]``) of ``½ |resid(x)|²`` from ``xs``, its Jacobian ``J0`` at the start carried
    by Broyden's rank-one update from the last accepted point; stops when a step lowers ½χ² by less
    than 0.05.  Returns (the end point clipped to the box, scipy's result)."""
    state = {"x": None, "J": None, "r": None}

    def jac(x):
        x = np.asarray(x, float)
        if state["J"] is None:
            J = J0
        else:  # Broyden's rank-one update from the last accepted point
            dx = x - state["x"]
            dr = resid(x) - state["r"]
            J = state["J"] + np.outer(dr - state["J"] @ dx, dx) / max(float(dx @ dx), 1e-300)
        state.update(x=x.copy(), J=J, r=resid(x))
        return J

    r_s = resid(xs)
    res = least_squares(
        resid,
        xs,
        jac=jac,
        bounds=(lb, ub),
        method="trf",
        x_scale=np.array([1.0, 0.1, 0.1]),
        max_nfev=max_nfev,
        xtol=1e-4,
        # stop when a step lowers ½χ² by less than 0.05 (a twentieth of a one-sigma change)
        ftol=max(1e-10, 0.1 / max(float(r_s @ r_s), 1e-300)),
        gtol=1e-8,
    )
    return np.clip(res.x, lb, ub), res


def interval95(X: FitCoords, x, Cx, k, prior: DesignPrior, lb, ub) -> tuple[np.ndarray, np.ndarray]:
    """The 95 % interval θ̂ ± 1.96 k sd at the fit coordinates ``x`` with covariance ``Cx`` (x units),
    clipped to the design box (E's in the fit's own coordinate ``e ± 1.96 k sd_e``, mapped back)."""
    Gx = X.dtheta(x)
    C = Gx @ Cx @ Gx.T  # in (d, h, ln E)
    th = X.theta(x)
    sd = np.sqrt(np.clip(np.diag(C), 0, None))
    d_range, E_range = prior.d_range, prior.E_range
    hlo, hhi = h_range(th[0], prior.thickness)
    se = Z95 * k[2] * math.sqrt(max(float(Cx[2, 2]), 0.0))
    e_lo, e_hi = X.theta([x[0], x[1], max(x[2] - se, lb[2])])[2], X.theta([x[0], x[1], min(x[2] + se, ub[2])])[2]
    lo = np.array([max(th[0] - Z95 * k[0] * sd[0], d_range[0]), max(th[1] - Z95 * k[1] * sd[1], hlo), e_lo])
    hi = np.array([min(th[0] + Z95 * k[0] * sd[0], d_range[1]), min(th[1] + Z95 * k[1] * sd[1], hhi), e_hi])
    lo[2], hi[2] = max(lo[2], E_range[0]), min(hi[2], E_range[1])
    return lo, hi


def valley_interval(X: FitCoords, x, lo, hi, prior: DesignPrior, lb, ub) -> tuple[np.ndarray, np.ndarray]:
    """The 95 % interval of a fit that ended with E on the design box's edge: the likelihood's maximum
    lies beyond the box along the d–E valley, so every point of the valley inside the box stays
    possible.  E's interval is the whole box, and d's the hull of its own and the valley's d across it:
    along the valley of equal amplitude ``3 ln d + e = const`` (``e = ln c(E)``, the contrast coordinate
    of :class:`~elastimap.identify.coords.FitCoords`), ``d(e) = d̂ exp((ê − e)/3)`` for e over the box."""
    lo, hi = np.array(lo, float), np.array(hi, float)
    d_ends = x[0] * np.exp((x[2] - np.array([ub[2], lb[2]])) / 3.0)
    lo[0] = max(min(lo[0], float(d_ends.min())), prior.d_range[0])
    hi[0] = min(max(hi[0], float(d_ends.max())), prior.d_range[1])
    lo[2], hi[2] = prior.E_range
    return lo, hi


def depth_shift(X: FitCoords, x, Cx, disc: Discrepancy, lb, ub) -> tuple[np.ndarray, np.ndarray]:
    """The estimate ``x`` and its covariance ``Cx`` (fit coordinates) under the discrepancy's depth mode
    (:meth:`~elastimap.identify.discrepancy.Discrepancy.depth_shift`, ``β ~ N(μ_h, v_h)``; unchanged
    without one).  The mode ``h ∂m/∂h`` is the map's own derivative along h, so the world's image is
    ``m(d, h (1 + β), E)`` and the closed world's estimate is ``ĥ ≈ h (1 + β)``:

        ln h ← ln ĥ − μ_h,      C_x ← C_x + v_h w wᵀ,      w = ∂x/∂ln h = (0, h ∂u/∂h, 0)

    (``u`` the depth fraction, :class:`~elastimap.identify.coords.FitCoords`; first order in β).  d and E
    do not move: unlike the image modes' mean (which the valley turns into a large move of d), the
    phantoms' mean depth error is a shift of h alone."""
    dv = disc.depth_shift()
    if dv is None:
        return x, Cx
    mu, var = dv
    h, dh_du = X.theta(x)[1], X.dtheta(x)[1, 1]  # h is linear in u at fixed d
    w = np.array([0.0, h / dh_du, 0.0])
    x = np.array(x, float)
    x[1] -= h * (1.0 - math.exp(-mu)) / dh_du  # h ← ĥ exp(−μ_h)
    return np.clip(x, lb, ub), Cx + var * np.outer(w, w)


#: an estimate of d or E within this fraction of the design box's limit (in mm or kPa) is on its edge: E's
#: contrast coordinate saturates at the stiff end, so 1e-3 of the box in it is about 2 kPa at 200 kPa
EDGE_REL = 0.01


def on_edge(x, th, lb, ub, prior: DesignPrior) -> list[str]:
    """The parameters of the estimate (fit coordinates ``x``, θ = ``th``) on the design box's edge: within
    1e-3 of the box in x, or (d, E) within :data:`EDGE_REL` of their limits."""
    tol = 1e-3 * (ub - lb)
    at = [q for j, q in enumerate(TARGETS) if x[j] <= lb[j] + tol[j] or x[j] >= ub[j] - tol[j]]
    for j, q, (a, b) in ((0, "d", prior.d_range), (2, "E", prior.E_range)):
        if q not in at and (th[j] <= a * (1 + EDGE_REL) or th[j] >= b / (1 + EDGE_REL)):
            at.append(q)
    return [q for q in TARGETS if q in at]


# ============================================================================ the fit
class ImageFit:
    """The maximum-likelihood fit of ``forward`` (with the other levels ``forward_alt``, a map or a
    list of maps, and the finer level ``forward_fine``) under ``config``; calling it on
    ``(image, sigma, theta0)`` returns a :class:`FitResult`.  See the module docstring."""

    def __init__(self, forward: Callable, forward_alt=None, forward_fine=None, config: FitConfig | None = None):
        self.config = config or FitConfig()
        self.forward, self.forward_fine = forward, forward_fine
        if forward_alt is None:
            self.alts = []
        else:
            self.alts = list(forward_alt) if isinstance(forward_alt, (list, tuple)) else [forward_alt]
        tangent = self.config.optimiser.tangent
        if tangent is None:
            tangent = bool(getattr(forward, "has_tangent", False))
            if self.config.fine == "direct" and forward_fine is not None:  # both maps' derivatives, or neither
                tangent = tangent and bool(getattr(forward_fine, "has_tangent", False))
        elif tangent and not getattr(forward, "has_tangent", False):
            raise UserError("tangent", "this forward map has no exact derivative (use central differences)")
        self.tangent = bool(tangent)

    def __call__(self, image, sigma, theta0) -> FitResult:
        """The fit of ``image`` (mm, ``(ny, nx)`` or flat) with per-pixel standard errors ``sigma``
        (mm, scalar or like ``image``) from ``theta0`` (d mm, h mm, E kPa): start, passes, then the
        model error, covariance and intervals at the estimate."""
        t0 = time.perf_counter()
        I, s_meas, shape, theta0 = self._inputs(image, sigma, theta0)
        prior = self.config.prior
        X = prior.coordinates(self.forward)
        lb, ub = X.box(prior.d_range, prior.E_range)
        model = FitModel(self.forward, self.alts, self.forward_fine, self.config.fine, self.tangent, X, I.size)
        noise = PixelNoise(s_meas, shape)

        # the start and the E scan: the map alone, σ_meas
        x0 = self._start(X, model, theta0, lb, ub)
        r0 = (model(x0, need_j=False) - I) / s_meas
        x0 = self._scan_E(model, I, s_meas, x0, r0, lb, ub)
        x, J, moving, msg = self._passes(X, model, noise, I, x0, lb, ub)
        model.measure(x)  # the model error at the estimate
        s_tot, s_mod = noise.sigma(model.delta)
        W = self._whiten(model, x, s_tot)
        J_raw = None
        if W.U is not None:  # the shared error's whitening differs from the pass's: a fresh Jacobian
            J_raw = self._jacobian(X, model, x, Whiten(np.ones_like(s_tot)), lb, ub)
            J = W(J_raw)
        elif self.tangent or J is None or moving:
            J = self._jacobian(X, model, x, W, lb, ub)
        r = W(model(x) - I)
        dof = max(I.size - 3, 1)
        chi2 = float(r @ r) / dof
        Cx = self._covariance(J, chi2, model.delta, W)
        disc = self.config.discrepancy
        if disc is not None:  # the model-form term: its marginal covariance at the estimate
            if shape is None:
                raise UserError("image", "a fit carrying a discrepancy needs the 2-D image (its modes are images)")
            Jx = J * s_tot[:, None] if J_raw is None else J_raw
            Cx, chi2 = self._marginal(model, I, s_tot, shape, x, Jx, W.U)
            x, Cx = depth_shift(X, x, Cx, disc, lb, ub)
        Gx = X.dtheta(x)
        th = X.theta(x)
        sd = np.sqrt(np.clip(np.diag(Gx @ Cx @ Gx.T), 0, None))
        relstd = np.array([sd[0] / th[0], sd[1] / th[1], sd[2]])
        lo_gauss, hi_gauss = interval95(X, x, Cx, np.ones(3), prior, lb, ub)
        calibrated = self.config.intervals == "calibrated" and disc is None  # the scales are the closed world's
        scale = scales_for(relstd, th, thickness=prior.thickness) if calibrated else np.ones(3)
        lo, hi = interval95(X, x, Cx, scale, prior, lb, ub)
        at = on_edge(x, th, lb, ub, prior)
        if disc is not None and "E" in at and prior.coords == "contrast":  # beyond the box along the valley
            lo, hi = valley_interval(X, x, lo, hi, prior, lb, ub)
            relstd[0] = max(relstd[0], (hi[0] - lo[0]) / (2 * Z95 * th[0]))
            relstd[2] = max(relstd[2], math.log(hi[2] / lo[2]) / (2 * Z95))
        big = np.abs(I) >= 0.1 * np.abs(I).max()
        me = float(np.sqrt(np.mean(s_mod[big] ** 2)) / np.sqrt(np.mean(s_meas[big] ** 2)))
        return FitResult(
            theta=th,
            theta0=theta0.copy(),
            relstd=relstd,
            lo=lo,
            hi=hi,
            chi2_red=chi2,
            chi2_red0=float(r0 @ r0) / dof,
            model_error=me,
            n_solves=model.n_eval,
            n_alt=model.n_alt,
            seconds=time.perf_counter() - t0,
            message="; ".join(msg),
            at_bound=at,
            n_fine=model.n_fine,
            moving=moving,  # empty when the fit converged (its last pass moved nothing by 0.2 sd)
            lo_gauss=lo_gauss,
            hi_gauss=hi_gauss,
            scale=scale,
            model_form=disc is not None,
        )

    def _marginal(self, model: FitModel, I, s_tot, shape, x, Jx, shared=None) -> tuple[np.ndarray, float]:
        """The covariance (x units) and χ² per degree of freedom of the estimate ``x`` under the model-form
        term (see the module docstring, 'model-form term'): the generalised least-squares information of
        the map's Jacobian ``Jx`` (mm per x unit, not whitened) with the discrepancy (and the ``shared``
        error's columns, :class:`FitConfig`) marginalised, its basis the map's image at ``x``, plus the
        discretisation's systematic part and the Birge factor."""
        cfg = self.config
        m0 = model(x)
        M = Marginal(I, s_tot.reshape(shape), m0.reshape(shape), float(cfg.pixel), cfg.discrepancy, shared=shared)
        st = M.step(m0, Jx, model.delta, birge=True)
        return st.cov, st.chi2 / st.dof

    @staticmethod
    def _inputs(image, sigma, theta0):
        """The image (flat), its pixel noise (flat), its 2-D shape (None for a flat image), θ₀; a
        :class:`~elastimap.errors.UserError` naming the bad one."""
        I = np.asarray(image, dtype=float)
        shape = I.shape if I.ndim == 2 else None
        I = I.ravel()
        if I.size == 0 or not np.isfinite(I).all():
            raise UserError("image", "must be a non-empty finite difference image")
        s_meas = np.broadcast_to(np.asarray(sigma, dtype=float), np.shape(image)).ravel().copy()
        if not (np.isfinite(s_meas).all() and (s_meas > 0).all()):
            raise UserError("sigma", "pixel noise must be finite and > 0")
        theta0 = np.asarray(theta0, dtype=float)
        if theta0.shape != (3,) or not np.isfinite(theta0).all() or theta0[2] <= 0:
            raise UserError("theta0", f"need a finite (d, h, E > 0) start (got {theta0})")
        return I, s_meas, shape, theta0

    def _start(self, X: FitCoords, model: FitModel, theta0, lb, ub) -> np.ndarray:
        """θ₀ clipped into the box (in x), the maps pinned there without correction or model error."""
        prior = self.config.prior
        pad = 1e-3 * (ub - lb)
        d_range, E_range = prior.d_range, prior.E_range
        th0 = np.clip(theta0, [d_range[0], -np.inf, E_range[0]], [d_range[1], np.inf, E_range[1]])
        x0 = np.clip(X.x(th0), lb + pad, ub - pad)
        model.pin(x0, correct=False, measure=False)
        return x0

    def _scan_E(self, model: FitModel, I, s_meas, x0, r0, lb, ub) -> np.ndarray:
        """A start's E can be far off (the d–E valley is long): scan e over the box at the start's
        (d, h) -- E-only evaluations, the map reuses its reference solve -- and start from the best."""
        e_scan = self.config.optimiser.e_scan
        if e_scan <= 1:
            return x0
        pad = 1e-3 * (ub - lb)
        best = float(r0 @ r0)
        for e in np.linspace(lb[2] + pad[2], ub[2] - pad[2], e_scan):
            xc = np.array([x0[0], x0[1], e])
            rc = (model(xc, need_j=False) - I) / s_meas
            if float(rc @ rc) < best:
                best, x0 = float(rc @ rc), xc
        return x0

    def _passes(self, X: FitCoords, model: FitModel, noise: PixelNoise, I, x, lb, ub):
        """The optimiser's passes from ``x``: (the estimate, the last pass's Jacobian, the parameters
        the last pass still moved, scipy's messages).

        Each pass starts from a fresh Jacobian (exact, or central differences), the reference meshes
        pinned and (from pass ``first`` on) the map corrected where it starts; the fit is accepted
        when such a pass moves no parameter by more than 0.2 of its standard deviation (from that
        Jacobian).  With a finer level pass 0 fits the cheaper map alone (σ_meas), so that the finer
        map is first evaluated near the answer.  The model error (the pixel weights) is measured
        where each pass starts -- with a finer level only where the first corrected pass starts, at
        pass 0's optimum and so already near the answer, and held for the later passes (one solve
        of each other level saved a pass; a fit without it starts pass 0 at θ₀, which can be far)."""
        opt = self.config.optimiser
        msg, J, moving = [], None, []
        corrected = self.forward_fine is not None
        first = 1 if corrected else 0  # the first corrected pass
        for k in range(opt.max_passes + first):
            model.pin(x, correct=k >= first, measure=k == first if corrected else True)
            s_tot, _ = noise.sigma(model.delta)
            W = self._whiten(model, x, s_tot)
            J = self._jacobian(X, model, x, W, lb, ub)

            def resid(z, W=W):
                return W(model(z, need_j=False) - I)

            xn, res = broyden_pass(resid, x, J, lb, ub, opt.max_nfev)
            msg.append(str(res.message))
            sd_x = np.sqrt(np.clip(np.diag(np.linalg.pinv(J.T @ J)), 0, None))
            moving = [q for j, q in enumerate(TARGETS) if abs(xn[j] - x[j]) > max(0.2 * sd_x[j], 1e-9)]
            x = xn
            if not moving and k >= first:
                break
        else:
            msg.append(f"{STILL_MOVING} after {opt.max_passes} passes")
        return x, J, moving, msg

    def _whiten(self, model: FitModel, x, s_tot) -> Whiten:
        """The pixels' whitening at ``x``: ``s_tot`` and, with a ``shared`` error (:class:`FitConfig`),
        its columns at the map's image there."""
        shared = self.config.shared
        return Whiten(s_tot, None if shared is None else shared(model(x)))

    def _jacobian(self, X: FitCoords, model: FitModel, x, W: Whiten, lb, ub) -> np.ndarray:
        """∂m/∂x whitened by ``W``: the map's exact derivative,
        ``[∂m/∂d, ∂m/∂h, E ∂m/∂E] ∂(d, h, ln E)/∂x`` (:meth:`FitCoords.dtheta`), where used; else
        central differences (one-sided at the box) with steps :attr:`Optimiser.fd`, E first (a map
        may reuse its reference solve while (d, h) stay)."""
        if self.tangent:
            jt = model.jacobian(x) * np.array([1.0, 1.0, X.theta(x)[2]])
            return W(jt @ X.dtheta(x))
        fd = self.config.optimiser.fd
        lo, hi = h_range(x[0], self.config.prior.thickness)
        st = np.array([fd[0], fd[1] / (hi - lo), fd[2] / X.dtheta(x)[2, 2]])  # fd[2] in ln E
        J = np.empty((model.n_pixels, 3))
        for j in (2, 0, 1):
            xp, xm = np.array(x, float), np.array(x, float)
            xp[j] += st[j]
            xm[j] -= st[j]
            if lb[j] <= xm[j] and xp[j] <= ub[j]:
                J[:, j] = (model(xp) - model(xm)) / (2 * st[j])
            elif xp[j] <= ub[j]:
                J[:, j] = (model(xp) - model(x)) / st[j]
            else:
                J[:, j] = (model(x) - model(xm)) / st[j]
        return W(J)

    @staticmethod
    def _covariance(J, chi2: float, delta: list, W: Whiten) -> np.ndarray:
        """``C_x = (JᵀJ)⁻¹ max(1, χ²_red) + Σ_k b_k b_kᵀ`` in x units: the discretisation error is one
        image, correlated over the pixels, so each level difference (measured at the estimate) enters
        through the estimator as a systematic shift ``b_k = (JᵀJ)⁻¹ Jᵀ W(δ_k)`` (``J`` whitened by ``W``)."""
        JtJi = np.linalg.pinv(J.T @ J)
        Cx = JtJi * max(1.0, chi2)
        for dl in delta:
            b = JtJi @ J.T @ W(dl)
            Cx = Cx + np.outer(b, b)
        return Cx


# ============================================================================ the public functions
def fit_image(
    image,
    sigma,
    theta0,
    forward: Callable,
    *,
    forward_alt: Callable | list | None = None,
    forward_fine: Callable | None = None,
    **config,
) -> FitResult:
    """Maximum-likelihood (d, h, E) of ``image`` (mm, ``(ny, nx)`` or flat) with per-pixel standard
    errors ``sigma`` (mm, scalar or like ``image``), starting from ``theta0`` (d mm, h mm, E kPa):
    :class:`ImageFit` of the maps under ``FitConfig.of(**config)``.

    ``forward(d, h, E)`` and ``forward_alt(d, h, E)`` return the difference image (see
    :func:`~elastimap.identify.forward_maps.image_of`) of the map and of its neighbouring mesh
    level (maps with a ``pin(d, h)`` method returning a map with a hashable ``key`` are pinned at the
    start of every pass, see :class:`~elastimap.identify.forward_maps.ForwardMap`).  ``forward_alt``
    may be a list of maps (several levels): each difference enters σ_model² and the systematic
    covariance as its own term.  Without ``forward_alt`` the model error is taken as zero (say so
    when reporting).  ``forward_fine``: a finer level of the same map; ``forward_alt`` should then
    be the finer map's neighbouring level (its error is what the corrected map carries).

    ``config`` (:meth:`FitConfig.of`): ``d_range``, ``E_range``, ``thickness``, ``coords``,
    ``E_tissue`` (the prior), ``fd``, ``max_nfev``, ``max_passes``, ``e_scan``, ``tangent`` (the
    optimiser), ``fine`` (``"correct"`` or ``"direct"``) and ``intervals`` (``"gauss"``, the
    default here, or ``"calibrated"``, for the maps of
    :func:`~elastimap.identify.forward_maps.default_intervals`)."""
    return ImageFit(forward, forward_alt, forward_fine, FitConfig.of(**config))(image, sigma, theta0)


def fit_forward(
    image, sigma, theta0, mesh: str = "coarse", geometry: str | None = None, correct: str | None = None, **config
) -> FitResult:
    """:func:`fit_image` on the solver's maps at ``mesh`` (:func:`~elastimap.identify.forward_maps.fit_maps`):
    its model error measured against the neighbouring level; with ``correct`` (a finer level) the
    map is defect-corrected by that level and its error measured against ``correct``'s neighbouring
    level.  ``intervals`` (in ``config``) defaults to
    :func:`~elastimap.identify.forward_maps.default_intervals`."""
    maps = fit_maps(mesh, correct, geometry)
    config.setdefault("intervals", maps.intervals)
    return fit_on_maps(image, sigma, theta0, maps, **config)


def fit_on_maps(image, sigma, theta0, maps, **config) -> FitResult:
    """:func:`fit_image` with the maps of ``maps`` (:class:`~elastimap.identify.forward_maps.FitMaps`):
    its map, the neighbouring level's (the model error) and the correcting one."""
    return fit_image(
        image, sigma, theta0, maps.forward, forward_alt=maps.forward_alt, forward_fine=maps.forward_fine, **config
    )
