"""Speed machinery of the gap diagnosis: batched solves (one mesh and model per geometry) and
adaptive magnitudes.  Real tiny-mesh FEM solves."""

import dataclasses

import numpy as np
import pytest

from elastimap.solver.batch import geometry_key, group_by_geometry, solve_batch
from elastimap.solver.params import Discretisation, SolveParams


def _variants():
    p0 = SolveParams(disc=Discretisation(mesh="tiny")).with_inclusion(d=8, h=7, E=50)
    r = dataclasses.replace
    return [
        p0,
        p0.replace(tissue=r(p0.tissue, E=6.5, nu=0.46)),
        p0.replace(probe=r(p0.probe, layers=((2.0, 200.0), (3.0, 150.0), (5.0, 40.0)))),
        p0.replace(loading=r(p0.loading, delta=3.4)).with_inclusion(E=80),
        p0.replace(probe=r(p0.probe, layers=((2.5, 300.0), (3.0, 150.0), (5.0, 50.0)))),  # a new geometry
    ]


def test_geometry_key_ignores_moduli_nu_and_travel_only():
    ps = _variants()
    assert len({geometry_key(p) for p in ps[:4]}) == 1
    assert geometry_key(ps[4]) != geometry_key(ps[0])
    assert group_by_geometry(ps) == [[0, 1, 2, 3], [4]]


def test_solve_batch_equals_solve():
    from elastimap.solver import solve

    ps = _variants()
    rb = solve_batch(ps)
    for p, b in zip(ps, rb):
        a = solve(p)
        for k in ("O1", "O2", "O3", "force", "force_ref", "delta"):
            # the inclusion press of a single sample is the difference of its two presses to 1e-6 of
            # that difference (docs/forward-model.md "Shared presses"); a variant's runs on other factors
            assert getattr(b, k) == pytest.approx(getattr(a, k), rel=1e-6, abs=1e-14), k
        for k in ("image", "image_raw"):
            x, y = getattr(a, k).astype(float), getattr(b, k).astype(float)
            assert np.max(np.abs(x - y)) <= 1e-6 * np.max(np.abs(x))  # float32 images
    # the variants really differ (the materials were switched, not left at the first sample's)
    assert len({round(r.O2, 9) for r in rb}) == len(rb)


# ---------------------------------------------------------------- adaptive magnitudes (TOY backend)
def test_adaptive_magnitudes_solve_less_and_find_the_same_answer():
    """Sensitivity solve + refinement near the fit vs the full grid, on the TOY backend (not
    physics: it only exercises the logic).  Same winner, magnitude within the interval, far
    fewer solves; the refined candidate carries the emulator's measured miss."""
    from elastimap.gap import effects as fx
    from elastimap.gap import synth
    from elastimap.gap.diagnose import diagnose
    from elastimap.gap.settings import Settings
    from elastimap.gap.simulate import Simulator

    dhe = synth.phantom_design(6, 1)
    cands = fx.parse_list("friction,background_E,tissue_nu,saturation")
    meas, _ = synth.synthesize(dhe, [(fx.get("background_E"), 6.3)], Simulator(None, "tiny", "toy"), frames=6, seed=4)
    out = {}
    for adaptive in (False, True):
        sim = Simulator(None, "tiny", "toy")
        # the closed world (data from the same TOY): no model-form level, whose 2 % per phantom holds
        # the TOY's small response to the background modulus (not physics)
        res = diagnose(meas, cands, sim, Settings(inverse=False, bootstrap=20, adaptive=adaptive, model_form=False))
        out[adaptive] = (res, sim.stats["solved"])
    (full, n_full), (ad, n_ad) = out[False], out[True]
    assert full["evaluation"]["winner"] == ad["evaluation"]["winner"] == "background_E"
    top = ad["evaluation"]["ranking"][0]
    assert (
        top["refined"] and len(top["solved_magnitudes"]["background_E"]) >= 3
    )  # nominal, sensitivity, >= 1 refinement
    lo, hi = top["magnitude_ci"][0]
    assert lo <= 6.3 <= hi
    assert top["magnitude"][0] == pytest.approx(full["evaluation"]["ranking"][0]["magnitude"][0], rel=0.02)
    assert n_ad < 0.5 * n_full  # 6 baselines + 3 sensitivity x 6 + refinements vs 6 + (8+8+4) x 6
    assert ad["refinement"]["solves"] > 0 and ad["solves_by_effect"]["background_E"] >= 2 * 6


