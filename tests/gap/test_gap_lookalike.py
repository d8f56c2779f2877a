"""Look-alikes: when the phantoms cannot tell the best candidate from another (docs/gap.md,
'Look-alikes'; :func:`elastimap.gap.selection.told_apart`).  SYNTHETIC sweeps only."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from elastimap.gap import effects as fx
from elastimap.gap.candidates import Candidate
from elastimap.gap.fit_models import Single
from elastimap.gap.model_form import Metric, level
from elastimap.gap.selection import evaluate, told_apart
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
