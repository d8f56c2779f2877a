"""Selection: the calibrated tests, the held-out ranking, and which effects are reported
(docs/gap.md, 'Method').

χ²_c = Σ_iq ((y − f_c)/S)² over N = n · Q terms.  The gap is **significant** when the baseline's
χ²_0 > χ²_N(1 − α); a candidate **passes** when its held-out (leave-one-phantom-out, or 10-fold
for n > 15) χ² ≤ χ²_N(1 − α).  score_c = held-out χ²_c + k_c ln N; every candidate within
``Settings.ambiguity_margin`` of a passing best is reported with it (one: **explained**,
several: **ambiguous**); nothing passes: **unexplained**.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from . import effects as fx
from .fit_models import chi2, jackknife_interval, with_systematic
from .settings import Settings


def folds(n: int, seed: int) -> list[np.ndarray]:
    """The held-out folds: one phantom each for n <= 15, else 10 random folds."""
    if n <= 15:
        return [np.array([i]) for i in range(n)]
    perm = np.random.default_rng(seed).permutation(n)
    return [perm[k::10] for k in range(10)]


def evaluate(y, S0, y0, models, n: int, st: Settings, sl: dict, sys=None, spread=None) -> dict:
    """Calibrated significance, per-candidate held-out fit, ranking, ambiguity set, outcome."""
    N = y.size
    chi0 = float(chi2(y, y0, S0).sum())
    thr = float(stats.chi2.ppf(1 - st.alpha, N))
    F = folds(n, st.seed)
    rows = [_row(mdl, y, S0, F, chi0, thr, sl, sys, spread) for mdl in models]
    rows.sort(key=lambda r: r["score"])
    significant = chi0 > thr
    best = rows[0] if rows else None
    ambiguity, reported = [], {}
    if not significant:
        outcome = "no significant gap"
    elif best and best["passes"]:
        reported = reported_set([r for r in rows if r["score"] - best["score"] <= st.ambiguity_margin], rows)
        ambiguity = list(reported)
        outcome = "explained" if len(ambiguity) == 1 else "ambiguous"
    else:
        outcome = "unexplained"
    for r in rows:
        r["delta_score"] = r["score"] - best["score"]
    return {
        "chi2_baseline": chi0,
        "n_terms": N,
        "chi2_threshold": thr,
        "alpha": st.alpha,
        "reduced_chi2_baseline": chi0 / N,
        "p_value_baseline": float(stats.chi2.sf(chi0, N)),
        "significant": significant,
        "ranking": rows,
        "outcome": outcome,
        "winner": ambiguity[0] if outcome == "explained" else None,
        "ambiguous_set": ambiguity if outcome in ("explained", "ambiguous") else [],
        "reported": reported,
        "best": best["effect"] if best else None,
        "runner_up": rows[1]["effect"] if len(rows) > 1 else None,
    }


def _row(mdl, y, S0, F: list, chi0: float, thr: float, sl: dict, sys, spread) -> dict:
    """One candidate's ranking row: its held-out χ² over the folds ``F``, its fit on every
    phantom with the likelihood interval (widened by the model-error modes ``sys``) and the
    jackknife interval, and its score."""
    n, N = y.shape[0], y.size
    S = np.sqrt(S0**2 + mdl.interp**2)
    pred = np.zeros_like(y)
    th_folds = []
    for te in F:
        tr = np.setdiff1d(np.arange(n), te)
        th_k = mdl.fit(y, S, tr)
        th_folds.append(th_k)
        pred[te] = mdl.predict(th_k)[te]
    held = ((y - pred) / S) ** 2
    ssr_cv = float(held.sum())
    th = mdl.fit(y, S, np.arange(n))
    own = mdl.own_delta(th) if (spread is not None and hasattr(mdl, "own_delta")) else None
    modes = sys if own is None else [sys[0], spread * own]
    ci_lik = with_systematic(mdl, y, S, th, mdl.interval(y, S, th), modes)
    ci_jk = jackknife_interval(mdl, th, np.array(th_folds))
    ci = [(min(a[0], b[0]), max(a[1], b[1])) for a, b in zip(ci_lik, ci_jk)] if ci_jk else ci_lik
    f = mdl.predict(th)
    return {
        "effect": mdl.name,
        "members": mdl.labels,
        "stage": mdl.stage,
        "unit": mdl.unit,
        "n_params": mdl.k,
        "magnitude": [float(t) for t in th],
        "magnitude_ci": [list(c) for c in ci],
        "magnitude_ci_likelihood": [list(c) for c in ci_lik],
        "magnitude_ci_jackknife": [list(c) for c in ci_jk] if ci_jk else None,
        "nominal": mdl.nominal(),
        "units": mdl.units(),
        "ssr_cv": ssr_cv,
        "chi2_fit": float(chi2(y, f, S).sum()),
        "explained_fraction": 1.0 - ssr_cv / chi0 if chi0 > 0 else 0.0,
        "reduced_chi2_cv": ssr_cv / N,
        "passes": bool(ssr_cv <= thr),
        "p_value_cv": float(stats.chi2.sf(ssr_cv, N)),
        "chi2_cv_by_view": {k: float(held[:, s].sum()) for k, s in sl.items()},
        "score": ssr_cv + mdl.k * math.log(N),
        "at_grid_edge": mdl.at_edge(th),
        "dropped_magnitudes": getattr(getattr(mdl, "c", None), "dropped", []),
        "_model": mdl,
        "_theta": th,
        "_S": S,
    }


def isolated_member(row: dict) -> str | None:
    """The member a family's fit names alone: the only member whose 95 % interval excludes its
    nominal magnitude while every other member's interval holds its nominal (None for a single
    effect, or when no member or several are off)."""
    members = row.get("members", [])
    if len(members) < 2:
        return None
    off = [not (lo <= nom <= hi) for (lo, hi), nom in zip(row["magnitude_ci"], row["nominal"])]
    return members[off.index(True)] if sum(off) == 1 else None


def common_factor(row: dict) -> tuple[str, tuple[float, float]] | None:
    """The nested single effect a family's fit names when it moves every member by one common
    factor (``Family.common``, e.g. ``probe_moduli`` in ``probe_layers_E``): the members' 95 %
    intervals as ratios to their nominal values, [lo_l/m_l, hi_l/m_l], have a common part that
    excludes 1 (so every member is off, all by a factor the data cannot tell apart).  Returns
    (that effect, the common part), or None."""
    fam = fx.FAMILIES.get(row.get("effect"))
    if fam is None or fam.common is None or list(row.get("members", [])) != list(fam.members):
        return None
    if any(nom <= 0 for nom in row["nominal"]):
        return None
    lo = max(a / nom for (a, _), nom in zip(row["magnitude_ci"], row["nominal"]))
    hi = min(b / nom for (_, b), nom in zip(row["magnitude_ci"], row["nominal"]))
    if lo > hi or lo <= 1.0 <= hi:
        return None
    return fam.common, (float(lo), float(hi))


def reported_set(rows: list[dict], ranking: list[dict] | None = None) -> dict:
    """The reported effects of the rows that cannot be told apart (best first), by name:
    magnitude, interval, unit and the ranking row they come from.  A family whose fit isolates
    one member (:func:`isolated_member`) is reported as that member with the family's fitted
    magnitude ("via" the family): its other parameters add nothing the data ask for, so the
    nested single effect is the statement (the family's extra freedom may still fit the
    model-form error better, which is why it can outscore the member's own fit).  A name
    reported twice keeps its first (better-scored) entry.  Likewise a family whose fit moves
    all members by one factor (:func:`common_factor`) is reported as its nested common-factor
    effect, with that effect's own fit from ``ranking`` (all rows) when it was a candidate, else
    with the members' geometric-mean ratio and the common part of their intervals."""
    out: dict[str, dict] = {}
    own = {r["effect"]: r for r in (ranking or rows)}
    for r in rows:
        cf = common_factor(r)
        if cf is not None and cf[0] not in out:
            name, (lo, hi) = cf
            o = own.get(name)
            if o is not None:
                mag, ci, units = o["magnitude"], o["magnitude_ci"], o["units"]
            else:
                ratios = [t / nom for t, nom in zip(r["magnitude"], r["nominal"])]
                g = float(np.exp(np.mean(np.log(np.maximum(ratios, 1e-300)))))
                mag, ci, units = [float(np.clip(g, lo, hi))], [[lo, hi]], [fx.get(name).unit]
            out[name] = {
                "magnitude": list(mag),
                "magnitude_ci": [list(c) for c in ci],
                "members": [name],
                "units": list(units),
                "via": r["effect"],
                "via_kind": "common factor",
                "_row": o if o is not None else r,
            }
            continue
        if cf is not None:
            continue
        m = isolated_member(r)
        i = r["members"].index(m) if m is not None else 0
        name = m if m is not None else r["effect"]
        if name in out:
            continue
        out[name] = {
            "magnitude": r["magnitude"] if m is None else [r["magnitude"][i]],
            "magnitude_ci": r["magnitude_ci"] if m is None else [r["magnitude_ci"][i]],
            "members": r["members"] if m is None else [m],
            "units": r["units"] if m is None else [r["units"][i]],
            "via": r["effect"] if m is not None else None,
            "via_kind": "member" if m is not None else None,
            "_row": r,
        }
    return out
