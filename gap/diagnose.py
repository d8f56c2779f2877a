"""The diagnosis: is there a gap beyond the model's own tolerance, which effect(s) explain it,
where it lies, how far it shrinks, and which measurement would tell look-alikes apart.

Notation: phantom i = 1..n with known (d, h, E)_i; for each phantom a vector of measured
quantities y_iq from one or more *views* (:mod:`elastimap.gap.views`: the three camera
features, the radial profile of the camera difference image, the plate force when measured)
with standard errors se_iq from the frame scatter; the baseline model's prediction y0_iq and
candidate c's prediction f_c(θ)_iq (θ its magnitude(s)).

* **Model error, measured.**  Every phantom's baseline is also solved on the next finer mesh
  level (``error_mesh``).  With Δ_iq = y0_iq(h) − y0_iq(h/r) and the refinement ratio r of the
  mesh sizes, the Richardson estimate of the discretisation error of the diagnosis mesh is
  σ_disc,iq = κ · max(|Δ_iq|, median_i(|Δ_iq| / |y0_iq|) · |y0_iq|), κ = 1 / (1 − r^(−p)),
  with the convergence order p per view (``order_image`` for features and profile,
  ``order_force`` for the force; measured on three levels, see docs/gap.md, 'Method').  The median floor
  keeps a quantity whose two-level difference happens to cross zero from getting no error.
  Without a second level the error is the assumed floor ρ |y0| (``model_floor``; the report
  says "assumed").  Each candidate adds its magnitude-interpolation error σ_int,c (adaptive
  mechanics effects: the emulator's measured miss at its last refinement solve; full grids: the
  leave-one-magnitude-out PCHIP miss of the sweep / 4).  Total, per phantom and quantity:
  S_iq² = se_iq² + σ_disc,iq² + σ_int,c,iq²  (diagonal covariance).
* **Adaptive magnitudes** (:func:`elastimap.gap.adaptive.refine`).  A mechanics effect is solved at its nominal and one
  sensitivity magnitude; while the gap is significant, the leading candidates are solved again at
  their fitted magnitude (every phantom) and the emulator's miss there is their interpolation error.
  An effect that costs no solves (optics: the camera alone; a linear model's plate travel: the
  baseline scaled) is rendered exactly at its fit the same way, so no candidate's fit rests on
  interpolation where it matters.
* **Calibrated tests.**  χ²_c = Σ_iq ((y − f_c)/S)² over N = n · Q terms.  The gap is
  **significant** when the baseline's χ²_0 > χ²_N(1 − α) (α = ``alpha``, 1 %), i.e. beyond
  the noise *and* the model's own tolerance.  A candidate **passes** when its held-out
  (leave-one-phantom-out, or 10-fold for n > 15) χ² ≤ χ²_N(1 − α).  α is fixed before any
  data are seen; nothing is tuned on the data scored.
* **Fit and intervals.**  Single effects: θ̂ minimises χ² over a dense PCHIP interpolation of
  the sweep; 95 % interval {θ : χ²(θ) − χ²_min ≤ 3.84 · c}, c = max(1, χ²_min / (N − 1)).
  Families (k parameters, composed f = y0 + Σ_l (f_l(θ_l) − y0)): coordinate descent on the
  members' dense grids; interval ±1.96 · sqrt(c · [2 H⁻¹]_ll) from the numerical Hessian H.
* **Selection and ambiguity.**  score_c = held-out χ²_c + k_c ln N.  If the best candidate
  passes, every candidate within ``ambiguity_margin`` (Δscore ≤ 2 ln 10 = 4.6, a likelihood
  ratio below 10) of it is reported with it, and with the model-form level every passing
  look-alike whose deficit is within the noise of the two fits' χ² difference
  (:func:`elastimap.gap.selection.told_apart`): one → **explained**, several → **ambiguous**
  ("cannot be told apart with these phantoms").  Nothing passes → **unexplained**.  A family
  in the set whose fit moves one member only is reported as that member, one that moves all
  members by one factor as its nested common-factor effect (:func:`elastimap.gap.selection.reported_set`).
* **What resolves an ambiguity** (:func:`elastimap.gap.propose.propose`): the predicted separation in noise units
  sqrt(Σ ((f_a − f_b) / S)²) of every pair of the set for (i) the plate force at the same
  phantoms (force gauge error ``force_noise`` relative, plus the force model error), (ii) a
  second indentation depth (solved) and (iii) new phantoms in the design box, predicted by a
  linear emulator of z_c = (f_c − y0)/S in (ln d, h, ln E) over the measured phantoms and
  checked with solves at the best proposal.
* **Where**: by view and feature (relative gap, bootstrap CI), by region of (d, h, E), by
  stage (affine-recalibration share), by image region (mean residual map and annuli with the
  noise band sqrt(Σ_i se_i²)/n plus the per-pixel model error).
* **Shrink**: on withheld phantoms (every third) before/after, and (d, h, E) after retraining the
  inverse (``elastimap.training.api.fit_ensemble``) for a single-effect winner.

This module is the driver; each step lives in its own module, in the order it runs:
:mod:`~elastimap.gap.candidates` (solve the baseline and the candidates' magnitudes),
:mod:`~elastimap.gap.model_error` (measure and extrapolate the discretisation error),
:mod:`~elastimap.gap.adaptive` (solve again near the fits), :mod:`~elastimap.gap.fit_models`
(fit and intervals), :mod:`~elastimap.gap.selection` (tests, ranking, reported set),
:mod:`~elastimap.gap.where`, :mod:`~elastimap.gap.propose`, :mod:`~elastimap.gap.shrink`.
Settings: :mod:`~elastimap.gap.settings`.
"""

