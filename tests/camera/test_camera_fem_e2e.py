"""End-to-end on the real forward model (tiny mesh): FEM training table → ensemble; nine phantoms →
SYNTHETIC camera → calibration; 30 SYNTHETIC frames of an inclusion not in the table → (d, h, E).

Stated tolerance: d within 15 %, h within 15 %.  E is NOT recovered: (O1, O2, O3) barely change with
E above about ten times the tissue modulus and a smaller stiffer inclusion looks like a larger
softer one (docs/training.md, docs/identifiability.md).  Measured here: d 7.74 mm (−14 %), h 7.71 mm (+3 %),
E 131 kPa for a true 45 kPa, with a confidently narrow ensemble range (115–145 kPa).  That E
result is kept as a strict xfail so that it is seen, and so that the day the inverse gets E right
the test says so.  Inference now knows this: with the shipped identifiability map (elastimap.identify.idmap)
the estimate carries ``non_identifiable:E`` and an E interval that holds the truth.
"""

import numpy as np
import pandas as pd
import pytest
from scipy.stats import qmc

from elastimap.camera.calibration import fit_calibration, simulate_phantoms
from elastimap.camera.features import FeatureSettings
from elastimap.camera.frames import write_frames
from elastimap.camera.infer import estimate_images
from elastimap.camera.optics import SensorModel, render_pair
from elastimap.dataset.phantoms import read_phantoms
from elastimap.solver import solve
from elastimap.solver.params import Discretisation, SolveParams

# its module fixture is costly: under pytest-xdist (make test) this module runs on one worker
pytestmark = pytest.mark.xdist_group("test_camera_fem_e2e")

TRUTH = (9.0, 7.5, 45.0)  # d mm, h mm, E kPa — not a table row, not a phantom


def _fem(d, h, E, tissue_E=5.0, thickness=20.0):
    return solve(SolveParams(disc=Discretisation(mesh="tiny")).with_inclusion(d=d, h=h, E=E))


@pytest.fixture(scope="module")
def estimate_of_truth(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("e2e")
    api = pytest.importorskip("elastimap.training.api")
    # training table: 40 LHS points over d 5-11 mm, h 6.5-10 mm, E 15-150 kPa (log), tiny mesh
    u = qmc.LatinHypercube(d=3, seed=3).random(40)
    d = 5 + 6 * u[:, 0]
    h = 6.5 + 3.5 * u[:, 1]
    E = np.exp(np.log(15) + np.log(10) * u[:, 2])
    rows = []
    for di, hi, Ei in zip(d, h, E):
        r = _fem(di, hi, Ei)
        rows.append((di, hi, Ei, r.O1, r.O2, r.O3))
    table = pd.DataFrame(rows, columns=["d", "h", "E", "O1", "O2", "O3"])
    ens = api.fit_ensemble(table, algo="lm", repeats=3, epochs=100, hidden=(6,), seed=0)

    sensor = SensorModel(seed=5)
    settings = FeatureSettings()
    ph = read_phantoms(None, min_rows=3, why="to fit a calibration line")
    fem, cam, _ = simulate_phantoms(ph, _fem, sensor, settings, frames=10, seed=1)
    cal = fit_calibration(
        ph, fem, cam, settings.to_dict() if hasattr(settings, "to_dict") else {}, sensor=sensor.to_dict()
    )

    res = _fem(*TRUTH)
    F, B = render_pair(sensor, res.image_raw, res.image, res.pixel, 30, np.random.default_rng(11))
    pf = write_frames(F, tmp_path, "lesion", "png")
    pb = write_frames(B, tmp_path, "lesion_background", "png")
    est = estimate_images(pf, pb, cal, ens, id="lesion")
    return est.to_dict()


def test_fem_frames_to_size_and_depth(estimate_of_truth):
    out = estimate_of_truth
    dd, hh, _ = TRUTH
    assert not [f for f in out["flags"].split(";") if f.startswith(("outside", "no_signal"))], out
    assert out["d"] == pytest.approx(dd, rel=0.15), out
    assert out["h"] == pytest.approx(hh, rel=0.15), out


def test_fem_frames_modulus_is_flagged_with_an_interval_holding_the_truth(estimate_of_truth):
    out = estimate_of_truth
    assert "non_identifiable:E" in out["flags"] and not out["E_identifiable"], out
    assert out["E_lo"] <= TRUTH[2] <= out["E_hi"], out
    assert out["E_hi"] / out["E_lo"] > 3, out  # wide, not a confident number


@pytest.mark.xfail(
    strict=True, reason="E is not identifiable from (O1, O2, O3) over this range (docs/identifiability.md)"
)
def test_fem_frames_to_modulus(estimate_of_truth):
    out = estimate_of_truth
    EE = TRUTH[2]
    assert out["E"] == pytest.approx(EE, rel=0.35) or out["E_p10"] <= EE <= out["E_p90"], out
