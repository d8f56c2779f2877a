"""The ``chest_wall`` candidate (a soft chest wall, ``Tissue.wall_compliance``) is diagnosable:
TOY data (the SYNTHETIC stand-in, not physics: it exercises the gap logic) and real tiny-mesh solves."""

import dataclasses

import numpy as np
import pytest

from elastimap.gap import effects as fx
from elastimap.gap import synth
from elastimap.gap.diagnose import diagnose
from elastimap.gap.settings import Settings
from elastimap.gap.simulate import Simulator


def test_chest_wall_is_a_default_mechanics_candidate_with_a_rigid_nominal():
    e = fx.get("chest_wall")
    assert e.name in fx.DEFAULT_CANDIDATES and e.stage == "mechanics" and e.nominal == 0.0
    p = synth.base_params("tiny", 8.0, 7.0, 50.0)
    assert e.apply_params(p, 0.0) is p and e.apply_params(p, 0.4).tissue.wall_compliance == 0.4
    assert fx.value_in(e, e.apply_params(p, 0.4), None) == 0.4
    assert e.lo <= e.blind[0] < e.blind[1] <= e.hi


def test_toy_chest_wall_is_found_with_a_covering_interval():
    toy = Simulator(None, "tiny", "toy")
    dhe = synth.phantom_design(10, 0)
    meas, _ = synth.synthesize(dhe, [(fx.get("chest_wall"), 0.5)], toy, frames=6, seed=11)
    cands = fx.parse_list("chest_wall,background_E,friction,skin,probe_E1,saturation,indentation")
    ev = diagnose(meas, cands, toy, Settings(inverse=False, bootstrap=20))["evaluation"]
    assert ev["outcome"] == "explained" and ev["winner"] == "chest_wall", (ev["outcome"], ev["ambiguous_set"])
    top = ev["ranking"][0]
    assert top["magnitude_ci"][0][0] <= 0.5 <= top["magnitude_ci"][0][1]


def test_fem_chest_wall_ranks_first_on_tiny_solves(tmp_path):
    """4 phantoms, a 2-point chest-wall sweep and an optics candidate, real tiny-mesh solves."""
    sim = Simulator(tmp_path / "cache", "tiny", "fem")
    cw = dataclasses.replace(fx.get("chest_wall"), grid=(0.0, 0.4), sensitivity_at=0.4)
    dhe = np.array([[8.0, 8.0, 80.0], [6.0, 7.0, 50.0], [10.0, 10.0, 120.0], [7.0, 11.0, 60.0]])
    meas, _ = synth.synthesize(dhe, [(cw, 0.3)], sim, frames=4, seed=0)
    res = diagnose(meas, [cw, fx.get("saturation")], sim, Settings(inverse=False, bootstrap=20))
    ev = res["evaluation"]
    assert ev["best"] == "chest_wall"
    assert ev["ranking"][0]["magnitude"][0] == pytest.approx(0.3, rel=0.15)