from __future__ import annotations

import time
from contextlib import contextmanager

import numpy as np

from elastimap.errors import UserError

from . import effects as fx
from .adaptive import refine
from .candidates import Candidate, needs_solves, phantom_params, simulate_candidates
from .fit_models import build_models, systematic_modes
from .measured import FEATURES, Measured, measured_views
from .model_error import model_error, richardson_correct
from .model_form import Metric, level
from .propose import propose
from .selection import evaluate
from .settings import Settings
from .shrink import shrink_features, shrink_inverse
from .simulate import Simulator
from .views import EDGES, cat, decision_views, slices
from .where import image_residual, view_baselines, where


def diagnose(
    meas: Measured,
    cands: list[fx.Effect],
    sim: Simulator,
    st: Settings | None = None,
    sim_fine: Simulator | None = None,
) -> dict:
    """The whole diagnosis.  ``sim_fine``: the simulator of the next finer mesh level for the
    measured model error (None: the assumed floor ``model_floor``).  The result carries the
    solve seconds by effect ("solve_seconds_by_effect") and the seconds by stage ("timing")."""
    t0 = time.perf_counter()
    st = st or Settings()
    if not cands:
        raise UserError("effects", "no candidate effects to test")
    sensor, settings = meas.sensor_model(), meas.settings()
    solved0 = sim.stats["solved"]
    timing: dict[str, float] = {}
    with _timed(timing, "candidates"):
        V0, D0, C, base_seconds = simulate_candidates(meas, cands, sim, sensor, settings, adaptive=st.adaptive)
    with _timed(timing, "model_error"):
        me = model_error(meas, sim, sim_fine, sensor, settings, V0, D0, st)
        if st.richardson and me["kind"] == "measured":
            V0, D0 = richardson_correct(V0, D0, C, me, st)
            me["note"] += (
                "; predictions extrapolated by it, σ = the spread of that extrapolation over orders "
                f"p in {list(st.order_range_image)} (image), {list(st.order_range_force)} (force)"
            )
    mv = measured_views(meas, sensor, settings)
    names = decision_views(mv)
    y, y0, S0 = _decision_data(mv, V0, me, names)
    mf = level(V0, D0, names, sensor.pixel_mm) if st.model_form else None
    S = Metric(S0, mf["M"] if mf else None)

    def evaluate_now():
        modes, spread = systematic_modes(me, names)
        models = build_models(C, names, V0, st)
        return evaluate(y, S, y0, models, meas.n, st, slices(V0, names), modes, spread, mf)

    with _timed(timing, "refine"):
        ref_solves, ref_rounds, ref_fine_seconds = (
            refine(meas, C, sim, sensor, settings, me, st, evaluate_now, sim_fine) if st.adaptive else (0, 0, 0.0)
        )
    with _timed(timing, "evaluate"):
        ev = evaluate_now()
    with _timed(timing, "rest"):
        _annotate_ranking(ev["ranking"], C)
        ev["views"] = names
        _locate_level(ev.get("residual_level"), meas, V0, names)
        ev["by_view"] = view_baselines(mv, V0, me, st)
        found = _findings(meas, ev, mv, V0, D0, me, names, y, y0, sim, sensor, settings, st)
    solve_seconds = {"baseline": base_seconds}
    solve_seconds.update({c.effect.name: c.solve_seconds for c in C if c.solve_seconds is not None})
    if "_solve_seconds" in me or ref_fine_seconds:
        solve_seconds["error_mesh"] = me.get("_solve_seconds", 0.0) + ref_fine_seconds
    return {
        "solves_by_effect": _solves_by_effect(meas, C, sim.mesh),
        "solve_seconds_by_effect": solve_seconds,
        "timing": timing,
        "refinement": {"solves": ref_solves, "rounds": ref_rounds, "adaptive": st.adaptive},
        "measured": {
            "source": meas.source,
            "n": meas.n,
            "synthetic": meas.synthetic,
            "description": meas.description,
            "mesh": sim.mesh,
            "ids": meas.ids,
            "dhe": meas.dhe.tolist(),
            "views_available": list(mv),
        },
        "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in st.__dict__.items()},
        "candidates": [c.effect.to_dict() for c in C],
        "model_error": {k: v for k, v in me.items() if k in ("kind", "note", "fine_mesh", "ratio", "relative_median")},
        "_model_error": me,
        "_views": mv,
        "_V0": V0,
        "baseline": V0["features"],
        "evaluation": ev,
        **found,
        "simulator": dict(
            sim.stats,
            backend=sim.backend,
            mesh=sim.mesh,
            solved_this_diagnosis=sim.stats["solved"] - solved0,
            fine_solved=(sim_fine.stats["solved"] if sim_fine is not None else 0),
            fine_mesh=(sim_fine.mesh if sim_fine is not None else None),
        ),
        "seconds": time.perf_counter() - t0,
    }


