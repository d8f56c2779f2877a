r"""The model-form level of the decision (docs/gap.md, 'Model-form level').

Another faithful model of the same sensor -- and every real sensor -- differs from elastimap by more
than elastimap's own discretisation: 1–3 % of the difference image, structured (mostly the bump's
height and width, larger for small, stiff, deep inclusions).  The decision's error budget therefore
gets, per phantom i, the model-form term of :mod:`elastimap.identify.discrepancy` (the same
formulation the fit uses) carried into the compared views: with the phantom's own simulated
difference image m_i (the baseline, extrapolated to the converged mesh),

    Σ_i = diag(S_i²) + Φ_i T Φ_iᵀ + ρ² B A_i K_ℓ A_i Bᵀ                     (view units²)

* ``S_i``: noise and the measured discretisation error (:mod:`elastimap.gap.model_error`);
* ``Φ_i`` ``(Q, 2)``: the amplitude mode ``m_i`` and the width mode ``r ∂m_i/∂r``
  (:func:`elastimap.identify.discrepancy.modes`) reduced like the data (the radial profile: the
  annulus means ``B``), ``T = diag τ₀²``;
* ``ρ a η``: the smooth remainder, a fraction ρ₀ of the signal envelope ``a``, correlated over ℓ mm.

τ₀ = 2 % (amplitude, width), ρ₀ = 1 % and ℓ = 2 mm are the **prior** of
:class:`elastimap.identify.discrepancy.Discrepancy` (:data:`~elastimap.identify.discrepancy.PRIOR_SCALE`):
the size of the difference between elastimap and the independent references of the same sensor,
stated as a prior's scale -- never learnt from the data being diagnosed, which hold the effect.
β is independent from phantom to phantom in the χ² (the decision); the part common to every phantom
(a coherent height or width difference, which a per-phantom χ² would average down) enters the
magnitude's interval as coherent modes ±z₀.₉₇₅ τ₀ Φ (:func:`coherent_modes`), the way the coherent
mesh error does (:func:`elastimap.gap.fit_models.with_systematic`).

The plate force: an independent relative term τ₀ |F₀| (no mode; a stated approximation).  The three
camera features (the decision's view only when the data have no images): the amplitude mode
``y0`` with τ² = τ_amp² + τ_width² and a diagonal remainder ρ₀ |y0| (a stated approximation; the
features' response to a width change is not modelled).

:class:`Metric` is the error model a χ² is computed with: per phantom the Cholesky factor of Σ_i, so
``χ² = Σ_i |L_i⁻¹ (y_i − f_i)|²``; without the term it is the diagonal ``S`` of before.
"""

from __future__ import annotations

import numpy as np

from elastimap.identify.discrepancy import Discrepancy, correlation_factors, envelope, modes

from .views import profile_matrix

#: the two-sided 95 % normal quantile: the coherent model-form modes are shifts of ±z τ₀ Φ
Z95 = 1.959963984540054


class Metric:
    """The decision's error model: per phantom i the covariance Σ_i = diag(s_i²) + M_i ``(Q, Q)``
    (``M`` None: diagonal, the closed-world budget).  ``chi2(y, f)`` = Σ_q (L_i⁻¹ (y_i − f_i))_q²
    over the last axis (per phantom); indexing by phantoms (``S[idx]``) gives the metric of those
    phantoms."""

    def __init__(self, s, M=None):
        self.s = np.asarray(s, float)
        self.M = None if M is None else np.asarray(M, float)
        self.Linv = None
        if self.M is not None:
            C = self.M + self.s[..., :, None] ** 2 * np.eye(self.s.shape[-1])
            self.Linv = np.linalg.inv(np.linalg.cholesky(C))

    @classmethod
    def _of(cls, s, M, Linv) -> Metric:
        out = cls.__new__(cls)
        out.s, out.M, out.Linv = s, M, Linv
        return out

    @property
    def shape(self) -> tuple:
        return self.s.shape

    def __getitem__(self, idx) -> Metric:
        return Metric._of(
            self.s[idx], None if self.M is None else self.M[idx], None if self.Linv is None else self.Linv[idx]
        )

    def z(self, r) -> np.ndarray:
        """Whitened residuals L_i⁻¹ r_i (``r``: (..., n, Q))."""
        r = np.asarray(r, float)
        if self.Linv is None:
            return r / self.s
        return np.einsum("iqp,...ip->...iq", self.Linv, r)

    def chi2(self, y, f) -> np.ndarray:
        return np.sum(self.z(np.asarray(y, float) - np.asarray(f, float)) ** 2, axis=-1)

    def plus(self, extra) -> Metric:
        """The metric with an extra independent error ``extra`` (n, Q) per quantity (a candidate's
        interpolation error)."""
        extra = np.asarray(extra, float)
        if not np.any(extra):
            return self
        return Metric(np.sqrt(self.s**2 + extra**2), self.M)

    @property
    def sd(self) -> np.ndarray:
        """Marginal sd per phantom and quantity, sqrt(s² + diag M) (displays and linear emulators)."""
        if self.M is None:
            return self.s
        return np.sqrt(self.s**2 + np.einsum("iqq->iq", self.M))


def prior() -> Discrepancy:
    """The model-form prior the decision uses: :class:`~elastimap.identify.discrepancy.Discrepancy`
    with its default prior scales (τ₀ 2 % amplitude and width, ρ₀ 1 %, ℓ 2 mm), nothing learnt."""
    return Discrepancy()


