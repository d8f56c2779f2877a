"""The candidates as fitted models: predict, fit, interval (docs/gap.md, 'Method').

* :class:`Single` -- one effect, one magnitude θ over its whole range: a dense PCHIP
  interpolation of the solved magnitudes; θ̂ minimises χ² = Σ_iq ((y − f(θ))/S)²; its 95 %
  interval is {θ : χ²(θ) − χ²_min ≤ 3.84 c}, c = max(1, χ²_min / (N − 1)).
* :class:`Composed` -- a family of k effects, f = y0 + Σ_l (f_l(θ_l) − y0), fitted by coordinate
  descent; interval ±1.96 sqrt(c [2 H⁻¹]_ll) from the numerical Hessian H of χ².
* Intervals are widened by the coherent model-error modes (:func:`with_systematic`,
  :func:`systematic_modes`) and by the grouped jackknife over the held-out folds
  (:func:`jackknife_interval`).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats
from scipy.interpolate import PchipInterpolator
from scipy.optimize import brentq, minimize_scalar

from . import effects as fx
from .candidates import Candidate, Interp, fit_range
from .model_form import Metric
from .settings import Settings
from .views import cat

#: points of the dense magnitude grid a fit starts from
NDENSE = 401
#: a fit within this fraction of its range from an end is at that end (:func:`at_end`)
END_RTOL = 1e-6


def at_end(m: float, lo: float, hi: float) -> bool:
    """Whether the fit ``m`` sits at an end of the range [lo, hi] it was fitted over: within
    ``END_RTOL`` of the range's width.  The fits end with a bounded Brent search (xatol 1e-7 of
    the range), which stops short of a bound it is pinned against by about its tolerance (a
    family's probe_E1 at 180.000024 for the grid end 180: docs/gap.md, 'Out-of-library checks');
    the range extension uses the same 1e-6 of the range (:meth:`elastimap.gap.effects.Effect.beyond`)."""
    tol = END_RTOL * max(hi - lo, 1e-300)
    return abs(m - lo) <= tol or abs(m - hi) <= tol


def _interp_error(g: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Leave-one-magnitude-out PCHIP miss over the interior grid points, / 4 (halved spacing)."""
    if len(g) < 3:
        return np.zeros(Y.shape[1:])
    err = np.zeros(Y.shape[1:])
    for k in range(1, len(g) - 1):
        keep = np.r_[0:k, k + 1 : len(g)]
        err = np.maximum(err, np.abs(Y[k] - PchipInterpolator(g[keep], Y[keep], axis=0)(g[k])))
    return 0.25 * err


def chi2(y, f, S) -> np.ndarray:
    """Σ_q ((y − f) / S)² over the last axis; ``S`` a :class:`~elastimap.gap.model_form.Metric`
    (the model-form level's covariance): Σ_q (L⁻¹ (y − f))_q², per phantom."""
    if isinstance(S, Metric):
        return S.chi2(y, f)
    return np.sum(((y - f) / S) ** 2, axis=-1)


def with_systematic(mdl, y, S, th, stat: list, sys) -> list[tuple[float, float]]:
    """Widen statistical intervals by the shift a coherent model error causes: refit with the
    data moved by +e and by −e in every quantity at once, for each coherent error mode e, and add
    the largest shift on each side in quadrature.  ``sys``: one mode (an array like ``y``) or a
    list of modes.  The diagnosis passes two (:func:`systematic_modes`): σ_sys in every quantity
    (the mesh error is one-signed across phantoms) and the signed shift of the Richardson
    extrapolation when the convergence order is off."""
    modes = [m for m in (sys if isinstance(sys, (list, tuple)) else [sys]) if m is not None and np.any(m != 0)]
    if not modes:
        return stat
    idx = np.arange(y.shape[0])
    fits = [mdl.fit(y + sgn * e, S, idx) for e in modes for sgn in (1.0, -1.0)]
    out = []
    for l, (lo, hi) in enumerate(stat):
        t = float(th[l])
        dlo = max(0.0, t - min(f[l] for f in fits))
        dhi = max(0.0, max(f[l] for f in fits) - t)
        g = mdl.grid_of(l)
        out.append((float(max(g.min(), t - math.hypot(t - lo, dlo))), float(min(g.max(), t + math.hypot(hi - t, dhi)))))
    return out


def systematic_modes(me: dict, names) -> tuple[list[np.ndarray], np.ndarray | None]:
    """The coherent model-error modes the intervals are widened by (:func:`with_systematic`):
    σ_sys itself (one sign in every quantity), and, when the predictions were extrapolated
    (:func:`~elastimap.gap.model_error.richardson_correct`), the signed error of that extrapolation if the order p is off
    by the bracketing range: spread_q · Δ_iq (Δ = coarse − error mesh, per phantom and quantity),
    the direction every prediction moves when p does.  Also returns spread_q per term, with
    which a candidate that has its own Δ (:meth:`Single.own_delta`) gets its own signed mode."""
    modes = [cat(me["sigma"], names)]
    spread = None
    if "_spread" in me and "delta" in me:
        modes.append(cat({k: me["_spread"][k] * me["delta"][k] for k in names}, names))
        spread = cat({k: np.full_like(me["delta"][k], me["_spread"][k]) for k in names}, names)
    return modes, spread


def jackknife_interval(mdl, th, th_folds: np.ndarray) -> list[tuple[float, float]] | None:
    r"""The fit's 95 % interval from its spread over the held-out folds (grouped jackknife):
    with θ̂_(k) fitted without fold k (g folds),

    $$ \widehat{\rm var}(\hat\theta) = \frac{g-1}{g} \sum_k (\hat\theta_{(k)} - \bar\theta)^2,
       \qquad \hat\theta \pm t_{0.975,\,g-1} \sqrt{\widehat{\rm var}} $$

    (Efron & Tibshirani 1993, ch. 11).  It measures how much the estimate depends on which
    phantoms it sees, whatever the cause: noise, and a model-form error that differs from
    phantom to phantom, which the likelihood interval (its error model: noise + the measured
    discretisation error) does not hold.  None with fewer than 3 folds."""
    g = len(th_folds)
    if g < 3:
        return None
    th_folds = np.atleast_2d(np.asarray(th_folds, float).reshape(g, -1))
    var = (g - 1) / g * np.sum((th_folds - th_folds.mean(axis=0)) ** 2, axis=0)
    hw = float(stats.t.ppf(0.975, g - 1)) * np.sqrt(var)
    out = []
    for l, (t, w) in enumerate(zip(np.atleast_1d(th), hw)):
        span = mdl.grid_of(l)
        out.append((float(max(span.min(), t - w)), float(min(span.max(), t + w))))
    return out


class Single:
    """One effect, one magnitude, over the effect's whole range [lo, hi]: interpolated between
    the solved magnitudes (the full grid, or the adaptive points), extrapolated linearly beyond."""

    def __init__(self, c: Candidate, names):
        self.c, self.name, self.k, self.names = c, c.effect.name, 1, list(names)
        self.effect, self.stage, self.unit = c.effect, c.effect.stage, c.effect.unit
        self.grid = c.grid
        self.lo, self.hi = fit_range(c)
        self.Y = cat(c.V, self.names)  # (K, n, Q)
        self._pchip = Interp(self.grid, self.Y)
        if self.hi > self.lo and len(self.grid) > 1:
            self.dense = np.linspace(self.lo, self.hi, NDENSE)
            self.dense_Y = self._pchip(self.dense)
        else:
            self.dense, self.dense_Y = self.grid.copy(), self.Y.copy()
        self.interp = (
            cat(c.interp_error, self.names) if c.interp_error is not None else _interp_error(self.grid, self.Y)
        )

    def span(self):
        return np.array([self.lo, self.hi]) if len(self.grid) > 1 else np.array([self.grid[0], self.grid[0]])

    @property
    def labels(self):
        return [self.name]

    def grid_of(self, l):
        return self.span()

    def predict(self, th, names=None) -> np.ndarray:
        m = float(np.clip(float(np.atleast_1d(th)[0]), *self.span()))
        if names is None or list(names) == self.names:
            return self._pchip(m)
        return Interp(self.grid, cat(self.c.V, names))(m)

    def image(self, th):
        D, g = self.c.D, self.grid
        if D is None:
            return None
        m = float(np.atleast_1d(th)[0])
        k = int(np.clip(np.searchsorted(g, m), 1, len(g) - 1)) if len(g) > 1 else 0
        if len(g) == 1:
            return D[0]
        t = float(np.clip((m - g[k - 1]) / (g[k] - g[k - 1]), 0, 1))
        return (1 - t) * D[k - 1] + t * D[k]

    def own_delta(self, th) -> np.ndarray | None:
        """Its own level difference Δ at magnitude th (linear between the magnitudes it was
        measured at), or None (the baseline's Δ stands for it)."""
        pts = sorted(self.c.own_delta, key=lambda x: x[0])
        if not pts:
            return None
        ms = np.array([m for m, _ in pts])
        D = np.array([cat(d, self.names) for _, d in pts])
        m = float(np.clip(float(np.atleast_1d(th)[0]), ms[0], ms[-1]))
        k = int(np.clip(np.searchsorted(ms, m), 1, len(ms) - 1)) if len(ms) > 1 else 0
        if len(ms) == 1:
            return D[0]
        t = (m - ms[k - 1]) / max(ms[k] - ms[k - 1], 1e-300)
        return (1 - t) * D[k - 1] + t * D[k]

    def tie(self) -> np.ndarray:
        """A negligible preference for the nominal magnitude, so that a flat χ² (an effect these
        phantoms do not see) fits the nominal, not a grid end."""
        span = max(float(self.hi - self.lo), 1e-300)
        return 1e-9 * ((self.dense - self.effect.nominal) / span) ** 2

    def _chi(self, m, y, S, idx) -> float:
        return float(chi2(y[idx], self.predict(m)[idx], S[idx]).sum())

    def fit(self, y, S, idx) -> np.ndarray:
        """Dense-grid argmin, then refined between the neighbouring dense points (bounded Brent):
        with precise data the dense spacing alone is coarser than the fit's resolution."""
        tot = chi2(y[idx], self.dense_Y[:, idx], S[idx]).sum(axis=1)
        k = int(np.argmin(tot + self.tie() * (1 + tot.min())))
        if len(self.dense) < 3:
            return np.array([self.dense[k]])
        lo, hi = self.dense[max(k - 1, 0)], self.dense[min(k + 1, len(self.dense) - 1)]
        r = minimize_scalar(
            lambda m: self._chi(m, y, S, idx),
            bounds=(lo, hi),
            method="bounded",
            options={"xatol": 1e-7 * (self.hi - self.lo)},
        )
        m = float(r.x) if r.fun < tot[k] else float(self.dense[k])
        return np.array([m])

    def interval(self, y, S, th) -> list[tuple[float, float]]:
        """{m : χ²(m) − χ²(m̂) ≤ 3.84 c}: the crossings located on the dense grid, then refined (Brent)."""
        m0 = float(th[0])
        idx = np.arange(y.shape[0])
        f0 = self._chi(m0, y, S, idx)
        N = y.size
        c = max(1.0, f0 / max(N - 1, 1))
        thr = 3.84 * c
        tot = chi2(y, self.dense_Y, S).sum(axis=1) - f0 - thr
        g = lambda m: self._chi(m, y, S, idx) - f0 - thr  # noqa: E731
        out = []
        left = np.flatnonzero((self.dense < m0) & (tot > 0))
        if len(left):
            a = self.dense[left[-1]]
            out.append(float(brentq(g, a, m0)) if g(a) > 0 > g(m0) else float(a))
        else:
            out.append(float(self.span()[0]))
        right = np.flatnonzero((self.dense > m0) & (tot > 0))
        if len(right):
            b = self.dense[right[0]]
            out.append(float(brentq(g, m0, b)) if g(b) > 0 > g(m0) else float(b))
        else:
            out.append(float(self.span()[1]))
        return [(out[0], out[1])]

    def at_edge(self, th) -> bool:
        return bool(len(self.grid) > 1 and at_end(float(th[0]), self.lo, self.hi))

    def params_at(self, p, th):
        return self.effect.apply_params(p, float(th[0]))

    def sensor_at(self, s, th):
        return self.effect.apply_sensor(s, float(th[0]))

    def nominal(self):
        return [self.effect.nominal]

    def units(self):
        return [self.unit]


class Composed:
    """A family: f(θ) = y0 + Σ_l (f_l(θ_l) − y0), fitted by coordinate descent."""

    def __init__(self, fam: fx.Family, members: list[Single], y0: np.ndarray, V0: dict):
        self.fam, self.name, self.members, self.k = fam, fam.name, members, len(members)
        self.names, self.stage, self.y0, self.V0 = members[0].names, fam.stage, y0, V0
        self.unit = "/".join(m.unit for m in members)
        self.interp = np.sqrt(sum(m.interp**2 for m in members))
        self.grid = members[0].grid
        self.effect = None
        #: each member is held inside its effect's grid range (an extension of a member's own
        #: range, made for its single fit, is not the family's)
        self.bounds = [(max(m.lo, m.effect.lo), min(m.hi, m.effect.hi)) for m in members]

    @property
    def labels(self):
        return [m.name for m in self.members]

    def grid_of(self, l):
        return np.array(self.bounds[l]) if len(self.members[l].grid) > 1 else self.members[l].span()

    def predict(self, th, names=None) -> np.ndarray:
        base = self.y0 if names is None or list(names) == self.names else cat(self.V0, names)
        return base + sum(m.predict(t, names) - base for m, t in zip(self.members, th))

    def image(self, th):
        Ds = [m.image(t) for m, t in zip(self.members, th)]
        if any(D is None for D in Ds):
            return None
        D0 = self.members[0].c.D[np.argmin(np.abs(self.members[0].grid - self.members[0].effect.nominal))]
        return D0 + sum(D - D0 for D in Ds)

    def fit(self, y, S, idx) -> np.ndarray:
        th = np.array([m.effect.nominal for m in self.members], float)
        parts = [m.predict(t) - self.y0 for m, t in zip(self.members, th)]
        for _ in range(4):
            for l, m in enumerate(self.members):
                rest = self.y0 + sum(p for j, p in enumerate(parts) if j != l)
                a, b = self.bounds[l]
                ok = (m.dense >= a - 1e-12) & (m.dense <= b + 1e-12)
                f = rest[None] + (m.dense_Y[ok] - self.y0[None])
                tot = chi2(y[idx], f[:, idx], S[idx]).sum(axis=1)
                th[l] = m.dense[ok][int(np.argmin(tot + m.tie()[ok] * (1 + tot.min())))]
                parts[l] = m.predict(th[l]) - self.y0
        for _ in range(2):  # refine each parameter between its neighbouring dense points
            for l, m in enumerate(self.members):
                step = (m.hi - m.lo) / (NDENSE - 1)
                if step <= 0:
                    continue
                rest = self.y0 + sum(p for j, p in enumerate(parts) if j != l)
                fun = lambda t, rest=rest, m=m: float(chi2(y[idx], (rest + m.predict(t) - self.y0)[idx], S[idx]).sum())
                lo, hi = max(self.bounds[l][0], th[l] - step), min(self.bounds[l][1], th[l] + step)
                r = minimize_scalar(fun, bounds=(lo, hi), method="bounded", options={"xatol": 1e-7 * step * NDENSE})
                if r.fun < fun(th[l]):
                    th[l] = float(r.x)
                    parts[l] = m.predict(th[l]) - self.y0
        return th

    def interval(self, y, S, th) -> list[tuple[float, float]]:
        th = np.asarray(th, float)
        spans = np.array([m.hi - m.lo for m in self.members])
        h = 0.01 * spans

        def F(t):
            return float(chi2(y, self.predict(t), S).sum())

        k = self.k
        H = np.zeros((k, k))
        f0 = F(th)
        for a in range(k):
            for b in range(a, k):
                ea, eb = np.eye(k)[a] * h[a], np.eye(k)[b] * h[b]
                H[a, b] = H[b, a] = (F(th + ea + eb) - F(th + ea - eb) - F(th - ea + eb) + F(th - ea - eb)) / (
                    4 * h[a] * h[b]
                )
        c = max(1.0, f0 / max(y.size - k, 1))
        try:
            cov = 2.0 * np.linalg.inv(H) * c
            sd = np.sqrt(np.clip(np.diag(cov), 0, None))
            if not np.all(np.isfinite(sd)) or np.any(np.diag(cov) <= 0):
                raise np.linalg.LinAlgError
        except np.linalg.LinAlgError:
            sd = spans  # not identifiable from these phantoms: the whole grid
        return [(float(max(a, t - 1.96 * s)), float(min(b, t + 1.96 * s))) for (a, b), t, s in zip(self.bounds, th, sd)]

    def at_edge(self, th) -> bool:
        return any(len(m.grid) > 1 and at_end(t, a, b) for m, (a, b), t in zip(self.members, self.bounds, th))

    def params_at(self, p, th):
        for m, t in zip(self.members, th):
            p = m.params_at(p, [t])
        return p

    def sensor_at(self, s, th):
        for m, t in zip(self.members, th):
            s = m.sensor_at(s, [t])
        return s

    def nominal(self):
        return [m.effect.nominal for m in self.members]

    def units(self):
        return [m.unit for m in self.members]


class Pair(Composed):
    """Two single effects at once (k = 2): f(θ_a, θ_b) = y0 + (f_a(θ_a) − y0) + (f_b(θ_b) − y0),
    composed to first order from their own sweeps like a family (interactions neglected), each held
    inside its effect's grid; named ``a+b``."""

    def __init__(self, a: Single, b: Single, y0: np.ndarray):
        super().__init__(fx.Family(f"{a.name}+{b.name}", (a.name, b.name), "two effects at once"), [a, b], y0, None)
        self.stage = a.stage if a.stage == b.stage else f"{a.stage}+{b.stage}"

    def predict(self, th, names=None) -> np.ndarray:
        if names is None or list(names) == self.names:
            return super().predict(th)
        a = self.members[0]
        base = a.predict([a.effect.nominal], names)  # the baseline in those views
        return base + sum(m.predict(t, names) - base for m, t in zip(self.members, th))


def build_models(C: list[Candidate], names, V0: dict, st: Settings) -> list:
    """A :class:`Single` per candidate and a :class:`Composed` per family of ``st.families`` whose
    members are all candidates, on the views ``names``."""
    singles = [Single(c, names) for c in C]
    byname = {m.name: m for m in singles}
    y0 = cat(V0, names)
    fams = [
        Composed(f, [byname[n] for n in f.members], y0, V0) for f in fx.families_for([c.effect for c in C], st.families)
    ]
    return singles + fams
