"""Look-alikes: when the phantoms cannot tell the best candidate from another (docs/gap.md,
'Look-alikes'; :func:`elastimap.gap.selection.told_apart`).  SYNTHETIC sweeps only."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from elastimap.gap import effects as fx
from elastimap.gap.candidates import Candidate
from elastimap.gap.fit_models import Composed, Single
from elastimap.gap.model_form import Metric, level
from elastimap.gap.report import verdict_line
from elastimap.gap.selection import beyond_design, evaluate, told_apart
from elastimap.gap.settings import Settings

Z = stats.norm.ppf(0.99)  # z_(1-α) at the default α = 1 %


class _Fixed:
    """A fitted prediction that does not depend on θ (a ranking row's model, for the test)."""

    def __init__(self, f):
        self.f = f

    def predict(self, theta):
        return self.f


def _row(f, score, passes=True, ci=(6.4, 7.0), nominal=5.0, edge=False):
    return {
        "_model": _Fixed(f),
        "_theta": [0.0],
        "score": score,
        "passes": passes,
        "magnitude_ci": [list(ci)],
        "nominal": [nominal],
        "at_grid_edge": edge,
    }


def _pair(D, n=12, Q=8):
    """Two fitted predictions whose separation in error units (unit diagonal metric) is D."""
    rng = np.random.default_rng(0)
    u = rng.standard_normal((n, Q))
    return np.zeros((n, Q)), u * math.sqrt(D / np.sum(u**2)), Metric(np.ones((n, Q)))


def test_a_deficit_within_the_noise_of_the_chi2_difference_is_no_lead():
    """D_ab = 55: the χ² difference of the two predictions has the noise sd 2 √55 = 14.8, so a
    Δscore of 9.4 (beyond the margin 4.6) does not tell them apart; 40 (> z 2 √D = 34.5) does."""
    fa, fb, S = _pair(55.0)
    a, st = _row(fa, 10.0), Settings()
    v = told_apart(a, _row(fb, 19.4), S, st)
    assert v["separation"] == pytest.approx(55.0) and v["noise"] == pytest.approx(2 * math.sqrt(55.0))
    assert not v["margin"] and v["within_noise"] and not v["told_apart"]
    assert told_apart(a, _row(fb, 10.0 + 1.01 * Z * v["noise"]), S, st)["told_apart"]
    assert not told_apart(a, _row(fb, 10.0 + 0.99 * Z * v["noise"]), S, st)["told_apart"]


def test_only_a_confident_passing_candidate_joins_by_the_noise_and_the_margin_stays():
    fa, fb, S = _pair(55.0)
    a, st = _row(fa, 10.0), Settings()
    assert told_apart(a, _row(fb, 19.4, passes=False), S, st)["told_apart"]  # rejected by the data
    assert told_apart(a, _row(fb, 19.4, ci=(4.0, 6.0)), S, st)["told_apart"]  # its interval holds no effect
    assert told_apart(a, _row(fb, 19.4, edge=True), S, st)["told_apart"]  # pinned at the end of its range
    assert told_apart(a, _row(fb, 19.4), S, st, model_form=False)["told_apart"]  # closed world: margin only
    v = told_apart(a, _row(fb, 14.0, passes=False), S, st, model_form=False)  # within the margin: as before
    assert v["margin"] and not v["told_apart"]


def _sweep(name, grid, y0, direction):
    e = fx.get(name)
    g = np.asarray(grid, float)
    return Candidate(e, g, {"profile": y0[None] + (g - e.nominal)[:, None, None] * direction[None]}, None)


def test_evaluate_reports_a_look_alike_set_and_keeps_a_clear_answer():
    """SYNTHETIC linear sweeps of two effects whose signatures differ by a structured part u
    (friction: d, nonlinearity: d + u/0.5 per unit).  Data = friction 0.5 plus 0.3 u: friction leads
    by about 0.4 D, beyond the margin, within z 2 √D: with the model-form level the set holds both
    (ambiguous); the closed-world budget keeps its margin (explained by friction).  Data = friction
    0.5 alone with an unrelated nonlinearity signature: explained by friction, also with the level."""
    rng = np.random.default_rng(3)
    n, Q = 12, 8
    y0 = rng.uniform(50, 100, (n, Q))
    d = rng.standard_normal((n, Q)) * 8
    u = rng.standard_normal((n, Q)) * 0.9
    grid = np.linspace(0, 1, 5)
    sl, st = {"profile": slice(0, Q)}, Settings()
    mf = level({"profile": y0}, None, ["profile"], 0.5)
    S = Metric(np.full((n, Q), 0.5), mf["M"])
    models = [
        Single(_sweep("friction", grid, y0, d), ["profile"]),
        Single(_sweep("nonlinearity", grid, y0, d + u / 0.5), ["profile"]),
    ]
    y = y0 + 0.5 * d + 0.3 * u + 0.05 * rng.standard_normal((n, Q))
    ev = evaluate(y, S, y0, models, n, st, sl, mf=mf)
    v = ev["ranking"][1]["vs_best"]
    assert ev["best"] == "friction" and v["delta_score"] > st.ambiguity_margin, v
    assert v["within_noise"] and ev["outcome"] == "ambiguous", v
    assert ev["ambiguous_set"] == ["friction", "nonlinearity"]
    closed = evaluate(y, Metric(np.full((n, Q), 0.5)), y0, models, n, st, sl)
    assert closed["outcome"] == "explained" and closed["winner"] == "friction"
    other = [models[0], Single(_sweep("nonlinearity", grid, y0, rng.standard_normal((n, Q)) * 8), ["profile"])]
    y = y0 + 0.5 * d + 0.05 * rng.standard_normal((n, Q))
    ev = evaluate(y, S, y0, other, n, st, sl, mf=mf)
    assert ev["outcome"] == "explained" and ev["winner"] == "friction", ev["ranking"][1].get("vs_best")


def _family_row(f, score, passes=True, edge=True, pair=False):
    r = _row(f, score, passes=passes, edge=edge)
    r.update(members=["probe_t1", "probe_t2", "probe_t3"], pair=pair, nominal=[2.0, 3.0, 5.0])
    r["magnitude_ci"] = [[2.4, 2.5], [3.4, 3.5], [5.4, 5.5]]
    return r


def test_a_passing_family_held_at_its_grid_ends_within_the_noise_is_a_shadow():
    """The shadow rule (docs/gap.md, 'Look-alikes'): a passing family held at its members' grid ends
    within the noise of the best's lead is a shadow; a single effect at the end of its range (a
    physical limit: its range is extended up to it) is not, nor a family inside its grids (a
    look-alike: it joins the set), a pair, a failing family, one beyond the noise, or the closed world."""
    fa, fb, S = _pair(55.0)
    a, st = _row(fa, 10.0), Settings()
    v = told_apart(a, _family_row(fb, 19.4), S, st)
    assert v["shadow"] and not v["within_noise"] and v["told_apart"]  # not reported: it makes the best unsure
    assert not told_apart(a, _row(fb, 19.4, edge=True) | {"members": ["tissue_nu"]}, S, st)["shadow"]
    inside = told_apart(a, _family_row(fb, 19.4, edge=False), S, st)
    assert not inside["shadow"] and inside["within_noise"]
    assert not told_apart(a, _family_row(fb, 19.4, pair=True), S, st)["shadow"]
    assert not told_apart(a, _family_row(fb, 19.4, passes=False), S, st)["shadow"]
    assert not told_apart(a, _family_row(fb, 10.0 + 1.01 * Z * 2 * math.sqrt(55.0)), S, st)["shadow"]
    assert not told_apart(a, _family_row(fb, 19.4), S, st, model_form=False)["shadow"]


def test_evaluate_calls_a_best_shadowed_by_a_family_at_its_grid_ends_unexplained():
    """SYNTHETIC linear sweeps: friction (d per unit) and the three probe thicknesses, each d + u/0.5
    per unit over a grid of ±0.16 about its nominal; data = friction 0.5 plus 0.3 u, whose second
    reading needs the three at +0.165 each (0.496 in all).  The family of the three, held at its grid
    ends, passes within the noise of friction's lead: "unexplained", the shadow named.  The same
    signature as one single effect pinned at the end of its range (nonlinearity, grid 0–0.48): no
    shadow, friction explains (the rule is about families).  Grids of ±0.6: the family fits inside
    them, no shadow; the closed-world budget keeps its margin."""
    rng = np.random.default_rng(3)
    n, Q = 12, 8
    y0 = rng.uniform(50, 100, (n, Q))
    d = rng.standard_normal((n, Q)) * 8
    u = rng.standard_normal((n, Q)) * 0.9
    sl, st = {"profile": slice(0, Q)}, Settings()
    mf = level({"profile": y0}, None, ["profile"], 0.5)
    S = Metric(np.full((n, Q), 0.5), mf["M"])
    y = y0 + 0.5 * d + 0.3 * u + 0.05 * rng.standard_normal((n, Q))
    fr = Single(_sweep("friction", np.linspace(0, 1, 5), y0, d), ["profile"])

    def family(top):
        ms = [
            Single(_sweep(m, fx.get(m).nominal + np.linspace(-top, top, 5), y0, d + u / 0.5), ["profile"])
            for m in fx.FAMILIES["probe_layers_t"].members
        ]
        return Composed(fx.FAMILIES["probe_layers_t"], ms, y0, {"profile": y0})

    ev = evaluate(y, S, y0, [fr, family(0.16)], n, st, sl, mf=mf)
    fam = ev["ranking"][1]
    assert ev["best"] == "friction" and fam["effect"] == "probe_layers_t", [r["effect"] for r in ev["ranking"]]
    assert fam["passes"] and fam["at_grid_edge"] and fam["vs_best"]["shadow"], fam["vs_best"]
    assert ev["outcome"] == "unexplained" and ev["shadowed_by"] == ["probe_layers_t"]
    assert ev["verdict"] == "unexplained" and ev["winner"] is None and ev["ambiguous_set"] == []
    assert "not told apart from probe_layers_t, a family held at its members' grid ends" in verdict_line(
        {"evaluation": ev}
    )
    nl = Single(_sweep("nonlinearity", np.linspace(0, 0.48, 5), y0, d + u / 0.5), ["profile"])
    single = evaluate(y, S, y0, [fr, nl], n, st, sl, mf=mf)
    assert single["ranking"][1]["at_grid_edge"] and not single["ranking"][1]["vs_best"]["shadow"]
    assert single["outcome"] == "explained" and single["winner"] == "friction" and single["shadowed_by"] == []
    wide = evaluate(y, S, y0, [fr, family(0.6)], n, st, sl, mf=mf)
    assert not wide["ranking"][1]["at_grid_edge"] and wide["shadowed_by"] == [], wide["ranking"][1]["magnitude"]
    assert wide["outcome"] in ("explained", "ambiguous") and wide["best"] == "friction"
    closed = evaluate(y, Metric(np.full((n, Q), 0.5)), y0, [fr, family(0.16)], n, st, sl)
    assert closed["outcome"] == "explained" and closed["winner"] == "friction"


def test_an_interval_wholly_beyond_the_design_grid_is_no_confident_answer():
    """``beyond_design``: only an interval that excludes the whole grid the library was built for
    (background_E: 3.5–7 kPa) counts; one reaching back into it (an effect just past the grid's end)
    does not.  In a diagnosis (SYNTHETIC linear sweep of background_E over a range extended down to
    1 kPa): data at 2.3 kPa are "unexplained" with the best named and the flag set; data at 3.6 kPa
    are explained by it; the closed-world budget keeps its answer at 2.3."""
    r = {"magnitude_ci": [[2.148, 2.592]], "design_range": [[3.5, 7.0]]}
    assert beyond_design(r)
    assert not beyond_design(r | {"magnitude_ci": [[3.2, 3.6]]})
    assert beyond_design(r | {"magnitude_ci": [[7.1, 7.6]]})
    fam = {"magnitude_ci": [[2.5, 2.9], [3.1, 3.9]], "design_range": [[1.2, 3.0], [2.0, 4.0]]}
    assert not beyond_design(fam)
    rng = np.random.default_rng(5)
    n, Q = 12, 8
    y0 = rng.uniform(50, 100, (n, Q))
    d = rng.standard_normal((n, Q)) * 8
    sl, st = {"profile": slice(0, Q)}, Settings()
    mf = level({"profile": y0}, None, ["profile"], 0.5)
    S = Metric(np.full((n, Q), 0.5), mf["M"])
    bg = Single(_sweep("background_E", np.linspace(1.0, 7.0, 9), y0, d), ["profile"])
    assert bg.effect.lo == 3.5 and bg.effect.hi == 7.0  # the design grid, not the extended one

    def run(m, metric=S, form=mf):
        y = y0 + (m - 5.0) * d + 0.05 * rng.standard_normal((n, Q))
        return evaluate(y, metric, y0, [bg], n, st, sl, mf=form)

    low = run(2.3)
    top = low["ranking"][0]
    assert top["passes"] and not top["at_grid_edge"] and top["magnitude_ci"][0][1] < 3.5, top["magnitude_ci"]
    assert low["outcome"] == "unexplained" and low["beyond_design"] and low["best"] == "background_E"
    line = verdict_line({"evaluation": low})
    assert "wholly beyond the magnitudes the library was built for, [3.5, 7]" in line and "background_E 2.3" in line, (
        line
    )
    near = run(3.6)
    assert near["outcome"] == "explained" and near["winner"] == "background_E" and not near["beyond_design"]
    closed = run(2.3, Metric(np.full((n, Q), 0.5)), None)
    assert closed["outcome"] == "explained" and not closed["beyond_design"]
