"""The diagnosis: where the sim-to-real gap lies, which effect explains it, how far it shrinks.

Notation: phantom i = 1..n with known (d, h, E)_i, measured camera features y_ij (j = O1, O2,
O3) with standard error se_ij (noise floor from repeated frames), simulated camera features of
the baseline model y0_ij and of candidate effect c at magnitude m, f_c(m)_ij.

* **Normalised residual** r_ij(m) = (y_ij − f_c(m)_ij) / s_ij with
  s_ij = sqrt(se_ij² + (ρ y0_ij)²); ρ (``model_floor``, default 0.5 %) is the model's own
  tolerance (mesh, interpolation between sweep magnitudes).  χ²_i(m) = Σ_j r_ij².
  The gap is **significant** when Σ_i χ²_i(nominal) exceeds the 99.9 % point of χ²(3n).
* **Magnitude fit**: f_c(m) is the monotone cubic (PCHIP) interpolation of the sweep
  magnitudes, evaluated on a dense grid; m̂ minimises Σ_i χ²_i(m) over the fitting phantoms.
  Interval: bootstrap over phantoms (2.5–97.5 %).
* **Ranking**: leave-one-out (n ≤ 15) or 10-fold cross-validation: m̂ is fitted without the
  held-out phantoms, SSR_cv = Σ held-out χ².  Explained fraction EF = 1 − SSR_cv / SSR_0 with
  SSR_0 the baseline's χ²; the ranking score is SSR_cv + k ln(3n) (a BIC-like penalty per
  fitted parameter k).  A candidate **explains** the gap when EF ≥ ``explain_min`` and its
  held-out reduced χ² is at most ``resid_max`` (the leftover is noise-like) once its own
  sweep-interpolation error (leave-one-magnitude-out PCHIP miss / 4) is added to s;
  otherwise the outcome is "no candidate explains the gap" (``unexplained``).
* **Where**: by feature (relative gap, bootstrap CI), by region of (d, h, E) (terciles), by
  stage (the share a per-feature affine recalibration y ≈ a y0 + b absorbs in cross-validation
  is optics-like -- a camera gain/offset; the rest is mechanics-like; the inverse's own error
  vs the error it makes on measured features), and by image region (mean residual map of the
  camera difference images, noise from the window's outer ring).
* **Shrink**: on withheld phantoms (every third phantom, never used for the magnitude fit of
  this step) the gap before (baseline) and after (winner at the magnitude fitted on the rest),
  in feature space (RMS normalised residual) and in (d, h, E) after retraining the inverse
  (``elastimap.training.api.fit_ensemble``, camera features -> (d, h, E)) on simulations with the effect.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import stats
from scipy.interpolate import PchipInterpolator

from elastimap.errors import UserError

from . import effects as fx
from .measured import FEATURES, Measured
from .simulate import Simulator, base_params, camera_features_of

NDENSE = 401


@dataclass
class Settings:
    model_floor: float = 0.005
    explain_min: float = 0.7
    resid_max: float = 4.0
    bootstrap: int = 200
    seed: int = 0
    inverse: bool = True
    n_train: int = 40
    train_repeats: int = 4
    train_epochs: int = 300


@dataclass
class Candidate:
    effect: fx.Effect
    grid: np.ndarray                  # (K,)
    Y: np.ndarray                     # (K, n, 3) camera features
    D: np.ndarray | None              # (K, n, ny, nx) camera difference images
    dropped: list = field(default_factory=list)
    dense_m: np.ndarray | None = None
    dense_Y: np.ndarray | None = None

    def prepare(self):
        g, Y = self.grid, self.Y
        if len(g) == 1:
            self.dense_m, self.dense_Y = g.copy(), Y.copy()
            return self
        self.dense_m = np.linspace(g.min(), g.max(), NDENSE)
        self.dense_Y = PchipInterpolator(g, Y, axis=0)(self.dense_m)
        return self

    def at(self, m: float) -> np.ndarray:
        if len(self.grid) == 1:
            return self.Y[0]
        return PchipInterpolator(self.grid, self.Y, axis=0)(np.clip(m, self.grid.min(), self.grid.max()))

    def image_at(self, m: float) -> np.ndarray | None:
        if self.D is None:
            return None
        k = np.searchsorted(self.grid, m)
        k = int(np.clip(k, 1, len(self.grid) - 1))
        g0, g1 = self.grid[k - 1], self.grid[k]
        t = float(np.clip((m - g0) / (g1 - g0), 0, 1)) if g1 > g0 else 0.0
        return (1 - t) * self.D[k - 1] + t * self.D[k]


# ------------------------------------------------------------------ simulation
def phantom_params(meas: Measured, mesh: str):
    return [base_params(mesh, *meas.dhe[i], tissue_E=meas.tissue_E[i]) for i in range(meas.n)]


def simulate_candidates(meas: Measured, cands: list[fx.Effect], sim: Simulator, sensor, settings,
                        want_images: bool = True) -> tuple[np.ndarray, np.ndarray | None, list[Candidate]]:
    """Baseline camera features (n, 3) [and difference images] and every candidate's sweep."""
    p0 = phantom_params(meas, sim.mesh)
    plan = []  # (effect, m, params list or None)
    for e in cands:
        for m in e.grid:
            if e.stage == "mechanics":
                try:
                    pl = [e.apply_params(p, m).validate() for p in p0]
                except UserError:
                    plan.append((e, m, None))
                    continue
                plan.append((e, m, pl))
            else:
                plan.append((e, m, p0))
    flat = list(p0) + [p for _, _, pl in plan if pl is not None for p in pl]
    recs = sim.run(flat)
    base = recs[: meas.n]
    y0, D0 = _cam(base, sensor, settings)
    if not np.all(np.isfinite(y0)):
        raise UserError("measured", "the baseline solve failed for phantom(s) "
                                    f"{[meas.ids[i] for i in np.flatnonzero(~np.all(np.isfinite(y0), axis=1))]}")
    pos = meas.n
    out = []
    for e in cands:
        ms, Ys, Ds, dropped = [], [], [], []
        for e2, m, pl in plan:
            if e2 is not e:
                continue
            if pl is None:
                dropped.append(float(m))
                continue
            if e.stage == "mechanics":
                rr = recs[pos: pos + meas.n]
                pos += meas.n
                Y, D = (y0, D0) if e.is_nominal(m) else _cam(rr, sensor, settings)
            else:
                pos += meas.n
                Y, D = (y0, D0) if e.is_nominal(m) else _cam(base, e.apply_sensor(sensor, m), settings)
            if not np.all(np.isfinite(Y)):
                dropped.append(float(m))      # a failed solve: drop this magnitude
                continue
            ms.append(float(m))
            Ys.append(Y)
            Ds.append(D)
        order = np.argsort(ms)
        out.append(Candidate(e, np.asarray(ms)[order], np.asarray(Ys)[order],
                             np.asarray(Ds)[order] if want_images else None, dropped).prepare())
    return y0, (D0 if want_images else None), out