def _profile_parts(D: np.ndarray, pixel: float, disc: Discrepancy) -> tuple[np.ndarray, np.ndarray]:
    """(Φ (K, k), R (K, K)) of one difference image ``D`` on the radial profile: the modes' annulus
    means and the remainder's covariance ρ² (B A) K_ℓ (B A)ᵀ (K_ℓ applied through its Kronecker
    factors)."""
    B = profile_matrix(D.shape, pixel)  # (K, p)
    Phi = B @ modes(D, pixel, disc.modes)
    W = B * (disc.rho * envelope(D))[None, :]  # (K, p): B A
    if disc.ell > 0:
        ny, nx = D.shape
        Ky, Kx = correlation_factors(D.shape, pixel, disc.ell)
        KW = np.array([(Ky @ w.reshape(ny, nx) @ Kx.T).ravel() for w in W])
        R = W @ KW.T
    else:
        R = W @ W.T
    return Phi, 0.5 * (R + R.T)


def level(V0: dict, D0, names, pixel: float, disc: Discrepancy | None = None) -> dict:
    """The model-form term of the decision views ``names`` at the baseline ``V0`` (views (n, q)) and
    its difference images ``D0`` (n, ny, nx): {"M": (n, Q, Q) covariance, "phi": (n, Q, k) the modes
    (zero rows for views without modes), "coherent": the modes of :func:`coherent_modes`,
    "disc": the prior, "note"}."""
    disc = disc or prior()
    n = next(iter(V0.values())).shape[0]
    blocks, phis = [], []
    T = np.diag(disc.tau**2)
    for k in names:
        q = V0[k].shape[1]
        Mk = np.zeros((n, q, q))
        Pk = np.zeros((n, q, len(disc.modes)))
        for i in range(n):
            if k == "profile" and D0 is not None:
                Phi, R = _profile_parts(np.asarray(D0[i], float), pixel, disc)
                Mk[i] = Phi @ T @ Phi.T + R
                Pk[i] = Phi
            elif k == "force":
                Mk[i] = np.diag((disc.tau[0] * V0[k][i]) ** 2)
            else:  # features: the amplitude mode with both modes' scales, a diagonal remainder
                y = V0[k][i]
                Mk[i] = float(np.sum(disc.tau**2)) * np.outer(y, y) + np.diag((disc.rho * y) ** 2)
                Pk[i, :, 0] = y
        blocks.append(Mk)
        phis.append(Pk)
    Q = sum(b.shape[1] for b in blocks)
    M = np.zeros((n, Q, Q))
    a = 0
    for b in blocks:
        q = b.shape[1]
        M[:, a : a + q, a : a + q] = b
        a += q
    phi = np.concatenate(phis, axis=1)
    return {
        "M": M,
        "phi": phi,
        "coherent": coherent_modes(phi, disc),
        "disc": disc,
        "note": (
            f"model-form prior of identify.discrepancy (a prior's scale from the independent references of "
            f"the same sensor, not learnt from these data): modes {', '.join(disc.modes)} τ₀ "
            f"{', '.join(f'{100 * t:g} %' for t in disc.tau)}, remainder ρ₀ {100 * disc.rho:g} % over "
            f"ℓ {disc.ell:g} mm"
        ),
    }


def coherent_modes(phi: np.ndarray, disc: Discrepancy) -> list[np.ndarray]:
    """The model-form difference common to every phantom, as data-shaped shifts (n, Q): for each
    mode k, z₀.₉₇₅ τ₀,k Φ_·,k (the same sign in every phantom).  An interval is widened by the shift
    of the fit when the data move by ± each (:func:`elastimap.gap.fit_models.with_systematic`)."""
    return [Z95 * float(t) * phi[:, :, j] for j, t in enumerate(disc.tau) if np.any(phi[:, :, j])]


def residual_level(y, f, S: Metric, phi: np.ndarray, disc: Discrepancy) -> dict:
    """What a fitted model leaves, in model-form units: per phantom the modes' coefficients
    β̂_i = (ΦᵀΣ_d⁻¹Φ + T⁻¹)⁻¹ ΦᵀΣ_d⁻¹ r_i (the posterior mean under the prior, Σ_d the rest of the
    covariance taken diagonal), their mean and spread over the phantoms (fractions), whether the mean
    is beyond :data:`~elastimap.identify.discrepancy.BEYOND` × τ₀ of the prior (not a model-form
    difference), and where the whitened residual is largest (phantom, quantity)."""
    from elastimap.identify.discrepancy import BEYOND, PRIOR_SCALE

    r = np.asarray(y, float) - np.asarray(f, float)
    n, _, k = phi.shape
    beta = np.zeros((n, k))
    Tinv = np.diag(1.0 / np.maximum(disc.tau, 1e-12) ** 2)
    for i in range(n):
        P = phi[i]
        if not np.any(P):
            continue
        w = 1.0 / np.maximum(S.s[i] ** 2, 1e-300)
        A = P.T @ (P * w[:, None]) + Tinv
        beta[i] = np.linalg.solve(A, P.T @ (w * r[i]))
    mean, sd = beta.mean(axis=0), beta.std(axis=0, ddof=1) if n > 1 else np.zeros(k)
    z = S.z(r)
    i, q = np.unravel_index(int(np.argmax(np.abs(z))), z.shape)
    beyond = [m for j, m in enumerate(disc.modes) if abs(mean[j]) > BEYOND * PRIOR_SCALE[m]]
    return {
        "modes": list(disc.modes),
        "beta_mean": mean.tolist(),
        "beta_sd": sd.tolist(),
        "beyond": beyond,
        "chi2": float(np.sum(z**2)),
        "n_terms": int(z.size),
        "largest": {"phantom": int(i), "quantity": int(q), "z": float(z[i, q])},
        "_beta": beta,
    }
