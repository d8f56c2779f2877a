r"""Model-form error: the discrepancy between elastimap's forward image and the world's, learned from
a lab's calibration phantoms and carried into a fit as an informative prior.

Why a term of its own.  The fit's error budget (:mod:`elastimap.identify.fit`) holds the pixel
noise and elastimap's own discretisation (the difference of two of its mesh levels).  Another faithful
model of the same sensor -- and every real sensor -- differs from elastimap by more: 1–3 % of the
difference image, structured (larger for small, stiff, deep inclusions), smooth over the image.  Left
out, a 2 % difference in the image's height moves a stiff inclusion's E along the flat d–E valley to
the design edge, with an interval that misses.

The formulation (Kennedy & O'Hagan, *J. R. Stat. Soc. B* 63 (2001) 425, with the informative prior
Brynjarsdóttir & O'Hagan, *Inverse Problems* 30 (2014) 114007, show is needed: a discrepancy with a
vague prior is confounded with the physical parameters, which then cannot be learnt)::

    I(x) = m(x; θ) + δ(x; θ) + ε(x)                        (mm; x a pixel, θ = (d mm, h mm, E kPa))
    δ(x; θ) = Σ_k β_k φ_k(x; θ) + a(x; θ) η(x),   β ~ N(μ, diag τ²),
    η ~ GP(0, ρ² exp(−|x − x'|² / 2ℓ²))
    ε(x) ~ N(0, σ_meas(x)²)

* ``m`` the forward difference image, ``ε`` the measured pixel noise (from the frames' scatter);
* ``φ_k`` a few **modes of the image itself** (:data:`MODES`), so the discrepancy is smooth over the
  image and grows with the inclusion's signal by construction: ``amplitude`` ``φ = m`` (a relative
  error of the image's height: a stiffer or softer world), ``width`` ``φ = r ∂m/∂r`` (the first-order
  change of ``m(x / (1 + λ))``: the world spreads the bump wider or narrower) -- the height and width
  of the bump, the two things two faithful models of the same press disagree on first (optional
  ``tail``: a flank the two do not give, :func:`modes`);
* the **depth mode** ``φ = h ∂m/∂h`` (:data:`DEPTH`; learnt where the map has an exact derivative,
  :data:`DEPTH_MODES`, :func:`forward_images`): a relative error ``β_h`` of the inclusion's depth,
  ``m(d, h (1 + β_h), E)``.  It is the fit's own derivative along h, so no image tells it from h: a fit
  carries it as a shift of ``ln h`` by ``−μ_h`` and ``τ_h²`` added to its variance, neither d nor E move
  (:meth:`Discrepancy.depth_shift`, :func:`elastimap.identify.fit.depth_shift`).  On the SYNTHETIC variant
  world (elastimap's coarse remeshed contact solve against the tiny morphed map) the nine phantoms gave
  ``μ_h`` −0.65 %, ``τ_h`` 1.6 % against the closed fit's own h errors of −3.1 … +0.6 % (mean −1.2 %), and
  17–38 % of ``h ∂m/∂h`` lies outside the amplitude and width modes, so they cannot hold it;
* ``a η`` what the modes leave: a fraction ``ρ`` of the local signal envelope ``a`` (``|m|`` smoothed
  over :data:`ENVELOPE_PX` pixels), correlated over ``ℓ`` mm (a smooth field: left white, its pull on
  the parameters would average down over the image's hundreds of pixels, which a model-form
  difference does not);
* ``μ, τ, ρ, ℓ``: learnt at run time from the lab's calibration phantoms (:func:`learn`), whose (d, h, E)
  are known, so that their residual images ``R_i = I_i − m(θ_i)`` **are** samples of ``δ + ε``:
  per phantom the modes' coefficients ``β̂_i`` by weighted least squares, then ``μ`` their mean and
  ``τ²`` their spread less what the noise explains, each shrunk toward a prior scale ``τ₀`` by an
  inverse-gamma prior of ``ν₀`` pseudo-phantoms, ``ℓ`` the most likely of :data:`ELL_GRID`
  (:data:`PRIOR_SCALE`, :data:`PRIOR_WEIGHT`; the only
  number here not learnt from the lab's phantoms -- its scale is that of the independent references
  of the same sensor, ``shared/devdata/independent-fem`` and its ``calculix.csv``, 1–3 %, stated as such).

What the fit does with it.  Marginalising ``β`` and ``η`` the pixels' covariance is
``Σ = D + Φ (T + V_μ) Φᵀ``, ``D = diag σ_meas² + ρ² A K_ℓ A`` (``A = diag a``, ``T = diag τ²``, ``V_μ``
the uncertainty of ``μ``), with mean ``Φ μ``.  Equivalently (what :func:`augment` builds on the
residuals whitened by ``D``'s Cholesky factor, :meth:`Discrepancy.whitener`) the
fit estimates ``β`` beside θ with the prior as ``K`` extra residual rows ``L⁻¹(β − μ)``: the
Gauss–Newton covariance of θ is then the marginal one, so a parameter confounded with a mode (a stiff
inclusion's E with the amplitude) gets the interval the prior allows -- to first order: a nonlinear fit
minimising this marginal misfit walked along the d–E valley on the dev set (docs/model-form.md, 'The
nonlinear check'), so the product's fit (:mod:`elastimap.identify.fit`) keeps the closed world's
estimate and takes only its covariance from here (:class:`Marginal`).  The informativeness
is what Brynjarsdóttir & O'Hagan ask for: ``τ`` is the spread over the lab's own phantoms, not a
free function.

Units: images and σ in mm; ``β`` dimensionless (a fraction of the image's mode), ``ρ`` a fraction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from elastimap.errors import UserError

#: the image modes of the discrepancy (:func:`modes`), in this order; ``tail`` is available (ALL_MODES)
MODES = ("amplitude", "width")
ALL_MODES = ("amplitude", "width", "tail")
#: the depth mode ``φ = h ∂m/∂h`` (:func:`modes` with the map's derivative): a relative error of the
#: inclusion's depth, a pure shift of h in a fit (:meth:`Discrepancy.depth_shift`)
DEPTH = "depth"
#: what ``camera calibrate`` learns: the image modes and the depth mode
DEPTH_MODES = (*MODES, DEPTH)
#: Gaussian σ (pixels) of the signal envelope ``a = G * |m|`` that scales the per-pixel remainder η
ENVELOPE_PX = 2.0
#: the prior scale ``τ₀`` of each mode's coefficient and ``ρ₀`` of the remainder (fractions): the size of
#: the model-form difference between elastimap and the independent references of the same sensor (the
#: README of shared/devdata/independent-fem: "about 1–3 % in the image features"; calculix.csv moves
#: its finest refinement by ≤ 0.7 %).  A prior's scale only, never a correction: the lab's phantoms
#: decide (:func:`learn`)
PRIOR_SCALE = {"amplitude": 0.02, "width": 0.02, "tail": 0.02, "depth": 0.02, "remainder": 0.01}
#: a learnt term beyond this many times its prior scale is no model-form difference (:meth:`Discrepancy.beyond`);
#: fixed in advance (a 3-sigma rule on the prior scale), not fitted to any data set
BEYOND = 3.0
#: ``ν₀``: how many phantoms' worth the prior scale weighs against the lab's phantoms
PRIOR_WEIGHT = 2.0
#: the remainder's correlation lengths (mm) :func:`learn` chooses from by the calibration phantoms'
#: likelihood (0: white).  At most 2 mm, about the element size under the probe: with 4 mm allowed the
#: likelihood chose it on the variant world (elastimap's remeshing `default` level, sized by d, contact,
#: against the morphed `coarse` map; ``python -m elastimap.workflows.studies.modelform --world-level
#: default --model-mesh coarse --alt-mesh tiny``), and the generalised least squares then trusted the
#: image's fine scale, where the map's own mesh is wrong: coverage of d/h/E 57/55/57 % against
#: 100/100/100 % with ℓ ≤ 2 mm (docs/model-form.md, 'Choosing the term's settings')
ELL_GRID = (0.0, 1.0, 2.0)
#: the pixels the choice of ℓ looks at: envelope at least this fraction of its peak
SUPPORT = 0.05


def _grid(shape, pixel: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates (mm) of an image on a footprint centred on 0 (rows y, columns x)."""
    ny, nx = shape
    y = (np.arange(ny) - (ny - 1) / 2) * pixel
    x = (np.arange(nx) - (nx - 1) / 2) * pixel
    return np.meshgrid(y, x, indexing="ij")


