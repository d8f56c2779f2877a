"""The ``lens_distortion`` candidate (radial lens distortion of the camera, ``SensorModel.lens_k1``;
docs/gap.md, 'Effects library'): a default optics candidate whose grid the camera renders, about
a sensor's own lens, and found by a diagnosis.  TOY solves (the SYNTHETIC stand-in for the FEM,
not physics); the camera and its distortion are the real camera model."""

import numpy as np
import pytest

from elastimap.camera.optics import SensorModel
from elastimap.gap import effects as fx
from elastimap.gap import selftest, synth
from elastimap.gap.diagnose import diagnose
from elastimap.gap.settings import Settings
from elastimap.gap.simulate import Simulator
from elastimap.sensor import CameraSpec, Sensor


def test_lens_distortion_is_a_default_optics_candidate():
    e = fx.get("lens_distortion")
    assert e.stage == "optics" and e.nominal == 0.0 and e.name not in fx.OUTSIDE_ONLY
    assert e.name in fx.DEFAULT_CANDIDATES and e.name in {c.name for c in selftest.default_candidates()}
    assert [c.name for c in fx.parse_list("friction,lens_distortion")] == ["friction", "lens_distortion"]
    # both signs (barrel and pincushion) on the grid; the blind range resolvable (|k1| >= 0.1: 0.05 was
    # "no gap" on the seed-11 worlds) and inside the grid
    assert e.lo < 0.0 < e.hi and e.lo <= min(e.blind) < max(e.blind) <= e.hi
    assert min(abs(b) for b in e.blind) >= 0.1 and max(e.blind) < 0.0
    s = SensorModel()
    for m in (*e.grid, *e.limits):  # every magnitude the diagnosis may render is a valid (unfolded) camera
        assert e.apply_sensor(s, m).validate().lens_k1 == m
    with pytest.raises(Exception, match="lens_k1"):
        e.apply_sensor(s, e.limits[0] - 0.03).validate()  # beyond the lower limit the frame folds
    assert e.apply_sensor(s, 0.0) is s


def test_lens_distortion_is_centred_on_a_sensors_own_lens():
    lab = Sensor(camera=CameraSpec(lens_k1=0.05)).validate()
    e = fx.for_sensor(lab)["lens_distortion"]
    assert e.nominal == 0.05 and 0.05 in e.grid and e.is_nominal(0.05)
    assert min(e.grid) >= e.limits[0] and e.blind == pytest.approx((-0.15, -0.05))


def test_toy_lens_distortion_is_found_first_with_a_covering_interval():
    toy_sim = Simulator(None, "tiny", "toy")
    dhe = synth.phantom_design(10, 0)
    meas, _ = synth.synthesize(dhe, [(fx.get("lens_distortion"), -0.15)], toy_sim, frames=6, seed=11)
    cands = fx.parse_list("lens_distortion,blur,vignetting,friction,probe_t2,background_E,saturation")
    ev = diagnose(meas, cands, toy_sim, Settings(inverse=False, bootstrap=20))["evaluation"]
    assert ev["significant"] and ev["best"] == "lens_distortion", (ev["outcome"], ev["ambiguous_set"])
    assert ev["outcome"] in ("explained", "ambiguous") and "lens_distortion" in (ev["ambiguous_set"] or [ev["winner"]])
    (lo, hi), m = ev["ranking"][0]["magnitude_ci"][0], ev["ranking"][0]["magnitude"][0]
    assert lo <= -0.15 <= hi and m == pytest.approx(-0.15, abs=0.03)
    assert np.isfinite(ev["ranking"][0]["reduced_chi2_cv"])


def test_selftest_draws_a_barrel_distortion_and_finds_it():
    """An in-library trial of the blind benchmark with the lens among the candidates: its magnitude
    from the blind range (barrel), answered with a set that holds it (TOY solves)."""
    cands = fx.parse_list("lens_distortion,blur")
    toy_sim = Simulator(None, "tiny", "toy")
    res = selftest.run(
        2, toy_sim, Simulator(None, "coarse", "toy"), cands, fx.parse_list("stray_light"),
        n_phantoms=8, frames=4, seed=3, st=Settings(inverse=False, bootstrap=10), log=None,
    )  # fmt: skip
    (tr,) = [r for r in res["trials"] if r["kind"] == "in"]
    assert tr["true_effect"] == "lens_distortion"  # seed 3 draws it (the other seeds may draw blur)
    lo, hi = fx.get("lens_distortion").blind
    assert lo <= tr["true_magnitude"] <= hi < 0.0 and tr["right"] and "lens_distortion" in tr["set"], tr
