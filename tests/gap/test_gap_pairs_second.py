"""Two effects at once beside a passing single effect (gap/selection.py: ``pairs``, ``second_effect``;
docs/gap.md, 'Two effects at once').  Hand-made SYNTHETIC linear sweeps only (not physics)."""

import numpy as np
import pytest

from elastimap.gap.report import verdict_line
from elastimap.gap.selection import evaluate, inside_grids, pairs, second_effect
from elastimap.gap.settings import Settings

#: the four SYNTHETIC linear effects of these worlds (tests/gap/conftest.py, `linear_world`)
FOUR = ("friction", "nonlinearity", "indentation", "gamma")


def _eval(y, y0, models, st=None):
    return evaluate(y, np.ones_like(y0), y0, models, y0.shape[0], st or Settings(), {"profile": slice(0, y0.shape[1])})


def test_a_pair_leads_beside_a_passing_single_when_the_data_ask_for_two(linear_world):
    """With ``pair_beside_single``: a small second effect leaves the first one's single fit passing; the
    pair still beats it by more than the margin with both effects needed, so the pair is the answer."""
    rng, y0, dirs, models = linear_world(effects=FOUR)
    y = y0 + 0.6 * dirs["friction"] + 0.07 * dirs["indentation"] + rng.standard_normal(y0.shape)
    ev = _eval(y, y0, models, Settings(pair_beside_single=True))
    singles = [r for r in ev["ranking"] if not r["pair"]]
    assert singles[0]["effect"] == "friction" and singles[0]["passes"]  # one effect alone would pass
    assert ev["outcome"] == "explained" and ev["winner"] == "friction+indentation", ev["ranking"][0]["effect"]
    (lo_f, hi_f), (lo_i, hi_i) = ev["reported"]["friction+indentation"]["magnitude_ci"]
    assert lo_f <= 0.6 <= hi_f and lo_i <= 0.07 <= hi_i and lo_i > 0.0  # both covered, both needed
    assert singles[0]["score"] - ev["ranking"][0]["score"] > Settings().ambiguity_margin
    assert ev["second_effect"] is None  # a leading pair is the answer, not a caveat on a single
    # with pair_beside_single off (the default), the pair leads only where no single passes: the single stands
    ev1 = _eval(y, y0, models)
    assert ev1["winner"] == "friction" and any(r["pair"] for r in ev1["ranking"])


def test_one_effect_stays_one_effect_with_pairs_weighed(linear_world):
    """Sparse: with one effect in the data the pairs are weighed (listed) but none leads and none
    moves the single's magnitude out of its interval."""
    rng, y0, dirs, models = linear_world(seed=1, effects=FOUR)
    y = y0 + 0.6 * dirs["friction"] + rng.standard_normal(y0.shape)
    ev = _eval(y, y0, models)
    assert ev["outcome"] == "explained" and ev["winner"] == "friction"
    assert any(r["pair"] for r in ev["ranking"])  # weighed
    assert ev["second_effect"] is None
    # without any pair (pair_top = 0) the same answer: the pairs change nothing here
    ev0 = _eval(y, y0, models, Settings(pair_top=0))
    assert ev0["winner"] == "friction" and not any(r["pair"] for r in ev0["ranking"])


def test_pairs_hold_each_of_the_best_with_every_other_single_effect(linear_world):
    """The second effect need not rank among the best alone: each of the best ``pair_top`` single
    effects is paired with every other one, once per pair."""
    _, y0, dirs, models = linear_world(effects=FOUR)
    rows = [{"effect": n} for n in ("gamma", "friction", "nonlinearity", "indentation")]
    got = [p.name for p in pairs(models, rows, Settings(pair_top=1), y0)]
    assert got == ["gamma+friction", "gamma+nonlinearity", "gamma+indentation"]
    got2 = {frozenset(p.name.split("+")) for p in pairs(models, rows, Settings(pair_top=2), y0)}
    assert len(got2) == 5 and frozenset(("friction", "nonlinearity")) in got2
    assert pairs(models, rows, Settings(pair_top=0), y0) == []


def _row(effect, score, mag, ci, nominal, passes=True, edge=False, pair=None):
    members = pair or [effect]
    return {
        "effect": effect,
        "pair": pair is not None,
        "members": members,
        "score": score,
        "magnitude": mag,
        "magnitude_ci": ci,
        "nominal": nominal,
        "passes": passes,
        "at_grid_edge": edge,
    }