def _cam(recs, sensor, settings):
    Y, D = [], []
    for r in recs:
        v, d = camera_features_of(r, sensor, settings)
        Y.append(v)
        D.append(d)
    return np.asarray(Y), np.asarray(D)


# ------------------------------------------------------------------ statistics
def scales(meas: Measured, y0: np.ndarray, rho: float) -> np.ndarray:
    s = np.sqrt(meas.se ** 2 + (rho * np.abs(y0)) ** 2)
    return np.maximum(s, 1e-12 * np.maximum(np.abs(y0), 1.0))


def chi2_rows(y, f, s) -> np.ndarray:
    """χ²_i = Σ_j ((y − f)/s)²; f may carry leading axes."""
    return np.sum(((y - f) / s) ** 2, axis=-1)


def interpolation_error(c: Candidate) -> np.ndarray:
    """(n, 3) estimate of the sweep-interpolation error of candidate ``c``: each interior grid
    magnitude is predicted from the others (leave-one-out PCHIP); the largest miss, scaled by
    1/4 for the halved spacing of the full grid, is the error bar of f_c(m)."""
    g, Y = c.grid, c.Y
    if len(g) < 3:
        return np.zeros(Y.shape[1:])
    err = np.zeros(Y.shape[1:])
    for k in range(1, len(g) - 1):
        keep = np.r_[0:k, k + 1:len(g)]
        pred = PchipInterpolator(g[keep], Y[keep], axis=0)(g[k])
        err = np.maximum(err, np.abs(Y[k] - pred))
    return 0.25 * err


