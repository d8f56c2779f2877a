"""Where the gap lies: by view, by feature, by (d, h, E) region, by stage and by image region
(docs/gap.md, 'Method').

Relative gap (y − y0)/|y0| per feature with a bootstrap 95 % interval; the rms normalised
residual (y − y0)/S per tercile of d, h and E; the share of the gap a held-out affine
recalibration of each feature removes (optics-like) against the rest (mechanics-like); and the
mean residual image over the phantoms with its noise band sqrt(Σ_i se_i²)/n plus the per-pixel
model error, by annulus.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from . import views as vw
from .fit_models import chi2
from .measured import FEATURES, Measured
from .selection import folds
from .settings import Settings


def bootstrap_ci(values: np.ndarray, stat, B: int, rng) -> tuple[float, float]:
    """The percentile 95 % bootstrap interval of ``stat`` over B resamples (nan for n < 2)."""
    n = len(values)
    if n < 2:
        return (math.nan, math.nan)
    bs = [stat(values[rng.integers(0, n, n)]) for _ in range(B)]
    return float(np.percentile(bs, 2.5)), float(np.percentile(bs, 97.5))


def view_baselines(mv: dict, V0: dict, me: dict, st: Settings) -> dict:
    """Per view: χ² of the baseline with noise only and with noise + model error (a view table)."""
    out = {}
    for k, (v, se) in mv.items():
        S = np.sqrt(se**2 + me["sigma"][k] ** 2)
        S = np.maximum(S, 1e-12 * np.maximum(np.abs(V0[k]), 1e-300))
        Sn = np.maximum(se, 1e-12 * np.maximum(np.abs(V0[k]), 1e-300))
        N = v.size
        c = float(chi2(v, V0[k], S).sum())
        out[k] = {
            "n_terms": N,
            "chi2_noise_only": float(chi2(v, V0[k], Sn).sum()),
            "chi2": c,
            "threshold": float(stats.chi2.ppf(1 - st.alpha, N)),
            "significant": bool(c > stats.chi2.ppf(1 - st.alpha, N)),
            "model_error_relative_median": np.median(
                me["sigma"][k] / np.maximum(np.abs(V0[k]), 1e-300), axis=0
            ).tolist(),
            "noise_relative_median": np.median(se / np.maximum(np.abs(v), 1e-300), axis=0).tolist(),
        }
    return out


def where(meas: Measured, mv: dict, V0: dict, D0, me: dict, st: Settings) -> dict:
    """Where the gap lies: by feature, by (d, h, E) region, by stage, by image region."""
    y = meas.y
    y0 = V0["features"]
    S = np.sqrt(meas.se**2 + me["sigma"]["features"] ** 2)
    S = np.maximum(S, 1e-12)
    rng = np.random.default_rng(st.seed + 1)
    rel = (y - y0) / np.where(np.abs(y0) > 0, np.abs(y0), 1.0)
    r = (y - y0) / S
    by_feature = {
        k: {
            "relative_gap_mean": float(rel[:, j].mean()),
            "relative_gap_ci": bootstrap_ci(rel[:, j], np.mean, st.bootstrap, rng),
            "noise_units_rms": float(np.sqrt(np.mean(r[:, j] ** 2))),
            "noise_floor_relative": float(np.median(meas.se[:, j] / np.maximum(np.abs(y[:, j]), 1e-300))),
            "model_error_relative": float(
                np.median(me["sigma"]["features"][:, j] / np.maximum(np.abs(y0[:, j]), 1e-300))
            ),
        }
        for j, k in enumerate(FEATURES)
    }
    rms_i = np.sqrt(np.mean(r**2, axis=1))
    by_region = {name: _terciles(meas.dhe[:, q], rms_i, rel, st, rng) for q, name in enumerate(("d", "h", "E"))}
    affine_share = _affine_share(y, y0, S, r, st)
    out = {
        "by_feature": by_feature,
        "by_region": by_region,
        "per_phantom_rms_noise_units": rms_i.tolist(),
        "stage": {"optics_like_affine_share": affine_share, "mechanics_like_share": 1 - affine_share},
        "relative_gap": rel,
        "normalised_residual": r,
    }
    if meas.has_images and D0 is not None and meas.difference[0].shape == D0[0].shape:
        out["image"] = image_residual(meas, D0, me, None)
    return out


def _terciles(v: np.ndarray, rms_i: np.ndarray, rel: np.ndarray, st: Settings, rng) -> list[dict]:
    """The rms normalised residual and relative gap of the phantoms in each tercile of ``v``."""
    edges = np.quantile(v, [0, 1 / 3, 2 / 3, 1])
    bins = []
    for b in range(3):
        sel = (v >= edges[b]) & ((v <= edges[b + 1]) if b == 2 else (v < edges[b + 1]))
        if sel.sum() == 0:
            continue
        bins.append(
            {
                "range": [float(edges[b]), float(edges[b + 1])],
                "n": int(sel.sum()),
                "rms_noise_units": float(np.sqrt(np.mean(rms_i[sel] ** 2))),
                "rms_ci": bootstrap_ci(rms_i[sel], lambda a: float(np.sqrt(np.mean(a**2))), st.bootstrap, rng),
                "relative_gap_mean": {k: float(rel[sel, j].mean()) for j, k in enumerate(FEATURES)},
            }
        )
    return bins


def _affine_share(y: np.ndarray, y0: np.ndarray, S: np.ndarray, r: np.ndarray, st: Settings) -> float:
    """The share of Σ r² that a held-out affine recalibration y ≈ a_j y0 + b_j of each feature
    removes (an optics-like gap is affine in the features)."""
    n = y.shape[0]
    ssr0 = float(np.sum(r**2))
    held = 0.0
    for te in folds(n, st.seed):
        tr = np.setdiff1d(np.arange(n), te)
        pred = np.empty((len(te), 3))
        for j in range(3):
            A = np.column_stack([y0[tr, j], np.ones(len(tr))])
            coef, *_ = np.linalg.lstsq(A, y[tr, j], rcond=None)
            pred[:, j] = coef[0] * y0[te, j] + coef[1]
        held += float(np.sum(((y[te] - pred) / S[te]) ** 2))
    return float(np.clip(1 - held / ssr0, 0, 1)) if ssr0 > 0 else 0.0


def image_residual(meas: Measured, Dsim, me: dict, sensor) -> dict:
    """Mean residual map over the phantoms with its noise band, and its annulus table."""
    n = meas.n
    R = np.array([meas.difference[i] - Dsim[i] for i in range(n)])
    if all(s is not None for s in meas.difference_se):
        se = np.sqrt(np.sum([s**2 for s in meas.difference_se], axis=0)) / n
        noise_kind = "per-pixel, from the frame scatter"
    else:
        ring = np.zeros(R.shape[1:], bool)
        w = max(2, R.shape[1] // 10)
        ring[:w, :] = ring[-w:, :] = ring[:, :w] = ring[:, -w:] = True
        se = np.full(R.shape[1:], float(np.std(R[:, ring])) / math.sqrt(n))
        noise_kind = "uniform, from the window's outer ring"
    mer = np.mean(me["image_sigma"], axis=0)
    band = np.sqrt(se**2 + mer**2)
    mean = R.mean(axis=0)
    pix = meas.sensor_model().pixel_mm
    rings = []
    for a, b, msk in zip(vw.EDGES[:-1], vw.EDGES[1:], vw._bins(mean.shape, pix)):
        if not msk.any():
            continue
        n_eff = max(1.0, msk.sum() / (4 * math.pi * max(meas.settings().smooth_px, 0.5) ** 2))
        bnd = float(np.sqrt((se[msk].mean() / math.sqrt(n_eff)) ** 2 + mer[msk].mean() ** 2))
        rings.append(
            {
                "r_mm": [a, b],
                "mean_residual": float(mean[msk].mean()),
                "band": bnd,
                "noise_units": float(mean[msk].mean() / bnd) if bnd > 0 else 0.0,
            }
        )
    return {
        "n": n,
        "mean_residual": mean,
        "band": band,
        "z": mean / np.maximum(band, 1e-300),
        "noise_kind": noise_kind,
        "mean_measured": np.mean(meas.difference, axis=0),
        "mean_simulated": Dsim.mean(axis=0),
        "rings": rings,
        "max_abs_z": float(np.max(np.abs(mean) / np.maximum(band, 1e-300))),
        "noise_px": float(np.median(se) * math.sqrt(n)),
        "pixel_mm": float(pix),
    }
