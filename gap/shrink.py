"""How far the gap shrinks with the best candidate: on withheld phantoms (every third), and in
(d, h, E) after retraining the inverse on simulations with the effect (docs/gap.md, 'Method').
"""

from __future__ import annotations

import numpy as np
from scipy.stats import qmc

from elastimap.dataset.schema import THICKNESS, depth_range
from elastimap.errors import UserError

from .candidates import phantom_params
from .measured import FEATURES, Measured
from .model_form import Metric
from .settings import Settings
from .simulate import Simulator, base_params
from .views import sim_views


def withheld_split(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(fit phantoms, withheld phantoms): every third phantom is withheld."""
    te = np.arange(n)[1::3]
    return np.setdiff1d(np.arange(n), te), te


def shrink_features(meas: Measured, y, y0, S, mdl, names) -> dict:
    """Gap before/after on withheld phantoms, magnitude fitted on the rest (decision view), and
    the relative gap of the three features."""
    tr, te = withheld_split(meas.n)
    th = mdl.fit(y, S, tr)
    f = mdl.predict(th)
    z = S[te].z if isinstance(S, Metric) else (lambda r: r / S[te])
    before = float(np.sqrt(np.mean(z(y[te] - y0[te]) ** 2)))
    after = float(np.sqrt(np.mean(z(y[te] - f[te]) ** 2)))
    ff = mdl.predict(th, ["features"])
    yf = meas.y
    y0f = mdl.predict(np.asarray(mdl.nominal(), float), ["features"])
    relb = np.mean(np.abs(yf[te] - y0f[te]) / np.abs(yf[te]), axis=0)
    rela = np.mean(np.abs(yf[te] - ff[te]) / np.abs(yf[te]), axis=0)
    return {
        "fit_phantoms": [meas.ids[i] for i in tr],
        "withheld": [meas.ids[i] for i in te],
        "magnitude": [float(t) for t in th],
        "views": list(names),
        "rms_noise_units_before": before,
        "rms_noise_units_after": after,
        "shrink": 1 - after / before if before > 0 else 0.0,
        "relative_gap_before": {k: float(relb[j]) for j, k in enumerate(FEATURES)},
        "relative_gap_after": {k: float(rela[j]) for j, k in enumerate(FEATURES)},
    }


def training_design(meas: Measured, n: int, seed: int, aspect_hi: float = 1.0) -> np.ndarray:
    """LHS of (d, h, E) over the phantoms' bounding box (E log-uniform), depths kept valid."""
    u = qmc.LatinHypercube(d=3, rng=np.random.default_rng(seed)).random(n)
    lo, hi = meas.dhe.min(0), meas.dhe.max(0)
    d = lo[0] + u[:, 0] * (hi[0] - lo[0])
    thickness = meas.sensor_description.tissue.thickness if meas.sensor_description else THICKNESS
    a, b = depth_range(d, thickness, aspect_hi)
    hl, hh = np.maximum(a, lo[1]), np.minimum(b, hi[1])
    hh = np.maximum(hh, hl)
    h = hl + u[:, 1] * (hh - hl)
    E = np.exp(np.log(lo[2]) + u[:, 2] * (np.log(hi[2]) - np.log(lo[2])))
    return np.column_stack([d, h, E])


def _train_inverse(X, T, st: Settings):
    """An ensemble inverse (camera features -> (d, h, E)) trained on features X, targets T."""
    # torch comes with training.api: imported only when an inverse is retrained (seconds of start-up)
    import pandas as pd

    from elastimap.training.api import fit_ensemble

    df = pd.DataFrame({"O1": X[:, 0], "O2": X[:, 1], "O3": X[:, 2], "d": T[:, 0], "h": T[:, 1], "E": T[:, 2]})
    return fit_ensemble(df, algo="scg", repeats=st.train_repeats, epochs=st.train_epochs, hidden=(10,), seed=st.seed)


def shrink_inverse(meas: Measured, mdl, th, sim: Simulator, sensor, settings, st: Settings) -> dict:
    """(d, h, E) error on the withheld phantoms: inverse trained on baseline sims vs on sims with
    the effect at ``th`` (camera features -> (d, h, E), ``fit_ensemble`` SCG)."""
    tr, te = withheld_split(meas.n)
    aspect_hi = max(
        1.0, max(float(t) for t, n in zip(th, mdl.labels) if n == "aspect") if "aspect" in mdl.labels else 1.0
    )
    T = training_design(meas, st.n_train, st.seed, aspect_hi)
    p_base = [base_params(sim.mesh, *t, sensor=meas.sensor_description) for t in T]
    p_eff = [mdl.params_at(p, th) for p in p_base]
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
    Vb, _ = sim_views(recs[:k], sensor, settings)
    Ve, _ = sim_views(recs[k:], mdl.sensor_at(sensor, th), settings)
    Xb, Xe = Vb["features"], Ve["features"]
    fin = np.all(np.isfinite(Xb), axis=1) & np.all(np.isfinite(Xe), axis=1)
    Xb, Xe, Tk = Xb[fin], Xe[fin], T[ok][fin]
    ens_b = _train_inverse(Xb, Tk, st)
    ens_e = _train_inverse(Xe, Tk, st)
    truth = meas.dhe[te]
    out = {
        "n_train": int(fin.sum()),
        "n_failed_solves": int(k - fin.sum()),
        "withheld": [meas.ids[i] for i in te],
        "magnitude": [float(t) for t in th],
    }
    own, _ = sim_views(sim.run(phantom_params(meas.subset(te), sim.mesh)), sensor, settings)
    for name, ens, X in (
        ("inverse_own", ens_b, own["features"]),
        ("before", ens_b, meas.y[te]),
        ("after", ens_e, meas.y[te]),
    ):
        est = ens.predict(X).mean(axis=0)
        err = np.abs(est - truth) / truth
        out[name] = {
            "mean_relative_error": {q: float(err[:, j].mean()) for j, q in enumerate(("d", "h", "E"))},
            "estimates": est.tolist(),
        }
    b = np.mean(list(out["before"]["mean_relative_error"].values()))
    a = np.mean(list(out["after"]["mean_relative_error"].values()))
    out["mean_error_before"], out["mean_error_after"] = float(b), float(a)
    out["shrink"] = float(1 - a / b) if b > 0 else 0.0
    return out