def fit_magnitude(c: Candidate, y, s, idx) -> float:
    """m̂ minimising Σ_{i in idx} χ²_i over the dense magnitude grid."""
    tot = chi2_rows(y[idx], c.dense_Y[:, idx], s[idx]).sum(axis=1)
    return float(c.dense_m[int(np.argmin(tot))])


def folds(n: int, seed: int) -> list[np.ndarray]:
    if n <= 15:
        return [np.array([i]) for i in range(n)]
    rng = np.random.default_rng(seed)
    perm = rng.permutation(n)
    return [perm[k::10] for k in range(10)]


def bootstrap_ci(values: np.ndarray, stat, B: int, rng) -> tuple[float, float]:
    n = len(values)
    if n < 2:
        return (math.nan, math.nan)
    bs = [stat(values[rng.integers(0, n, n)]) for _ in range(B)]
    return float(np.percentile(bs, 2.5)), float(np.percentile(bs, 97.5))


def evaluate(meas: Measured, y0, cands: list[Candidate], st: Settings) -> dict:
    """Ranking of the candidates (cross-validated), fitted magnitudes and intervals, outcome."""
    y, n = meas.y, meas.n
    s = scales(meas, y0, st.model_floor)
    chi0 = chi2_rows(y, y0, s)
    ssr0 = float(chi0.sum())
    N = 3 * n
    thr = float(stats.chi2.ppf(0.999, N))
    rng = np.random.default_rng(st.seed)
    F = folds(n, st.seed)
    rows = []
    for c in cands:
        held = np.zeros(n)
        pred = np.zeros((n, 3))
        for te in F:
            tr = np.setdiff1d(np.arange(n), te)
            m = fit_magnitude(c, y, s, tr)
            f = c.at(m)
            held[te] = chi2_rows(y[te], f[te], s[te])
            pred[te] = f[te]
        m_all = fit_magnitude(c, y, s, np.arange(n))
        boots = [fit_magnitude(c, y, s, rng.integers(0, n, n)) for _ in range(st.bootstrap)]
        ssr_cv = float(held.sum())
        ef = 1.0 - ssr_cv / ssr0 if ssr0 > 0 else 0.0
        # the "explains" test allows for the candidate's own sweep-interpolation error
        sc = np.sqrt(s ** 2 + interpolation_error(c) ** 2)
        held_c = np.zeros(n)
        for te in F:
            tr = np.setdiff1d(np.arange(n), te)
            held_c[te] = chi2_rows(y[te], c.at(fit_magnitude(c, y, sc, tr))[te], sc[te])
        rows.append({
            "effect": c.effect.name, "stage": c.effect.stage, "unit": c.effect.unit,
            "magnitude": m_all, "magnitude_ci": [float(np.percentile(boots, 2.5)), float(np.percentile(boots, 97.5))],
            "nominal": c.effect.nominal, "grid": c.grid.tolist(), "dropped_magnitudes": c.dropped,
            "ssr_cv": ssr_cv, "explained_fraction": ef, "reduced_chi2_cv": ssr_cv / N,
            "reduced_chi2_cv_with_interpolation": float(held_c.sum()) / N,
            "score": ssr_cv + c.effect.n_params * math.log(N), "n_params": c.effect.n_params,
            "at_grid_edge": bool(abs(m_all - c.grid.min()) < 1e-9 or abs(m_all - c.grid.max()) < 1e-9),
            "_pred_cv": pred,
        })
    rows.sort(key=lambda r: r["score"])
    significant = ssr0 > thr
    win = rows[0] if rows else None
    explains = bool(win and significant and win["explained_fraction"] >= st.explain_min
                    and win["reduced_chi2_cv_with_interpolation"] <= st.resid_max)
    if not significant:
        outcome = "no significant gap"
    elif explains:
        outcome = "explained"
    else:
        outcome = "unexplained"
    return {"ssr0": ssr0, "chi2_threshold": thr, "reduced_chi2_baseline": ssr0 / N, "significant": significant,
            "ranking": rows, "outcome": outcome,
            "winner": win["effect"] if outcome == "explained" else None,
            "best": win["effect"] if win else None,
            "runner_up": rows[1]["effect"] if len(rows) > 1 else None, "scales": s}