def test_a_second_effect_that_moves_the_single_out_of_its_interval_withdraws_the_single():
    """The single's magnitude is no confident statement when a pair holding it beats it by more than
    the margin and puts it outside the single's interval; not when the pair is within the margin,
    fails, is pinned at its range's end, or keeps the magnitude inside the interval."""
    st = Settings()
    best = _row("probe_E2", 17.0, [77.6], [[66.7, 90.3]], [150.0])
    pair = _row(
        "probe_E2+background_E",
        9.6,
        [102.1, 6.36],
        [[90, 128.6], [4.8, 7]],
        [150.0, 5.0],
        pair=["probe_E2", "background_E"],
    )
    assert second_effect(best, [best, pair], st) is pair
    assert second_effect(best, [best, dict(pair, score=13.0)], st) is None  # within the margin (4.0)
    assert second_effect(best, [best, dict(pair, passes=False)], st) is None
    assert second_effect(best, [best, dict(pair, at_grid_edge=True)], st) is None
    assert second_effect(best, [best, dict(pair, magnitude=[85.0, 6.36])], st) is None  # inside its interval
    other = dict(pair, members=["probe_moduli", "background_E"], effect="probe_moduli+background_E")
    assert second_effect(best, [best, other], st) is None  # does not hold the best's effect
    assert second_effect(pair, [pair, best], st) is None  # a pair as the best: nothing to withdraw


def test_the_verdict_line_names_the_second_effect(linear_world):
    """The unexplained line says why: the pair, its lead, and both magnitudes."""
    rng, y0, dirs, models = linear_world(effects=FOUR)
    y = y0 + 0.6 * dirs["friction"] + rng.standard_normal(y0.shape)
    ev = _eval(y, y0, models)
    top = ev["ranking"][0]
    ev.update(
        outcome="unexplained",
        second_effect={
            "pair": "friction+gamma",
            "delta_score": 7.5,
            "effect": "friction",
            "magnitude_in_pair": 0.8,
            "magnitude_ci_in_pair": [0.7, 0.9],
            "second": "gamma",
            "second_magnitude": 1.1,
            "second_magnitude_ci": [0.95, 1.25],
            "second_needed": False,
        },
    )
    line = verdict_line({"evaluation": ev})
    assert line.startswith("outcome: unexplained") and f"best {top['effect']}" in line
    assert "a second effect may be present: friction+gamma" in line and "7.5" in line
    assert "gamma 1.1 [0.95, 1.25] (its interval holding its nominal)" in line


def test_a_pair_whose_interval_reaches_a_grid_end_does_not_lead(linear_world):
    """A pair's members are held inside their grids; a pair whose interval reaches a grid's end is a
    fit the library cut short (a look-alike pair standing in for an effect outside it), no answer."""
    rng, y0, dirs, models = linear_world(seed=2, effects=FOUR)
    y = y0 + 0.5 * dirs["friction"] + 0.6 * dirs["indentation"] + rng.standard_normal(y0.shape)  # 0.6: its grid's end
    ev = _eval(y, y0, models)
    pr = next(r for r in ev["ranking"] if set(r["members"]) == {"friction", "indentation"})
    assert pr["passes"] and pr["both_needed"] and not pr["inside_grids"]
    assert pr["magnitude_ci"][pr["members"].index("indentation")][1] == pytest.approx(0.6)  # held at the grid's end
    assert not any(r["passes"] for r in ev["ranking"] if not r["pair"])  # no single effect is enough
    assert ev["outcome"] == "unexplained" and not ev["ranking"][0]["pair"]
    y2 = y0 + 0.5 * dirs["friction"] + 0.3 * dirs["indentation"] + rng.standard_normal(y0.shape)  # inside
    assert set(_eval(y2, y0, models)["winner"].split("+")) == {"friction", "indentation"}


def test_inside_grids():
    row = {"magnitude_ci": [[0.4, 0.6], [1.0, 1.2]], "design_range": [[0.0, 1.0], [0.7, 1.4]]}
    assert inside_grids(row)
    assert not inside_grids(dict(row, magnitude_ci=[[0.0, 0.6], [1.0, 1.2]]))
    assert not inside_grids(dict(row, magnitude_ci=[[0.4, 0.6], [1.0, 1.4]]))
