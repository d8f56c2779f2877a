"""The physics fit's forward maps press with a lab's own sensor (identify/forward_maps.py, ``fit_maps(sensor=)``):
on the tiny mesh with layers 2:200,3:150,5:50 and a 20 mm footprint, every map of the fit (its own
level and the neighbouring one, morphed and remeshed) gives the image ``solve --sensor`` gives, and
another sensor's fit reports the Gauss–Newton intervals (the calibrated ones are the paper's)."""

from __future__ import annotations

import numpy as np
import pytest

from elastimap.identify.forward_maps import fit_maps, image_of, sensor_template
from elastimap.sensor import Sensor, load
from elastimap.solver.params import Discretisation, Inclusion, SolveParams, from_sensor

LAB = (
    'name = "lab-A"\n[probe]\nfootprint = 20.0\n'
    "layers = [{thickness = 2.0, E = 200.0}, {thickness = 3.0, E = 150.0}, {thickness = 5.0, E = 50.0}]\n"
    "[camera]\nwindow_native = 800\n"
)


@pytest.fixture
def lab(tmp_path) -> Sensor:
    p = tmp_path / "lab-A.toml"
    p.write_text(LAB)
    return load(p)


def test_sensor_template_is_none_for_the_papers_mechanics(lab):
    assert sensor_template(None) is None and sensor_template(Sensor()) is None
    assert sensor_template(Sensor().replace(name="other-camera")) is None  # a name (or camera) is no mechanics
    t = sensor_template(lab)
    assert t == from_sensor(lab) and t != SolveParams() and t.probe.size == 20.0
    # the calibrated intervals stay the paper's sensor's; the maps are built lazily (no solve here)
    assert fit_maps("coarse", "fine", "morph", Sensor()).intervals == "calibrated"
    m = fit_maps("coarse", "fine", "morph", lab)
    assert m.intervals == "gauss"
    assert {f.morphed.template.probe.size for f in (m.forward, m.forward_alt, m.forward_fine)} == {20.0}


@pytest.mark.slow
@pytest.mark.parametrize("geometry", ["remesh", "morph"])
def test_fit_maps_of_a_lab_sensor_equal_its_solves(geometry, lab):
    from elastimap.solver import solve

    maps = fit_maps("tiny", None, geometry, lab)
    assert maps.intervals == "gauss"
    for level, f in (("tiny", maps.forward), ("coarse", maps.forward_alt)):
        got = image_of(f(8.0, 7.0, 60.0))
        want = solve(from_sensor(lab, Inclusion(d=8.0, h=7.0, E=60.0, nu=lab.tissue.nu), Discretisation(mesh=level)))
        assert got.shape == want.image.shape == (40, 40)  # the 20 mm footprint's grid, not the paper's 50 x 50
        np.testing.assert_allclose(got, want.image, rtol=0, atol=1e-9 * np.abs(want.image).max())
    paper = image_of(fit_maps("tiny", None, geometry).forward(8.0, 7.0, 60.0))
    assert paper.shape == (50, 50)  # the paper's map is still the paper's (cached apart)
