"""Selection: the calibrated tests, the held-out ranking, and which effects are reported
(docs/gap.md, 'Method' and 'Model-form level').

χ²_c = Σ_i |L_i⁻¹ (y_i − f_c,i)|² over N = n · Q terms, Σ_i = L_i L_iᵀ the phantom's error
covariance: noise, the measured discretisation error and the model-form level
(:mod:`elastimap.gap.model_form`).  The gap is **significant** when the baseline's
χ²_0 > χ²_N(1 − α); a candidate **passes** when its held-out (leave-one-phantom-out, or 10-fold
for n > 15) χ² ≤ χ²_N(1 − α).  score_c = held-out χ²_c + k_c ln N.  When the gap is significant,
pairs of single effects (two effects at once, k = 2) are ranked beside them and lead only when no
single effect or family passes (``Settings.pair_beside_single``), both their effects are needed, their
intervals lie inside their grids and they beat every single effect and family by more than
``Settings.ambiguity_margin`` (sparse: one effect unless the data ask for two); a single best is no
confident answer when a pair holding it beats it by that margin and moves its magnitude outside its
interval (:func:`second_effect`: a second effect may be present).  Every candidate of the leader's kind
the phantoms do not tell from a passing best (:func:`told_apart`: within the margin, or -- with the model-form
level -- a passing candidate whose deficit is within the noise z_{1−α} 2 √D_ab of the χ² difference of the two
fits) is reported with it (one: **explained**, several: **ambiguous**), provided what the best leaves is at
the model-form level (its modes' mean within :data:`~elastimap.identify.discrepancy.BEYOND` × τ₀)
and, with the model-form level, its fit is neither pinned at the end of its range nor holding its
nominal within its interval (:func:`_unsure`), nor within that noise of a passing family held at its
members' grid ends (a shadow, :func:`held_at_grid_ends`), nor with its whole interval beyond the
magnitudes the library was built for (:func:`beyond_design`), nor moved by a second effect
(:func:`second_effect`); otherwise, or when nothing passes: **unexplained**.  The three verdicts a user acts on
(:func:`verdict`): "no gap beyond the model-form level", "explained", "unexplained".
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from . import effects as fx
from .fit_models import Pair, Single, chi2, jackknife_interval, with_systematic
from .model_form import Metric, residual_level
from .settings import Settings

#: the three verdicts of a diagnosis (docs/gap.md, 'The three outcomes'), by the outcome they summarise
VERDICTS = {
    "no significant gap": "no gap beyond the model-form level",
    "explained": "explained",
    "ambiguous": "explained",
    "unexplained": "unexplained",
}


def verdict(outcome: str, model_form: bool = True) -> str:
    """The verdict a user acts on for an ``outcome`` ("no significant gap", "explained",
    "ambiguous", "unexplained"); an ambiguous set is explained by one of its members."""
    v = VERDICTS[outcome]
    if not model_form and outcome == "no significant gap":
        return "no gap beyond the model's own tolerance"
    return v


def folds(n: int, seed: int) -> list[np.ndarray]:
    """The held-out folds: one phantom each for n <= 15, else 10 random folds."""
    if n <= 15:
        return [np.array([i]) for i in range(n)]
    perm = np.random.default_rng(seed).permutation(n)
    return [perm[k::10] for k in range(10)]


def pairs(models: list, rows: list[dict], st: Settings, y0: np.ndarray) -> list:
    """Two effects at once: a :class:`~elastimap.gap.fit_models.Pair` of each of the best
    ``st.pair_top`` single effects by score with every other single effect (not two members of one
    family, which the family holds).  The second effect need not rank high alone: a softer
    background beside a softer probe layer fits badly alone and is found only beside it."""
    if st.pair_top < 1:
        return []
    byname = {m.name: m for m in models if isinstance(m, Single)}
    order = [r["effect"] for r in rows if r["effect"] in byname]
    fam_of = {n: f.name for f in fx.FAMILIES.values() for n in f.members}
    out, seen = [], set()
    for na in order[: st.pair_top]:
        for nb in order:
            key = frozenset((na, nb))
            if na == nb or key in seen or (fam_of.get(na) is not None and fam_of.get(na) == fam_of.get(nb)):
                continue
            seen.add(key)
            out.append(Pair(byname[na], byname[nb], y0))
    return out


def _may_beat(pair, y: np.ndarray, S0: Metric, lead: float) -> bool:
    """Whether a pair is worth its held-out fit: its fit on every phantom, charged k ln N, scores
    below the best single effect or family ``lead`` (a held-out χ² is not below the fit's own, so a
    pair that fails this can neither lead nor move the best; it saves the folds' fits of the many
    pairs formed)."""
    S = S0.plus(pair.interp)
    th = pair.fit(y, S, np.arange(y.shape[0]))
    return float(chi2(y, pair.predict(th), S).sum()) + pair.k * math.log(y.size) < lead


def both_needed(row: dict) -> bool:
    """Whether every member of a pair row is needed: its 95 % interval excludes its nominal."""
    return all(not (lo <= nom <= hi) for (lo, hi), nom in zip(row["magnitude_ci"], row["nominal"]))


def inside_grids(row: dict) -> bool:
    """Whether every member's 95 % interval lies inside its effect's grid (``design_range``), short of
    both ends by more than 10⁻⁶ of the grid's width.  A pair's members are held inside their grids
    (``Composed.bounds``, never extended), so an interval that reaches a grid's end is one the
    library cut short: the data may ask for more of it than the library holds -- what a pair of
    look-alikes does when it stands in for an effect outside the library (chosen on the seed-10
    draws: docs/gap.md, 'Two effects at once (SYNTHETIC)')."""
    return all(
        lo > a + 1e-6 * (b - a) and hi < b - 1e-6 * (b - a)
        for (lo, hi), (a, b) in zip(row["magnitude_ci"], row["design_range"])
    )


def _pair_charge(row: dict, st: Settings) -> float:
    """What a pair row is charged in the ordering beyond its score: the ambiguity margin when both
    its effects are needed and its intervals lie inside its members' grids (:func:`inside_grids`),
    else infinity (a pair with a member at its nominal is that member's single effect, whose own row
    stands for it; its larger interpolation error would flatter it)."""
    row["both_needed"] = both_needed(row)
    row["inside_grids"] = inside_grids(row)
    return st.ambiguity_margin if row["both_needed"] and row["inside_grids"] else math.inf


def needed(row: dict) -> bool:
    """Whether a row's fit needs its effect: some member's 95 % interval excludes its nominal."""
    return any(not (lo <= nom <= hi) for (lo, hi), nom in zip(row["magnitude_ci"], row["nominal"]))


def _unsure(row: dict) -> bool:
    """With the model-form level, a passing best is no confident answer when its fit is pinned at the
    end of its range, or when its interval holds the nominal (no effect) although the gap is
    significant (chosen on variant worlds: docs/gap.md, 'Method', 'Out-of-library safety')."""
    return bool(row["at_grid_edge"]) or not needed(row)


def held_at_grid_ends(row: dict) -> bool:
    """Whether a row is a family (several single effects fitted together, not a pair) whose fit is
    held at the end of a member's grid.  A family's members are held inside their effects' grids
    (``Composed.bounds``, the library's design range, never extended), so such a fit says the data
    ask for more of it than the library holds -- unlike a single effect, whose range is extended
    up to its physical limits, so that a single effect at its end is at physics' end, not the
    library's."""
    return len(row.get("members", [])) > 1 and not row.get("pair") and bool(row["at_grid_edge"])


def beyond_design(row: dict) -> bool:
    """Whether a row's 95 % interval lies wholly outside the magnitudes the library was built for
    (some member's interval entirely below or above its effect's grid, ``design_range``).  A single
    effect's range is extended beyond its grid when its fit sits at the grid's end, so that an
    effect just past the grid is found (its interval then reaches back to the grid); an interval
    that excludes the whole grid says the data want a magnitude the library's design did not
    expect -- what a look-alike does when it stands in for an effect the library does not hold,
    by moving further than the real effect would."""
    return any(hi < a or lo > b for (lo, hi), (a, b) in zip(row["magnitude_ci"], row["design_range"]))


def second_effect(best: dict, rows: list[dict], st: Settings) -> dict | None:
    """The pair row that says a second effect may be present beside a single best ``best`` (None when
    none does): a pair holding the best's effect that passes, is not pinned at the end of its range,
    beats the best's score by more than ``st.ambiguity_margin`` (its score already charged for the
    second effect's parameter, ln N) and fits the best's effect at a magnitude **outside the best's
    own 95 % interval**.  The single answer's magnitude is then no confident statement: the data fit
    clearly better with a second effect beside it, and that moves it (docs/gap.md, 'Two effects at
    once').  Of several such pairs, the best-scored."""
    if best.get("pair") or len(best["members"]) != 1:
        return None
    name, (lo, hi) = best["effect"], best["magnitude_ci"][0]
    found = [
        r
        for r in rows
        if r.get("pair")
        and name in r["members"]
        and r["passes"]
        and not r["at_grid_edge"]
        and best["score"] - r["score"] > st.ambiguity_margin
        and not (lo <= r["magnitude"][r["members"].index(name)] <= hi)
    ]
    return min(found, key=lambda r: r["score"]) if found else None


def _second_summary(best: dict | None, pair: dict | None) -> dict | None:
    """What ``evaluation.second_effect`` records: the pair, its Δscore to the best, the best's
    magnitude in the pair and its interval there, and the second effect's."""
    if best is None or pair is None:
        return None
    i = pair["members"].index(best["effect"])
    return {
        "pair": pair["effect"],
        "delta_score": float(best["score"] - pair["score"]),
        "effect": best["effect"],
        "magnitude_in_pair": pair["magnitude"][i],
        "magnitude_ci_in_pair": list(pair["magnitude_ci"][i]),
        "second": pair["members"][1 - i],
        "second_magnitude": pair["magnitude"][1 - i],
        "second_magnitude_ci": list(pair["magnitude_ci"][1 - i]),
        "second_needed": bool(
            needed({"magnitude_ci": [pair["magnitude_ci"][1 - i]], "nominal": [pair["nominal"][1 - i]]})
        ),
    }


def told_apart(a: dict, b: dict, S: Metric, st: Settings, model_form: bool = True) -> dict:
    """Whether these phantoms tell candidate row ``b`` from the best row ``a`` (docs/gap.md,
    'Look-alikes').  They do not when

    * **margin**: Δscore = score_b − score_a ≤ ``st.ambiguity_margin`` (a likelihood ratio below 10), or
    * **within the noise of Δscore** (with the model-form level only): b passes, would be a
      confident answer itself (:func:`_unsure` false), and its deficit is within what the error
      alone makes of a χ² difference between the two fitted predictions.  With whitened data
      y = μ + e, e ~ N(0, I), χ²_b − χ²_a = |f_b − μ|² − |f_a − μ|² + 2 eᵀ(f_a − f_b), whose noise
      has the sd 2 √D_ab,

          D_ab = Σ_i |L_i⁻¹ (f_a,i(θ̂_a) − f_b,i(θ̂_b))|²     (Σ_i = L_i L_iᵀ: noise, discretisation,
                                                             model-form level)

      so a leads b only when Δscore > z_{1−α} · 2 √D_ab (one-sided, α = ``st.alpha``).  The fixed
      margin is right for near-identical predictions; two effects whose predictions differ by a
      large D_ab (a different shape over the phantoms) trade χ² differences far larger than 4.6 on
      the error alone, and on data whose model-form difference is structured over the phantoms,
      more than that.

    * **shadow** (with the model-form level only): b passes, its deficit is within that noise, and b
      is a family held at its members' grid ends (:func:`held_at_grid_ends`).  Then the best is not
      told apart from an answer beyond what the library holds, so it is no confident answer
      (:func:`evaluate`: **unexplained**; docs/gap.md, 'Look-alikes').

    Returns {"delta_score", "separation" (D_ab), "noise" (2 √D_ab), "margin", "within_noise",
    "shadow", "told_apart"}."""
    dscore = float(b["score"] - a["score"])
    sep = float(S.chi2(a["_model"].predict(a["_theta"]), b["_model"].predict(b["_theta"])).sum())
    noise = 2.0 * math.sqrt(max(sep, 0.0))
    margin = dscore <= st.ambiguity_margin
    close = model_form and bool(b["passes"]) and dscore <= stats.norm.ppf(1 - st.alpha) * noise
    within = close and not _unsure(b)
    return {
        "delta_score": dscore,
        "separation": sep,
        "noise": noise,
        "margin": bool(margin),
        "within_noise": bool(within),
        "shadow": bool(close and held_at_grid_ends(b)),
        "told_apart": not (margin or within),
    }


def evaluate(y, S0, y0, models, n: int, st: Settings, sl: dict, sys=None, spread=None, mf: dict | None = None) -> dict:
    """Calibrated significance, per-candidate held-out fit, ranking (pairs beside the single effects
    when the gap is significant), ambiguity set, outcome and verdict.  ``S0``: the error model (a
    :class:`~elastimap.gap.model_form.Metric`, or the diagonal sd); ``mf``: the model-form level
    (:func:`elastimap.gap.model_form.level`; None: the closed-world budget)."""
    S0 = S0 if isinstance(S0, Metric) else Metric(S0)
    N = y.size
    chi0 = float(chi2(y, y0, S0).sum())
    thr = float(stats.chi2.ppf(1 - st.alpha, N))
    F = folds(n, st.seed)
    coherent = mf["coherent"] if mf else []
    rows = [_row(mdl, y, S0, F, chi0, thr, sl, sys, spread, coherent) for mdl in models]
    rows.sort(key=lambda r: r["score"])
    significant = chi0 > thr
    if significant:  # two effects at once, weighed beside the single effects and families
        lead, alone = rows[0]["score"], rows[0]["passes"]
        rows += [
            _row(p, y, S0, F, chi0, thr, sl, sys, spread, coherent)
            for p in pairs(models, rows, st, y0)
            if _may_beat(p, y, S0, lead)
        ]
        # a pair leads only when both its effects are needed (each member's interval excludes its
        # nominal) and it beats every single effect and family by more than the margin
        # (beside a passing single effect or family only with ``st.pair_beside_single``)
        held = alone and not st.pair_beside_single
        rows.sort(
            key=lambda r: r["score"] + (_pair_charge(r, st) + (math.inf if held else 0.0) if r.get("pair") else 0.0)
        )
    best = rows[0] if rows else None
    ambiguity, reported, level, shadows, second = [], {}, None, [], None
    if best is not None and mf is not None:  # what the best leaves (no gap: what the baseline leaves)
        f, Sb = (best["_model"].predict(best["_theta"]), best["_S"]) if significant else (y0, S0)
        level = residual_level(y, f, Sb, mf["phi"], mf["disc"])
        level["of"] = best["effect"] if significant else "baseline"
    if not significant:
        outcome = "no significant gap"
    elif (
        best
        and best["passes"]
        and not (level and level["beyond"])
        and not (mf is not None and (_unsure(best) or beyond_design(best)))
    ):
        kind = bool(best.get("pair"))
        # pairs of the best's kind: only those whose both effects are needed (one with a member at its
        # nominal is that member's single effect)
        same = [
            r
            for r in rows[1:]
            if bool(r.get("pair")) == kind and (not kind or (r["both_needed"] and r["inside_grids"]))
        ]
        for r in same:
            r["vs_best"] = told_apart(best, r, S0, st, mf is not None)
        shadows = [r["effect"] for r in same if r["vs_best"]["shadow"]]
        second = second_effect(best, rows, st)
        if shadows or second:  # not told apart from an answer beyond the library's grids, or a
            outcome = "unexplained"  # second effect beside the best moves the best's magnitude
        else:
            close = [best] + [r for r in same if not r["vs_best"]["told_apart"]]
            reported = reported_set(close, rows)
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
        "model_form": mf is not None,
        "model_form_note": mf["note"] if mf else "none: noise and the measured discretisation error only",
        "ranking": rows,
        "outcome": outcome,
        "verdict": verdict(outcome, mf is not None),
        "residual_level": level,
        "winner": ambiguity[0] if outcome == "explained" else None,
        "ambiguous_set": ambiguity if outcome in ("explained", "ambiguous") else [],
        "reported": reported,
        "best": best["effect"] if best else None,
        "shadowed_by": shadows,
        "second_effect": _second_summary(best, second),
        "beyond_design": bool(significant and mf is not None and best is not None and beyond_design(best)),
        "runner_up": rows[1]["effect"] if len(rows) > 1 else None,
    }