def test_nothing_is_refined_without_a_significant_gap():
    from elastimap.gap import effects as fx
    from elastimap.gap import synth
    from elastimap.gap.diagnose import diagnose
    from elastimap.gap.settings import Settings
    from elastimap.gap.simulate import Simulator

    sim = Simulator(None, "tiny", "toy")
    meas, _ = synth.synthesize(synth.phantom_design(8, 1), [], sim, frames=6, seed=4)
    res = diagnose(meas, fx.parse_list("friction,background_E,saturation"), sim, Settings(inverse=False, bootstrap=20))
    assert res["evaluation"]["outcome"] == "no significant gap"
    assert res["refinement"]["solves"] == 0


def test_selftest_resume_replays_the_same_draws():
    """--start K runs trials K.. with the draws of a whole run (TOY backend, tiny)."""
    from elastimap.gap import effects as fx
    from elastimap.gap import selftest
    from elastimap.gap.settings import Settings
    from elastimap.gap.simulate import Simulator

    cands = fx.parse_list("background_E,saturation")
    outside = fx.parse_list("stray_light")
    kw = dict(n_phantoms=6, frames=4, seed=3, st=Settings(inverse=False, bootstrap=10, propose_solves=False), log=None)
    seen = []
    whole = selftest.run(3, Simulator(None, "tiny", "toy"), Simulator(None, "tiny", "toy"), cands, outside, **kw)
    part = selftest.run(
        3,
        Simulator(None, "tiny", "toy"),
        Simulator(None, "tiny", "toy"),
        cands,
        outside,
        start=2,
        on_trial=seen.append,
        **kw,
    )
    assert [r["trial"] for r in part["trials"]] == [2] and not part["partial"] and part["first_trial"] == 2
    a, b = whole["trials"][2], part["trials"][0]
    assert (a["true_effect"], a["true_magnitude"], a["commitment"]) == (
        b["true_effect"],
        b["true_magnitude"],
        b["commitment"],
    )
    assert len(seen) == 1 and "PARTIAL" not in selftest.markdown(part)
    assert "PARTIAL: 1 of 3" in selftest.markdown(whole | {"partial": True, "n_trials": 1, "trials_planned": 3})


def test_selftest_trial_with_failed_data_is_void_and_the_run_goes_on(monkeypatch):
    from elastimap.errors import UserError
    from elastimap.gap import effects as fx
    from elastimap.gap import selftest
    from elastimap.gap.settings import Settings
    from elastimap.gap.simulate import Simulator

    real = selftest.synthesize

    def flaky(dhe, effs, *a, seed=0, **k):
        if seed == 1:  # trial 1
            raise UserError("synth", "the forward solve failed for phantom(s) [0] with these effects")
        return real(dhe, effs, *a, seed=seed, **k)

    monkeypatch.setattr(selftest, "synthesize", flaky)
    res = selftest.run(
        3,
        Simulator(None, "tiny", "toy"),
        Simulator(None, "tiny", "toy"),
        fx.parse_list("background_E,saturation"),
        fx.parse_list("stray_light"),
        n_phantoms=6,
        frames=4,
        seed=0,
        st=Settings(inverse=False, bootstrap=10, propose_solves=False),
        log=None,
    )
    assert [r["trial"] for r in res["trials"]] == [0, 2] and [v["trial"] for v in res["void_trials"]] == [1]
    assert res["partial"] and "VOID" in selftest.markdown(res)