@contextmanager
def _timed(timing: dict, stage: str):
    """Add the wall seconds of the block to ``timing[stage]``."""
    t = time.perf_counter()
    yield
    timing[stage] = time.perf_counter() - t


def _decision_data(mv: dict, V0: dict, me: dict, names) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(y, y0, S0) of the decision views ``names``: measured, baseline and
    S0 = sqrt(se² + σ_model²) (floored at 1e-12 |y0|)."""
    y = cat({k: v for k, (v, _) in mv.items()}, names)
    se = cat({k: s for k, (_, s) in mv.items()}, names)
    y0 = cat(V0, names)
    S0 = np.sqrt(se**2 + cat(me["sigma"], names) ** 2)
    return y, y0, np.maximum(S0, 1e-12 * np.maximum(np.abs(y0), 1e-300))


def _findings(meas: Measured, ev: dict, mv, V0, D0, me: dict, names, y, y0, sim, sensor, settings, st) -> dict:
    """Where the gap lies, how far it shrinks with the best candidate, and (ambiguous) which
    measurement would separate the reported set: {"where", "shrink_features", "shrink_inverse",
    "proposal"}."""
    wh = where(meas, mv, V0, D0, me, st)
    rows = {r["effect"]: r for r in ev["ranking"]}
    best = rows[ev["best"]] if ev["best"] else None
    shrink = shrink_features(meas, y, y0, best["_S"], best["_model"], names) if best else None
    prop = None
    if ev["outcome"] == "ambiguous":
        prop = propose(
            meas, [ev["reported"][n]["_row"] for n in ev["ambiguous_set"]], V0, me, names, sim, sensor, settings, st
        )
    inv = None
    if st.inverse and best is not None and ev["outcome"] not in ("no significant gap",):
        inv = shrink_inverse(meas, best["_model"], shrink["magnitude"], sim, sensor, settings, st)
    _stage_summary(wh["stage"], ev["ranking"], inv)
    if best is not None and "image" in wh:
        Dw = best["_model"].image(best["_theta"])
        if Dw is not None:
            wh["image_after"] = image_residual(meas, Dw, me, sensor)
            wh["image_after"]["effect"] = best["effect"]
    return {"where": wh, "shrink_features": shrink, "shrink_inverse": inv, "proposal": prop}


def _locate_level(lv: dict | None, meas: Measured, V0: dict, names) -> None:
    """Name where the best candidate's whitened residual is largest: the phantom and the view's
    quantity (an annulus of the profile in mm, a feature, the force)."""
    if not lv:
        return
    i, q = lv["largest"]["phantom"], lv["largest"]["quantity"]
    for k, sl in slices(V0, names).items():
        if sl.start <= q < sl.stop:
            j = q - sl.start
            what = (
                f"annulus {EDGES[j]:g}–{EDGES[j + 1]:g} mm"
                if k == "profile"
                else (FEATURES[j] if k == "features" else "plate force")
            )
            lv["where"] = f"phantom {meas.ids[i]}, {what} ({lv['largest']['z']:+.2g} sd)"
            lv["largest"]["phantom_id"] = meas.ids[i]


def _annotate_ranking(rows: list[dict], C: list[Candidate]) -> None:
    """Add to each ranking row how its members were solved (adaptive, magnitudes, refined, own
    model error, extended range)."""
    for r in rows:
        cs = [c for c in C if c.effect.name in r["members"]]
        r["adaptive"] = any(c.adaptive for c in cs)
        r["solved_magnitudes"] = {c.effect.name: [float(x) for x in c.grid] for c in cs if c.adaptive}
        r["refined"] = all(len(c.refinements) > 0 for c in cs if c.adaptive) if r["adaptive"] else None
        r["own_model_error_at"] = {c.effect.name: list(c.own_error) for c in cs if c.own_error}
        r["extended_to"] = {c.effect.name: list(c.extended) for c in cs if c.extended}


def _stage_summary(stage: dict, rows: list[dict], inv: dict | None) -> None:
    """The best mechanics and optics candidates (and the inverse's errors) beside the stage shares."""
    bm = [r for r in rows if r["stage"] == "mechanics"]
    bo = [r for r in rows if r["stage"] == "optics"]
    stage["best_mechanics_candidate"] = (bm[0]["effect"], bm[0]["explained_fraction"]) if bm else None
    stage["best_optics_candidate"] = (bo[0]["effect"], bo[0]["explained_fraction"]) if bo else None
    if inv:
        stage["inverse_own_error"] = inv["inverse_own"]["mean_relative_error"]
        stage["inverse_error_on_measured"] = inv["before"]["mean_relative_error"]


def _solves_by_effect(meas: Measured, C: list[Candidate], mesh: str) -> dict:
    """Solves each solved effect cost: phantoms x its non-nominal magnitudes."""
    lin = not any(p.nonlinear for p in phantom_params(meas, mesh))
    return {
        c.effect.name: meas.n * sum(1 for m in c.grid if not c.effect.is_nominal(m))
        for c in C
        if needs_solves(c.effect, lin)
    }