def where(meas: Measured, y0, D0, st: Settings) -> dict:
    """Where the gap lies: by feature, by (d, h, E) region, by stage (affine share), by image region."""
    y, n = meas.y, meas.n
    s = scales(meas, y0, st.model_floor)
    rng = np.random.default_rng(st.seed + 1)
    rel = (y - y0) / np.where(np.abs(y0) > 0, np.abs(y0), 1.0)
    r = (y - y0) / s
    by_feature = {}
    for j, k in enumerate(FEATURES):
        by_feature[k] = {"relative_gap_mean": float(rel[:, j].mean()),
                         "relative_gap_ci": bootstrap_ci(rel[:, j], np.mean, st.bootstrap, rng),
                         "noise_units_rms": float(np.sqrt(np.mean(r[:, j] ** 2))),
                         "noise_floor_relative": float(np.median(meas.se[:, j] / np.maximum(np.abs(y[:, j]), 1e-300)))}
    rms_i = np.sqrt(np.mean(r ** 2, axis=1))
    by_region = {}
    for q, name in enumerate(("d", "h", "E")):
        v = meas.dhe[:, q]
        edges = np.quantile(v, [0, 1 / 3, 2 / 3, 1])
        bins = []
        for b in range(3):
            sel = (v >= edges[b]) & ((v <= edges[b + 1]) if b == 2 else (v < edges[b + 1]))
            if sel.sum() == 0:
                continue
            bins.append({"range": [float(edges[b]), float(edges[b + 1])], "n": int(sel.sum()),
                         "rms_noise_units": float(np.sqrt(np.mean(rms_i[sel] ** 2))),
                         "rms_ci": bootstrap_ci(rms_i[sel], lambda a: float(np.sqrt(np.mean(a ** 2))), st.bootstrap, rng),
                         "relative_gap_mean": {k: float(rel[sel, j].mean()) for j, k in enumerate(FEATURES)}})
        by_region[name] = bins
    # stage: how much a per-feature affine recalibration absorbs (held-out)
    ssr0 = float(np.sum(r ** 2))
    held = 0.0
    for te in folds(n, st.seed):
        tr = np.setdiff1d(np.arange(n), te)
        pred = np.empty((len(te), 3))
        for j in range(3):
            A = np.column_stack([y0[tr, j], np.ones(len(tr))])
            coef, *_ = np.linalg.lstsq(A, y[tr, j], rcond=None)
            pred[:, j] = coef[0] * y0[te, j] + coef[1]
        held += float(np.sum(((y[te] - pred) / s[te]) ** 2))
    affine_share = float(np.clip(1 - held / ssr0, 0, 1)) if ssr0 > 0 else 0.0
    out = {"by_feature": by_feature, "by_region": by_region, "per_phantom_rms_noise_units": rms_i.tolist(),
           "stage": {"optics_like_affine_share": affine_share, "mechanics_like_share": 1 - affine_share},
           "relative_gap": rel, "normalised_residual": r}
    have = [i for i in range(n) if meas.difference[i] is not None]
    if have and D0 is not None and meas.difference[have[0]].shape == D0[0].shape:
        R = np.array([meas.difference[i] - D0[i] for i in have])
        ring = np.zeros(R.shape[1:], bool)
        w = max(2, R.shape[1] // 10)
        ring[:w, :] = ring[-w:, :] = ring[:, :w] = ring[:, -w:] = True
        noise = float(np.std(R[:, ring]))
        out["image"] = {"n": len(have), "mean_residual": R.mean(axis=0), "noise_px": noise,
                        "mean_measured": np.mean([meas.difference[i] for i in have], axis=0),
                        "mean_simulated": D0[have].mean(axis=0),
                        "max_abs_mean_residual_noise_units": float(np.max(np.abs(R.mean(axis=0))) /
                                                                   (noise / math.sqrt(len(have)) + 1e-300))}
    return out


# ------------------------------------------------------------------ shrink
def withheld_split(n: int) -> tuple[np.ndarray, np.ndarray]:
    te = np.arange(n)[1::3]
    return np.setdiff1d(np.arange(n), te), te


def shrink_features(meas: Measured, y0, c: Candidate, st: Settings) -> dict:
    y = meas.y
    s = scales(meas, y0, st.model_floor)
    tr, te = withheld_split(meas.n)
    m = fit_magnitude(c, y, s, tr)
    f = c.at(m)
    before = float(np.sqrt(np.mean(((y[te] - y0[te]) / s[te]) ** 2)))
    after = float(np.sqrt(np.mean(((y[te] - f[te]) / s[te]) ** 2)))
    relb = np.mean(np.abs(y[te] - y0[te]) / np.abs(y[te]), axis=0)
    rela = np.mean(np.abs(y[te] - f[te]) / np.abs(y[te]), axis=0)
    return {"fit_phantoms": [meas.ids[i] for i in tr], "withheld": [meas.ids[i] for i in te], "magnitude": m,
            "rms_noise_units_before": before, "rms_noise_units_after": after,
            "shrink": 1 - after / before if before > 0 else 0.0,
            "relative_gap_before": {k: float(relb[j]) for j, k in enumerate(FEATURES)},
            "relative_gap_after": {k: float(rela[j]) for j, k in enumerate(FEATURES)}}


def training_design(meas: Measured, n: int, seed: int, aspect_hi: float = 1.0) -> np.ndarray:
    """LHS of (d, h, E) over the phantoms' bounding box (E log-uniform), depths kept valid."""
    from scipy.stats import qmc

    from elastimap.dataset.schema import THICKNESS, depth_range

    u = qmc.LatinHypercube(d=3, rng=np.random.default_rng(seed)).random(n)
    lo, hi = meas.dhe.min(0), meas.dhe.max(0)
    d = lo[0] + u[:, 0] * (hi[0] - lo[0])
    a, b = depth_range(d, THICKNESS, aspect_hi)
    hl, hh = np.maximum(a, lo[1]), np.minimum(b, hi[1])
    hh = np.maximum(hh, hl)
    h = hl + u[:, 1] * (hh - hl)
    E = np.exp(np.log(lo[2]) + u[:, 2] * (np.log(hi[2]) - np.log(lo[2])))
    return np.column_stack([d, h, E])


def _train_inverse(X, T, st: Settings):
    import pandas as pd

    from elastimap.training.api import fit_ensemble

    df = pd.DataFrame({"O1": X[:, 0], "O2": X[:, 1], "O3": X[:, 2], "d": T[:, 0], "h": T[:, 1], "E": T[:, 2]})
    return fit_ensemble(df, algo="scg", repeats=st.train_repeats, epochs=st.train_epochs, hidden=(10,), seed=st.seed)


def shrink_inverse(meas: Measured, c: Candidate, m: float, sim: Simulator, sensor, settings, st: Settings) -> dict:
    """(d, h, E) error on the withheld phantoms: inverse trained on baseline sims vs on sims with
    the effect at ``m`` (camera features -> (d, h, E), ``fit_ensemble`` SCG)."""
    tr, te = withheld_split(meas.n)
    aspect_hi = max(1.0, c.effect.hi if c.effect.name == "aspect" else 1.0)
    T = training_design(meas, st.n_train, st.seed, aspect_hi)
    p_base = [base_params(sim.mesh, *t) for t in T]
    e = c.effect
    p_eff = [e.apply_params(p, m) for p in p_base] if e.stage == "mechanics" else p_base
    ok = []
    for i, p in enumerate(p_eff):
        try:
            p.validate()
            ok.append(i)
        except UserError:
            pass
    ok = np.array(ok)
    recs = sim.run([p_base[i] for i in ok] + [p_eff[i] for i in ok])
    k = len(ok)
    Xb, _ = _cam(recs[:k], sensor, settings)
    s_eff = e.apply_sensor(sensor, m) if e.stage == "optics" else sensor
    Xe, _ = _cam(recs[k:], s_eff, settings)
    # a failed solve (NaN record) drops its design point from both training sets (paired design)
    fin = np.all(np.isfinite(Xb), axis=1) & np.all(np.isfinite(Xe), axis=1)
    Xb, Xe, Tk = Xb[fin], Xe[fin], T[ok][fin]
    ens_b = _train_inverse(Xb, Tk, st)
    ens_e = _train_inverse(Xe, Tk, st)
    truth = meas.dhe[te]
    out = {"n_train": int(fin.sum()), "n_failed_solves": int(k - fin.sum()),
           "withheld": [meas.ids[i] for i in te], "magnitude": m}
    # the inverse's own error: baseline inverse on noise-free baseline simulations of the withheld phantoms
    own_recs = sim.run(phantom_params(meas.subset(te), sim.mesh))
    Xown, _ = _cam(own_recs, sensor, settings)
    for name, ens, X in (("inverse_own", ens_b, Xown), ("before", ens_b, meas.y[te]), ("after", ens_e, meas.y[te])):
        est = ens.predict(X).mean(axis=0)
        err = np.abs(est - truth) / truth
        out[name] = {"mean_relative_error": {q: float(err[:, j].mean()) for j, q in enumerate(("d", "h", "E"))},
                     "estimates": est.tolist()}
    b = np.mean(list(out["before"]["mean_relative_error"].values()))
    a = np.mean(list(out["after"]["mean_relative_error"].values()))
    out["mean_error_before"], out["mean_error_after"] = float(b), float(a)
    out["shrink"] = float(1 - a / b) if b > 0 else 0.0
    return out


# ------------------------------------------------------------------ driver
def diagnose(meas: Measured, cands: list[fx.Effect], sim: Simulator, st: Settings | None = None) -> dict:
    st = st or Settings()
    if not cands:
        raise UserError("effects", "no candidate effects to test")
    sensor, settings = meas.sensor_model(), meas.settings()
    y0, D0, C = simulate_candidates(meas, cands, sim, sensor, settings)
    ev = evaluate(meas, y0, C, st)
    wh = where(meas, y0, D0, st)
    byname = {c.effect.name: c for c in C}
    best = byname[ev["best"]] if ev["best"] else None
    shrink = shrink_features(meas, y0, best, st) if best else None
    inv = None
    if st.inverse and best is not None and ev["outcome"] != "no significant gap":
        inv = shrink_inverse(meas, best, shrink["magnitude"], sim, sensor, settings, st)
    stage = wh["stage"]
    bm = [r for r in ev["ranking"] if r["stage"] == "mechanics"]
    bo = [r for r in ev["ranking"] if r["stage"] == "optics"]
    stage["best_mechanics_candidate"] = (bm[0]["effect"], bm[0]["explained_fraction"]) if bm else None
    stage["best_optics_candidate"] = (bo[0]["effect"], bo[0]["explained_fraction"]) if bo else None
    if inv:
        stage["inverse_own_error"] = inv["inverse_own"]["mean_relative_error"]
        stage["inverse_error_on_measured"] = inv["before"]["mean_relative_error"]
    resid_after = None
    if best is not None and "image" in wh:
        have = [i for i in range(meas.n) if meas.difference[i] is not None]
        m_best = next(r["magnitude"] for r in ev["ranking"] if r["effect"] == best.effect.name)
        Dw = best.image_at(m_best)
        if Dw is not None:
            resid_after = np.array([meas.difference[i] - Dw[i] for i in have]).mean(axis=0)
            wh["image"]["mean_residual_after"] = resid_after
    return {"measured": {"source": meas.source, "n": meas.n, "synthetic": meas.synthetic,
                         "description": meas.description, "mesh": sim.mesh, "ids": meas.ids,
                         "dhe": meas.dhe.tolist()},
            "settings": st.__dict__, "candidates": [c.effect.to_dict() for c in C],
            "baseline": y0, "evaluation": ev, "where": wh, "shrink_features": shrink, "shrink_inverse": inv,
            "simulator": dict(sim.stats, backend=sim.backend, mesh=sim.mesh)}
