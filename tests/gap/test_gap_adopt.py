"""Adopting diagnosed effects into the sensor description (gap/adopt.py) and the effects library
about another sensor (gap/effects.py, ``for_sensor``)."""

from __future__ import annotations

import math

import pytest

from elastimap.gap import effects as fx
from elastimap.gap.adopt import adopt
from elastimap.sensor import Layer, Sensor, dumps, load

LAB = (
    'name = "lab-A"\n[probe]\nfootprint = 20.0\n'
    "layers = [{thickness = 2.0, E = 200.0}, {thickness = 3.0, E = 150.0}, {thickness = 5.0, E = 50.0}]\n"
    "[camera]\nwindow_native = 800\n"
)


@pytest.fixture
def lab(tmp_path):
    p = tmp_path / "lab.toml"
    p.write_text(LAB)
    return load(p)


def test_the_paper_sensor_gives_the_library_itself():
    t = fx.for_sensor(Sensor())
    assert t.keys() == fx.EFFECTS.keys() and all(t[n] is fx.EFFECTS[n] for n in t)


def test_effects_are_recentred_on_the_sensor(lab):
    t = fx.for_sensor(lab)
    e1 = t["probe_E1"]
    assert e1.nominal == 200.0 and e1.is_nominal(200.0) and 200.0 in e1.grid
    assert e1.grid == pytest.approx([x * 200 / 300 for x in fx.EFFECTS["probe_E1"].grid])
    assert e1.limits == (pytest.approx(40.0), None)
    assert t["probe_E2"] is fx.EFFECTS["probe_E2"]  # the paper's value: unchanged
    # an adopted friction is the next diagnosis's nominal, grid shifted, never below its limit 0
    f = fx.for_sensor(lab.replace(interface=lab.interface.__class__(friction_kt=0.3)))["friction"]
    assert f.nominal == 0.3 and min(f.grid) == pytest.approx(0.3) and f.limits == (0.0, None)
    # a two-layer probe has no third layer to diagnose
    two = lab.replace(probe=lab.probe.__class__(footprint=20.0, layers=(Layer(2.0, 200.0), Layer(8.0, 60.0))))
    t2 = fx.for_sensor(two)
    assert "probe_E3" not in t2 and "probe_t3" not in t2 and t2["probe_E2"].nominal == 60.0
    with pytest.raises(Exception, match="probe_E3 does not apply"):
        fx.parse_list("probe_E3", table=t2)
    assert [e.name for e in fx.parse_list(None, table=t2)] == [n for n in fx.DEFAULT_CANDIDATES if n in t2]


def test_sensor_effects_are_adopted_at_their_magnitude(lab):
    a = adopt(lab, {"probe_E1": [230.0]})
    assert a.sensor.probe.layers[0] == Layer(2.0, 230.0) and a.adopted == ["probe_E1"]
    assert a.sensor.name == "lab-A+adopted" and a.sensor.hash() != lab.hash()
    b = adopt(lab, {"friction": [0.4], "blur": [0.5], "indentation": [0.3], "led_imbalance": [0.7]})
    s = b.sensor
    assert s.interface.friction_kt == 0.4 and s.camera.blur_mm == 0.5 and s.loading.delta == pytest.approx(3.3)
    assert s.camera.led_power[0] == pytest.approx(0.7) and s.camera.led_power[1:] == lab.camera.led_power[1:]
    assert s.probe == lab.probe and s.tissue == lab.tissue
    c = adopt(lab, {"probe_layers_E": [220.0, 140.0, 55.0]})
    assert [l.E for l in c.sensor.probe.layers] == [220.0, 140.0, 55.0]
    assert all(r["via"] == "probe_layers_E" for r in c.rows)
    t = adopt(Sensor(), {"tilt": [0.5], "skin": [40.0], "tissue_nu": [0.47]}).sensor
    assert t.loading.tilt == pytest.approx(math.radians(0.5)) and t.tissue.skin_thickness == fx.SKIN_THICKNESS
    assert t.tissue.skin_E == 40.0 and t.tissue.nu == 0.47


def test_lesion_effects_are_reported_not_adopted(lab, tmp_path):
    a = adopt(lab, {"aspect": [0.8], "friction": [0.2]})
    assert a.adopted == ["friction"] and a.reported_only == ["aspect"]
    assert "not of the sensor" in a.rows[0]["why"]
    only = adopt(lab, {"offaxis": [2.0]})
    assert only.sensor == lab and only.adopted == []
    # what is written reads back as the adopted sensor
    p = tmp_path / "adopted-sensor.toml"
    p.write_text(dumps(a.sensor, "adopted: friction = 0.2 kPa/mm"))
    assert load(p) == a.sensor


def test_adopting_the_nominal_changes_nothing(lab):
    t = fx.for_sensor(lab)
    a = adopt(lab, {"probe_E1": [t["probe_E1"].nominal], "saturation": [lab.camera.w_sat]})
    assert a.sensor.replace(name=lab.name) == lab


def test_the_adopted_file_belongs_to_the_report_folder():
    """A rerun of ``gap diagnose`` into its own ``--out`` replaces the adopted file with the report."""
    from elastimap.gap.adopt import ADOPTED
    from elastimap.gap.report import REPORT_FILES

    assert ADOPTED in REPORT_FILES