def modes(m: np.ndarray, pixel: float, which: tuple[str, ...] = MODES, depth=None) -> np.ndarray:
    """The discrepancy's modes ``Φ`` ``(p, K)`` of a forward difference image ``m`` ``(ny, nx)`` (mm)
    with square pixels of ``pixel`` mm, flattened like ``m.ravel()``:

    * ``amplitude``: ``m``;
    * ``width``: ``r ∂m/∂r = x ∂m/∂x + y ∂m/∂y`` (central differences): ``m(x/(1+λ)) ≈ m − λ r ∂m/∂r``;
    * ``tail`` (not in :data:`MODES`): ``m (r/R)⁴`` (``R`` half the footprint) less its projection on
      the other modes, scaled to the norm of ``m`` (a flank the height and width do not give; for a
      bump ``r ∂m/∂r`` is already close to ``m r²``, so a quadratic gain would repeat the width);
    * ``depth`` (:data:`DEPTH`, not in :data:`MODES`): ``h ∂m/∂h``, given as ``depth`` (mm, the map's
      derivative: the image alone does not hold it): ``m(h (1 + β)) ≈ m + β h ∂m/∂h``, a relative
      error of the inclusion's depth.
    """
    m = np.asarray(m, dtype=float)
    if m.ndim != 2:
        raise UserError("image", f"the forward image must be 2-D (got shape {m.shape})")
    unknown = [w for w in which if w not in (*ALL_MODES, DEPTH)]
    if unknown:
        raise UserError("modes", f"must be among {', '.join((*ALL_MODES, DEPTH))} (got {', '.join(unknown)})")
    if DEPTH in which and (depth is None or np.size(depth) != m.size):
        raise UserError("depth", "the depth mode needs the map's h ∂m/∂h image (mm), of the image's shape")
    Y, X = _grid(m.shape, pixel)
    cols = []
    for w in which:
        if w == "amplitude":
            cols.append(m)
        elif w == DEPTH:
            cols.append(np.asarray(depth, float).reshape(m.shape))
        elif w == "width":
            gy, gx = np.gradient(m, pixel)
            cols.append(X * gx + Y * gy)
        else:
            R2 = (0.5 * m.shape[1] * pixel) ** 2
            cols.append(m * ((X * X + Y * Y) / R2) ** 2)
    P = np.column_stack([c.ravel() for c in cols])
    if "tail" in which:  # Gram–Schmidt against the other modes, scaled to the norm of m
        j = which.index("tail")
        others = np.delete(P, j, axis=1)
        t = P[:, j] - others @ np.linalg.lstsq(others, P[:, j], rcond=None)[0] if others.size else P[:, j]
        tt, mm = float(t @ t), float(np.sum(m * m))
        P[:, j] = t * math.sqrt(mm / tt) if tt > 0 else t
    return P