def _row(mdl, y, S0: Metric, F: list, chi0: float, thr: float, sl: dict, sys, spread, coherent=()) -> dict:
    """One candidate's ranking row: its held-out χ² over the folds ``F``, its fit on every
    phantom with the likelihood interval (widened by the model-error modes ``sys`` and the coherent
    model-form modes ``coherent``) and the jackknife interval, and its score."""
    n, N = y.shape[0], y.size
    S = S0.plus(mdl.interp)
    pred = np.zeros_like(y)
    th_folds = []
    for te in F:
        tr = np.setdiff1d(np.arange(n), te)
        th_k = mdl.fit(y, S, tr)
        th_folds.append(th_k)
        pred[te] = mdl.predict(th_k)[te]
    held = S.z(y - pred) ** 2
    ssr_cv = float(held.sum())
    th = mdl.fit(y, S, np.arange(n))
    own = mdl.own_delta(th) if (spread is not None and hasattr(mdl, "own_delta")) else None
    mesh = [] if sys is None else (list(sys) if isinstance(sys, (list, tuple)) else [sys])
    modes = (mesh if own is None else [mesh[0], spread * own]) + list(coherent)
    ci_lik = with_systematic(mdl, y, S, th, mdl.interval(y, S, th), modes)
    ci_jk = jackknife_interval(mdl, th, np.array(th_folds))
    ci = [(min(a[0], b[0]), max(a[1], b[1])) for a, b in zip(ci_lik, ci_jk)] if ci_jk else ci_lik
    f = mdl.predict(th)
    return {
        "effect": mdl.name,
        "pair": isinstance(mdl, Pair),
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
        "design_range": [[float(m.effect.lo), float(m.effect.hi)] for m in getattr(mdl, "members", [mdl])],
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