def envelope(m: np.ndarray, px: float = ENVELOPE_PX) -> np.ndarray:
    """The signal envelope ``a = G_px * |m|`` (mm, flattened): where the image is, smooth, never zero
    where a signed image crosses zero."""
    return ndimage.gaussian_filter(np.abs(np.asarray(m, dtype=float)), px, mode="nearest").ravel()


def correlation_factors(shape, pixel: float, ell: float) -> tuple[np.ndarray, np.ndarray]:
    """``(K_y, K_x)``: the Kronecker factors of :func:`correlation` (``ℓ > 0``), the 1-D Gaussian
    correlations of the rows' and the columns' pixel centres (mm): ``K_ℓ = K_y ⊗ K_x``."""

    def k1(n):
        t = np.arange(n) * pixel
        return np.exp(-0.5 * ((t[:, None] - t[None, :]) / ell) ** 2)

    ny, nx = shape
    return k1(ny), k1(nx)


def correlation(shape, pixel: float, ell: float) -> np.ndarray:
    """``K_ℓ`` ``(p, p)``: the Gaussian correlation ``exp(−|x − x'|² / 2ℓ²)`` of the pixel centres (mm) of
    an image of ``shape`` (flattened like ``ravel``; the identity for ``ℓ = 0``)."""
    if ell <= 0:
        return np.eye(shape[0] * shape[1])
    return np.kron(*correlation_factors(shape, pixel, ell))


class Whitener:
    """``L⁻¹ v`` for ``D = L Lᵀ = diag σ² + ρ² A K_ℓ A`` (mm²): the noise and the remainder, dense where
    ``ℓ > 0`` (one Cholesky factorisation, ~1 s for 50 x 50 pixels), diagonal otherwise."""

    def __init__(self, sigma: np.ndarray, env: np.ndarray, rho: float, ell: float, shape, pixel: float):
        from scipy import linalg

        self.dense = ell > 0 and rho > 0
        if self.dense:
            D = correlation(shape, pixel, ell) * np.outer(rho * env, rho * env)
            D[np.diag_indices_from(D)] += sigma**2
            self.L = linalg.cholesky(D, lower=True)
            self.logdet = 2.0 * float(np.sum(np.log(np.diag(self.L))))
        else:
            self.s = np.hypot(sigma, rho * env)
            self.logdet = 2.0 * float(np.sum(np.log(self.s)))

    def __call__(self, v: np.ndarray) -> np.ndarray:
        from scipy import linalg

        v = np.asarray(v, float)
        if self.dense:
            return linalg.solve_triangular(self.L, v, lower=True)
        return v / (self.s if v.ndim == 1 else self.s[:, None])


@dataclass(frozen=True)
class Discrepancy:
    """The learnt model-form error: ``β ~ N(mean, diag(tau²) + mean_cov)`` on :attr:`modes`, and the
    remainder's fraction ``rho`` of the signal envelope (see the module docstring).

    ``n_phantoms``: how many phantoms it was learnt from (0: the prior alone); ``source``: what it
    was learnt from, in words (reports print it)."""

    modes: tuple[str, ...] = MODES
    mean: np.ndarray = field(default_factory=lambda: np.zeros(len(MODES)))
    tau: np.ndarray = field(default_factory=lambda: np.array([PRIOR_SCALE[k] for k in MODES]))
    mean_cov: np.ndarray = field(default_factory=lambda: np.zeros((len(MODES), len(MODES))))
    rho: float = PRIOR_SCALE["remainder"]
    n_phantoms: int = 0
    source: str = "prior scale only (independent references of the same sensor, 1–3 %)"
    ell: float = 2.0  # mm, the remainder's correlation length

    def __post_init__(self):
        k = len(self.modes)
        for name, v, shape in (("mean", self.mean, (k,)), ("tau", self.tau, (k,)), ("mean_cov", self.mean_cov, (k, k))):
            a = np.asarray(v, dtype=float)
            if a.shape != shape or not np.isfinite(a).all():
                raise UserError(name, f"must be finite of shape {shape} (got {a.shape})")
            object.__setattr__(self, name, a)
        if (self.tau < 0).any() or not (math.isfinite(self.rho) and self.rho >= 0):
            raise UserError("tau", "the discrepancy's scales must be >= 0")
        if not (math.isfinite(self.ell) and self.ell >= 0):
            raise UserError("ell", f"the remainder's correlation length must be >= 0 mm (got {self.ell})")

    @classmethod
    def none(cls) -> Discrepancy:
        """No model-form error (the closed world: elastimap's own solver made the data)."""
        k = len(MODES)
        return cls(MODES, np.zeros(k), np.zeros(k), np.zeros((k, k)), 0.0, 0, "none (closed world)", 0.0)

    def beyond(self, factor: float = BEYOND) -> list[str]:
        """The terms whose learnt size exceeds ``factor`` times their prior scale (:data:`PRIOR_SCALE`): a
        mode's mean or spread, or the remainder.  Non-empty: the phantoms differ from elastimap by more
        than a model-form difference of two faithful models -- a physical effect (run ``gap diagnose``)
        or a mislabelled phantom, which a fit should not absorb as model-form error."""
        out = []
        for k, w in enumerate(self.modes):
            lim = factor * PRIOR_SCALE[w]
            if abs(self.mean[k]) > lim or self.tau[k] > lim:
                out.append(w)
        if self.rho > factor * PRIOR_SCALE["remainder"]:
            out.append("remainder")
        return out

    @property
    def prior_cov(self) -> np.ndarray:
        """Covariance of ``β`` for a new lesion: the spread over phantoms plus the mean's uncertainty."""
        return np.diag(self.tau**2) + self.mean_cov

    def image_term(self) -> Discrepancy:
        """The term without its depth mode (:data:`DEPTH`): what the pixels' covariance carries (the modes
        built from the image alone); the depth mode enters a fit as a shift of h (:meth:`depth_shift`)."""
        if DEPTH not in self.modes:
            return self
        keep = [k for k, w in enumerate(self.modes) if w != DEPTH]
        sub = np.ix_(keep, keep)
        mods = tuple(self.modes[k] for k in keep)
        return Discrepancy(
            mods, self.mean[keep], self.tau[keep], self.mean_cov[sub], self.rho, self.n_phantoms, self.source, self.ell
        )

    def depth_shift(self) -> tuple[float, float] | None:
        """``(μ_h, v_h)``: the mean and variance of the depth mode's coefficient (a relative error of the
        inclusion's depth, ``m(h (1 + β))``), or None without a depth mode.  Because ``h ∂m/∂h`` is the
        fit's own derivative along h, ``m(θ) + β h ∂m/∂h = m(d, h (1 + β), E)`` to first order: marginalising
        ``β ~ N(μ_h, v_h)`` (Kennedy & O'Hagan's posterior given the phantoms) shifts the estimate's
        ``ln h`` by ``−μ_h`` and adds ``v_h`` to its variance, and moves neither d nor E
        (:mod:`elastimap.identify.fit`, 'model-form term')."""
        if DEPTH not in self.modes:
            return None
        k = self.modes.index(DEPTH)
        return float(self.mean[k]), float(self.prior_cov[k, k])

    def basis(self, m: np.ndarray, pixel: float, depth=None) -> np.ndarray:
        """The modes ``Φ`` ``(p, K)`` at the forward image ``m`` (:func:`modes`; ``depth`` the map's
        ``h ∂m/∂h`` where the term has a depth mode)."""
        return modes(m, pixel, self.modes, depth)

    def remainder_sd(self, m: np.ndarray) -> np.ndarray:
        """Per-pixel sd of the remainder η (mm, flattened): ``ρ a``."""
        return self.rho * envelope(m)

    def mean_image(self, m: np.ndarray, pixel: float) -> np.ndarray:
        """The discrepancy's expected image ``Φ μ`` (mm, flattened)."""
        return self.basis(m, pixel) @ self.mean

    def sd_image(self, m: np.ndarray, pixel: float) -> np.ndarray:
        """Marginal per-pixel sd of δ (mm, flattened): ``sqrt(diag(Φ C Φᵀ) + ρ² a²)``."""
        P = self.basis(m, pixel)
        v = np.einsum("pk,kl,pl->p", P, self.prior_cov, P)
        return np.sqrt(np.clip(v, 0, None) + self.remainder_sd(m) ** 2)

    def covariance(self, m: np.ndarray, pixel: float, sigma) -> np.ndarray:
        """The pixels' full covariance ``diag σ² + ρ² A K_ℓ A + Φ C Φᵀ`` (mm², ``(p, p)``; tests -- a fit
        uses :meth:`whitener` and :func:`augment`)."""
        P = self.basis(m, pixel)
        a = self.remainder_sd(m)
        s2 = np.broadcast_to(np.asarray(sigma, float), np.shape(m)).ravel() ** 2
        return np.diag(s2) + correlation(np.shape(m), pixel, self.ell) * np.outer(a, a) + P @ self.prior_cov @ P.T

    def whitener(self, m: np.ndarray, pixel: float, sigma) -> Whitener:
        """The whitening of the noise and the remainder at the forward image ``m`` (:class:`Whitener`)."""
        m = np.asarray(m, float)
        return Whitener(_sigma(sigma, m.shape), envelope(m), self.rho, self.ell, m.shape, pixel)

    def to_dict(self) -> dict:
        return {
            "modes": list(self.modes),
            "mean": self.mean.tolist(),
            "tau": self.tau.tolist(),
            "mean_cov": self.mean_cov.tolist(),
            "rho": self.rho,
            "n_phantoms": self.n_phantoms,
            "source": self.source,
            "ell": self.ell,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Discrepancy:
        try:
            return cls(
                tuple(d["modes"]),
                np.asarray(d["mean"], float),
                np.asarray(d["tau"], float),
                np.asarray(d["mean_cov"], float),
                float(d["rho"]),
                int(d.get("n_phantoms", 0)),
                str(d.get("source", "")),
                float(d.get("ell", 0.0)),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise UserError("discrepancy", f"not a model-form error record ({exc})") from exc


def _sigma(sigma, shape) -> np.ndarray:
    s = np.broadcast_to(np.asarray(sigma, dtype=float), shape).ravel()
    if not (np.isfinite(s).all() and (s > 0).all()):
        raise UserError("sigma", "pixel noise must be finite and > 0")
    return s


@dataclass(frozen=True)
class PhantomFit:
    """One calibration phantom's residual on the modes: ``beta`` (weighted least squares), its noise
    covariance ``cov`` and the remainder ``rem`` (mm, flattened) with the noise ``sigma`` it carries."""

    beta: np.ndarray
    cov: np.ndarray
    rem: np.ndarray
    sigma: np.ndarray
    env: np.ndarray
    leverage: np.ndarray


def project(residual, m, sigma, pixel: float, which: tuple[str, ...] = MODES, depth=None) -> PhantomFit:
    """Weighted least squares of a residual image ``R = I − m(θ)`` (mm) on the modes of ``m`` (``depth``
    its ``h ∂m/∂h`` for the depth mode): ``β̂ = (ΦᵀWΦ)⁻¹ΦᵀW R``, ``W = diag σ⁻²``; covariance
    ``(ΦᵀWΦ)⁻¹`` (what the noise alone puts in β̂)."""
    m = np.asarray(m, float)
    R = np.asarray(residual, float).ravel()
    s = _sigma(sigma, m.shape)
    P = modes(m, pixel, which, depth)
    A = P / s[:, None]
    C = np.linalg.pinv(A.T @ A)
    beta = C @ (A.T @ (R / s))
    lev = np.einsum("pk,kl,pl->p", A, C, A)  # hat matrix diagonal
    return PhantomFit(beta, C, R - P @ beta, s, envelope(m), lev)


def learn(
    residuals,
    models,
    sigmas,
    pixel: float,
    *,
    which: tuple[str, ...] = MODES,
    prior_scale: dict | None = None,
    prior_weight: float = PRIOR_WEIGHT,
    ell_grid: tuple[float, ...] = ELL_GRID,
    source: str = "",
    depths=None,
) -> Discrepancy:
    """The model-form error of a lab's calibration phantoms: residual images ``R_i = I_i − m(θ_i)``
    (mm, the measured minus elastimap's image at the phantom's known (d, h, E)), the forward images
    ``m_i`` and the measured pixel noise ``σ_i`` (mm).

    Per mode ``k``: ``μ_k`` the mean of ``β̂_ik`` (:func:`project`); the spread less the noise,
    ``s_k² = Σ_i ((β̂_ik − μ_k)² − V_i,kk) / (n − 1)`` (method of moments, floored at 0), shrunk to the
    prior scale ``τ₀`` (:data:`PRIOR_SCALE`) by an inverse-gamma prior of ``ν₀`` = ``prior_weight``
    pseudo-phantoms: ``τ_k² = (ν₀ τ₀² + (n − 1) s_k²) / (ν₀ + n − 1)``.  ``μ``'s own uncertainty
    ``V_μ = (diag τ² + mean V_i) / n`` enters a new lesion's prior (:attr:`Discrepancy.prior_cov`).
    The remainder: ``ρ² = (ν₀ ρ₀² + n ρ̂²) / (ν₀ + n)``, ``ρ̂² = max(0, Σ_i Σ_x (rem² − σ² (1 − lev))) /
    Σ_i Σ_x a²`` (the remainder's energy beyond the noise per unit envelope energy).  One phantom: ``μ``
    is held at 0 (no spread can be measured) and ``τ`` is the prior's scale widened by its ``β̂``.
    The remainder's correlation length ``ℓ``: the most likely of ``ell_grid`` (mm) for the remainders
    on the pixels where the image is (envelope ≥ :data:`SUPPORT` of its peak; :func:`_remainder_loglik`).
    ``depths``: the map's ``h ∂m/∂h`` (mm) at each phantom, needed when ``which`` holds the depth mode
    (:data:`DEPTH_MODES`)."""
    ps = dict(PRIOR_SCALE, **(prior_scale or {}))
    residuals, models, sigmas = list(residuals), list(models), list(sigmas)
    n = len(residuals)
    depths = [None] * n if depths is None else list(depths)
    if n == 0 or len(models) != n or len(sigmas) != n or len(depths) != n:
        raise UserError("phantoms", "need at least one calibration phantom (a residual, image and noise each)")
    if not (math.isfinite(prior_weight) and prior_weight > 0):
        raise UserError("prior_weight", f"must be a finite number > 0 (got {prior_weight})")
    rho = ps["remainder"]
    for _ in range(3):  # the modes' weights hold the remainder, whose size the remainders measure
        d = _learn_once(residuals, models, sigmas, depths, pixel, which, ps, prior_weight, rho)
        if abs(d.rho - rho) <= 0.02 * max(rho, 1e-12):
            break
        rho = d.rho
    fits = [project(R, m, sg, pixel, which, dp) for R, m, sg, dp in zip(residuals, models, sigmas, depths, strict=True)]
    ell = max(ell_grid, key=lambda e: _remainder_loglik(fits, models, d.rho, e, pixel))
    return Discrepancy(d.modes, d.mean, d.tau, d.mean_cov, d.rho, n, source or f"{n} calibration phantom(s)", ell)


def _remainder_loglik(fits, models, rho: float, ell: float, pixel: float) -> float:
    """Σ_i log N(rem_i; 0, diag σ_i² + ρ² A_i K_ℓ A_i): how likely the calibration phantoms' remainders
    are under a correlation length ``ell``."""
    from scipy import linalg

    total = 0.0
    for f, m in zip(fits, models, strict=True):
        m = np.asarray(m, float)
        on = f.env >= SUPPORT * f.env.max()  # where the image is: outside, the remainder is noise alone
        a = rho * f.env[on]
        D = (correlation(m.shape, pixel, ell)[np.ix_(on, on)] if ell > 0 else np.eye(int(on.sum()))) * np.outer(a, a)
        D[np.diag_indices_from(D)] += f.sigma[on] ** 2
        L = linalg.cholesky(D, lower=True)
        z = linalg.solve_triangular(L, f.rem[on], lower=True)
        total -= 0.5 * float(z @ z) + float(np.sum(np.log(np.diag(L))))
    return total


def _learn_once(residuals, models, sigmas, depths, pixel, which, ps, prior_weight, rho) -> Discrepancy:
    """:func:`learn` with the modes weighted by ``σ² + ρ² a²`` for a given remainder fraction ``ρ``; the
    remainder's own estimate is of the noise ``σ`` alone."""
    fits = []
    for R, m, s, dp in zip(residuals, models, sigmas, depths, strict=True):
        m = np.asarray(m, float)
        w = np.hypot(_sigma(s, m.shape), rho * envelope(m))
        f = project(R, m, w.reshape(m.shape), pixel, which, dp)
        fits.append(PhantomFit(f.beta, f.cov, f.rem, _sigma(s, m.shape), f.env, f.leverage))
    n = len(fits)
    B = np.array([f.beta for f in fits])
    V = np.array([np.diag(f.cov) for f in fits])
    tau0 = np.array([ps[w] for w in which])
    if n >= 2:
        mu = B.mean(axis=0)
        s2 = np.clip(np.sum((B - mu) ** 2 - V * (n - 1) / n, axis=0) / (n - 1), 0, None)
        tau2 = (prior_weight * tau0**2 + (n - 1) * s2) / (prior_weight + n - 1)
        mean_cov = (np.diag(tau2) + np.diag(V.mean(axis=0))) / n
    else:
        mu = np.zeros(len(which))
        tau2 = (prior_weight * tau0**2 + np.clip(B[0] ** 2 - V[0], 0, None)) / (prior_weight + 1)
        mean_cov = np.zeros((len(which), len(which)))
    num = sum(float(np.sum(f.rem**2 - f.sigma**2 * (1 - f.leverage))) for f in fits)
    den = sum(float(np.sum(f.env**2)) for f in fits)
    rho2_hat = max(num / den, 0.0) if den > 0 else 0.0
    rho2 = (prior_weight * ps["remainder"] ** 2 + n * rho2_hat) / (prior_weight + n)
    return Discrepancy(tuple(which), mu, np.sqrt(tau2), mean_cov, math.sqrt(rho2), n)


def augment(r_w, J_w, P_w, disc: Discrepancy, beta=None):
    """The augmented least-squares problem of a fit that carries the discrepancy: with the whitened
    residual ``r_w = L⁻¹(m(θ) − I)`` ``(p,)``, Jacobian ``J_w = L⁻¹ ∂m/∂x`` ``(p, n)`` and modes
    ``P_w = L⁻¹ Φ`` ``(p, K)``, all whitened by the noise and the remainder (:meth:`Discrepancy.whitener`), returns
    ``(r_a, J_a)`` of the unknowns ``(x, β)``::

        r_a = [ r_w + P_w β ;  L⁻¹ (β − μ) ],   J_a = [ J_w  P_w ; 0  L⁻¹ ],   L Lᵀ = C (prior_cov)

    (the sign: the discrepancy is part of the model the data are compared with, ``m + Φβ ≈ I``).
    Minimising ``|r_a|²`` over (x, β) is the marginal generalised least squares of x under
    ``Σ = D + Φ C Φᵀ`` (``D = L Lᵀ``) with mean ``Φ μ``, and ``(J_aᵀJ_a)⁻¹``'s x block its covariance.  ``beta``:
    the current β (default ``μ``).  Modes with zero prior variance are dropped (a closed world)."""
    C = disc.prior_cov
    keep = np.diag(C) > 0
    mu = disc.mean[keep]
    b = mu if beta is None else np.asarray(beta, float)[keep]
    P = np.asarray(P_w, float)[:, keep]
    Li = np.linalg.inv(np.linalg.cholesky(C[np.ix_(keep, keep)])) if keep.any() else np.zeros((0, 0))
    n = np.shape(J_w)[1]
    r_a = np.concatenate([np.asarray(r_w, float) + P @ b, Li @ (b - mu)])
    J_a = np.block([[np.asarray(J_w, float), P], [np.zeros((Li.shape[0], n)), Li]])
    return r_a, J_a, keep


def _inverse(H: np.ndarray, rcond: float = 1e-12) -> np.ndarray:
    """``H⁻¹`` of a symmetric information matrix with its eigenvalues floored at ``rcond`` x the largest: a
    direction the data (and the prior) do not inform gets a variance ``1/rcond`` times the best-told one's
    -- not identifiable -- where a pseudo-inverse would give it none."""
    if H.size == 0:
        return np.zeros_like(H)
    lam, V = np.linalg.eigh(0.5 * (H + H.T))
    lam = np.clip(lam, rcond * max(float(lam.max()), 1e-300), None)
    return (V / lam) @ V.T


@dataclass(frozen=True)
class LinearFit:
    """One Gauss–Newton step of a fit linearised at ``x0``: the step ``dx``, its covariance ``cov``
    (the marginal one with a discrepancy), the modes' coefficients ``beta`` and ``chi2`` the
    augmented misfit after the step, over ``dof`` pixels less parameters."""

    dx: np.ndarray
    cov: np.ndarray
    beta: np.ndarray
    chi2: float
    dof: int


class Marginal:
    """The marginal misfit of an image under the discrepancy, its basis held fixed: the measured
    ``image`` (mm), its pixel noise ``sigma`` (mm) and the image ``basis_image`` (mm, 2-D) the modes and
    the remainder's envelope are built from, whitened once (one Cholesky factorisation of ``D``).

    :meth:`step` is the generalised least-squares step of a fit linearised at a forward image ``m``
    with Jacobian ``J`` ``(p, n)`` (mm per unit of the fit's coordinates):
    ``min_(z, β) |L_D⁻¹(m + J z + Φ β − I)|² + |L_C⁻¹(β − μ)|²`` (:func:`augment`), whose minimum is
    the marginal ``χ²`` of ``m`` over the directions ``J`` and the modes (the depth mode only with
    ``depth``, the map's ``h ∂m/∂h``; else :meth:`Discrepancy.image_term`).  Holding the basis fixed
    matters when misfits at several points are compared: a covariance that grows with the trial image
    lowers ``rᵀΣ⁻¹r`` where the image is larger, and a fit would drift there (the log-determinant
    that would balance it is not in a least-squares misfit).

    ``shared``: further error columns ``U`` ``(p, K)`` (mm) with coefficients ``γ ~ N(0, I)`` (e.g. the
    flat field's press uncertainty, :class:`elastimap.camera.deflection.PressTerm`), marginalised beside
    the modes: ``Σ = D + Φ C Φᵀ + U Uᵀ``."""

    def __init__(
        self, image, sigma, basis_image, pixel: float, disc: Discrepancy | None = None, depth=None, shared=None
    ):
        mb = np.asarray(basis_image, float)
        self.I = np.asarray(image, float).ravel()
        self.disc = disc or Discrepancy.none()
        if depth is None:  # without the map's h ∂m/∂h the depth mode is left to the fit (a shift of h)
            self.disc = self.disc.image_term()
        self.W = self.disc.whitener(mb, pixel, sigma)
        self.P_w = self.W(self.disc.basis(mb, pixel, depth))
        self.I_w = self.W(self.I)
        self.U_w = None if shared is None or np.shape(shared)[1] == 0 else self.W(np.asarray(shared, float))

    def step(self, m, J=None, systematic=(), birge: bool = False) -> LinearFit:
        """The step from the forward image ``m`` (mm) along ``J`` (None: no parameters, the misfit
        alone); ``systematic`` and ``birge`` as in :func:`linear_fit`."""
        J = np.zeros((self.I.size, 0)) if J is None else np.asarray(J, float).reshape(self.I.size, -1)
        r_w = self.W(np.asarray(m, float).ravel()) - self.I_w
        r_a, J_a, keep = augment(r_w, self.W(J) if J.shape[1] else J, self.P_w, self.disc)
        if self.U_w is not None:  # the shared columns: unknowns γ with the prior |γ|²
            K, rows = self.U_w.shape[1], J_a.shape[0]
            U_a = np.vstack([self.U_w, np.zeros((rows - self.I.size, K))])
            J_a = np.block([[J_a, U_a], [np.zeros((K, J_a.shape[1])), np.eye(K)]])
            r_a = np.concatenate([r_a, np.zeros(K)])
        step = -np.linalg.lstsq(J_a, r_a, rcond=None)[0]
        Hi = _inverse(J_a.T @ J_a)
        n = J.shape[1]
        r_after = r_a + J_a @ step
        chi2, dof = float(r_after @ r_after), max(self.I.size - n, 1)
        cov = Hi * (max(1.0, chi2 / dof) if birge else 1.0)
        for dl in systematic:
            rhs = np.concatenate([self.W(np.asarray(dl, float).ravel()), np.zeros(J_a.shape[0] - self.I.size)])
            b = Hi @ (J_a.T @ rhs)
            cov = cov + np.outer(b, b)
        beta = self.disc.mean.copy()
        beta[keep] = beta[keep] + step[n : n + int(keep.sum())]
        return LinearFit(step[:n], cov[:n, :n], beta, chi2, dof)


def linear_fit(
    image,
    m0,
    J,
    sigma,
    pixel: float,
    disc: Discrepancy | None = None,
    systematic=(),
    birge: bool = False,
    basis_image=None,
) -> LinearFit:
    """The fit of ``image`` (mm) linearised at a point whose forward image is ``m0`` and Jacobian ``J``
    ``(p, n)`` (mm per unit of the fit's coordinates), pixel noise ``sigma`` (mm): the generalised
    least-squares step ``dx`` under the discrepancy ``disc`` (None: noise alone, the closed world).
    ``systematic``: images (mm) of a known-size error that moves every pixel together (the map's
    discretisation error, the difference of two mesh levels), each propagated through the estimator as
    a shift ``b`` added as ``b bᵀ`` to the covariance -- as :func:`elastimap.identify.fit.fit_image`
    does; ``birge``: the covariance widened by ``max(1, χ²/dof)``.  ``basis_image``: the image (mm) the
    discrepancy's modes and envelope are built from (default ``m0``; :class:`Marginal` explains why a
    fit comparing several points holds it fixed).  What :mod:`elastimap.workflows.studies.modelform`
    scores."""
    m0 = np.asarray(m0, float)
    mb = m0 if basis_image is None else np.asarray(basis_image, float).reshape(m0.shape)
    return Marginal(image, sigma, mb, pixel, disc).step(m0, J, systematic, birge)


@dataclass(frozen=True)
class HeldOut:
    """One calibration phantom scored by the discrepancy learnt from the others: ``chi2_px`` the residual's
    ``rᵀ Σ⁻¹ r / p`` under that budget (about 1 when the budget is the right size; residual less the
    learnt mean), ``z`` its modes' coefficients in units of their predicted sd and ``covered`` whether
    each lies within 1.96 of them."""

    chi2_px: float
    z: np.ndarray
    covered: np.ndarray


def leave_one_out(residuals, models, sigmas, pixel: float, depths=None, **kw) -> list[HeldOut]:
    """Leave-one-phantom-out check of :func:`learn` (``depths`` and ``kw`` passed on): each calibration
    phantom's residual scored by the discrepancy learnt from the others (:class:`HeldOut`).  What a lab's
    recalibration reports beside the learnt scales."""
    residuals, models, sigmas = list(residuals), list(models), list(sigmas)
    n = len(residuals)
    depths = [None] * n if depths is None else list(depths)
    if n < 3:
        raise UserError("phantoms", f"a leave-one-out check needs at least 3 calibration phantoms (got {n})")
    out = []
    for i in range(n):
        rest = [j for j in range(n) if j != i]
        d = learn(
            [residuals[j] for j in rest],
            [models[j] for j in rest],
            [sigmas[j] for j in rest],
            pixel,
            depths=None if depths[i] is None else [depths[j] for j in rest],
            **kw,
        )
        m = np.asarray(models[i], float)
        R = np.asarray(residuals[i], float)
        held = Marginal(m + R, sigmas[i], m, pixel, d, depths[i]).step(m)
        w = np.hypot(_sigma(sigmas[i], m.shape), d.remainder_sd(m)).reshape(m.shape)
        f = project(R, m, w, pixel, d.modes, depths[i])
        sd = np.sqrt(np.diag(d.prior_cov) + np.diag(f.cov))
        z = (f.beta - d.mean) / sd
        out.append(HeldOut(held.chi2 / m.size, z, np.abs(z) <= 1.96))
    return out


def forward_images(forward, thetas) -> tuple[list[np.ndarray], list[np.ndarray] | None]:
    """elastimap's images ``m(θ_i)`` (mm) at the designs ``thetas`` (d mm, h mm, E kPa) and, where the map
    has an exact derivative (a morphed map's ``tangent``, the same solve), the depth mode's ``h ∂m/∂h``
    (mm) there; else None (the term is then learnt without the depth mode).  ``forward(d, h, E)``
    returns an array or a result with ``.image``."""
    models, depths = [], []
    exact = bool(getattr(forward, "has_tangent", False))
    for th in thetas:
        d, h, E = (float(v) for v in th)
        if exact:
            out, J = forward.tangent(d, h, E)
            depths.append(h * np.asarray(J, float).reshape(3, -1)[1])
        else:
            out = forward(d, h, E)
        models.append(np.asarray(getattr(out, "image", out), dtype=float))
    return models, (depths if exact else None)


def calibrate(measured, sigmas, thetas, forward, pixel: float, **kw) -> tuple[Discrepancy, list[HeldOut]]:
    """The model-form error of a lab's calibration phantoms from their measured difference images
    (mm, e.g. recovered from camera frames), pixel noise (mm) and known ``thetas`` (d mm, h mm, E kPa),
    with ``forward(d, h, E)`` elastimap's image at a design (:func:`forward_images`; with the map's exact
    derivative the term holds the depth mode, :data:`DEPTH_MODES`, unless ``kw`` gives ``which``):
    the learnt :class:`Discrepancy` (:func:`learn`, ``kw`` passed on) and its leave-one-phantom-out check
    (:func:`leave_one_out`; empty for fewer than 3 phantoms)."""
    models, depths = forward_images(forward, thetas)
    kw.setdefault("which", MODES if depths is None else DEPTH_MODES)
    if DEPTH not in kw["which"]:
        depths = None
    residuals = [np.asarray(I, float) - m.reshape(np.shape(I)) for I, m in zip(measured, models, strict=True)]
    models = [m.reshape(np.shape(I)) for I, m in zip(measured, models, strict=True)]
    d = learn(residuals, models, sigmas, pixel, depths=depths, **kw)
    loo = leave_one_out(residuals, models, sigmas, pixel, depths=depths, **kw) if len(models) >= 3 else []
    return d, loo
