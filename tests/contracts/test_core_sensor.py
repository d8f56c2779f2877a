"""The sensor description (elastimap/sensor.py): the paper's sensor is every room's default,
files round-trip, the hash is canonical, and bad descriptions get one line naming the field."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import pytest

from elastimap.camera.optics import SensorModel
from elastimap.errors import UserError
from elastimap.sensor import PAPER_HASH, CameraSpec, Layer, ProbeSpec, Sensor, dumps, load
from elastimap.solver.params import INTERFACES, Discretisation, ImageSpec, Inclusion, SolveParams, from_sensor

LAB = """
name = "lab-A"
[probe]
footprint = 20.0
layers = [ { thickness = 2.0, E = 200.0 }, { thickness = 3.0, E = 150.0 }, { thickness = 5.0, E = 50.0 } ]
[camera]
window_native = 800
"""


def write(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_the_paper_sensor_is_every_rooms_default():
    s = Sensor().validate()
    assert from_sensor(s) == SolveParams()
    assert SensorModel.of(s) == SensorModel()
    assert tuple(INTERFACES) == ("tied", "contact", "bonded") and s.interface.model in INTERFACES
    # the camera's fields are declared once, in the core
    assert [f.name for f in dataclasses.fields(SensorModel)] == [f.name for f in dataclasses.fields(CameraSpec)]
    assert s.is_paper and Sensor(name="other name").is_paper


def test_paper_hash_is_pinned():
    """Outputs of the paper's sensor record this hash; changing it splits old and new sweeps."""
    assert PAPER_HASH == Sensor().hash() == "3a396e9f7d07b0e2"
    # integers given for float fields in code are the same sensor
    ints = Sensor(probe=ProbeSpec(footprint=25, layers=(Layer(2, 300), Layer(3, 150), Layer(5, 50))))
    assert ints == Sensor() and ints.hash() == PAPER_HASH


def test_toml_round_trip_and_canonical_hash(tmp_path):
    s = load(write(tmp_path, LAB))
    assert s.name == "lab-A" and s.probe.footprint == 20.0 and s.camera.footprint_mm == 20.0
    assert s.probe.layers == (Layer(2.0, 200.0), Layer(3.0, 150.0), Layer(5.0, 50.0))
    assert s.camera.window_native == 800 and s.tissue == Sensor().tissue
    assert not s.is_paper and s.hash() != PAPER_HASH
    back = load(write(tmp_path, dumps(s, "adopted"), "back.toml"))
    assert back == s and back.hash() == s.hash()
    # ints for floats, another name, keys in another order: the same physics, the same hash
    same = LAB.replace("20.0", "20").replace('"lab-A"', '"renamed"')
    assert load(write(tmp_path, same, "same.toml")).hash() == s.hash()
    # an output's JSON record reads back as the description
    rec = tmp_path / "rec.json"
    rec.write_text(json.dumps(s.record()))
    assert load(rec) == s


def test_force_control_and_solver_parameters(tmp_path):
    s = load(write(tmp_path, "[loading]\nforce = 400.0\n[interface]\nmodel = 'contact'\nfriction_kt = 2.0\n"))
    p = from_sensor(s, Inclusion(d=6, h=6, E=40), Discretisation(mesh="tiny"), ImageSpec(pixel=0.5)).validate()
    assert p.loading.force == 400.0 and p.disc.interface == "contact" and p.disc.friction_kt == 2.0
    assert p.disc.mesh == "tiny" and p.inclusion.d == 6
    assert "force" not in Sensor().to_dict()["loading"]


@pytest.mark.parametrize(
    "text, message",
    [
        (
            "[probe]\nlayers = [{thickness = 2.0, E = 300.0}, {thickness = 3.0, E = -5.0}]",
            "probe.layers[2].E: must be > 0 kPa",
        ),
        ("[probe]\nlayers = [{thickness = 2.0}]", "probe.layers[1].E: is required"),
        ("[probe]\nlayers = []", "probe.layers: at least one layer"),
        ("[probe]\nnu = 0.5", "probe.nu: must be in (-1, 0.5)"),
        ("[probe]\nfootprint = 'wide'", "probe.footprint: must be a number"),
        ("[probe]\ncolour = 'blue'", "probe.colour: unknown field"),
        ("[tissue]\nE = 0", "tissue.E: must be > 0 kPa"),
        ("[tissue]\nthickness = 200.0", "tissue.thickness: must be <= the slab size"),
        ("[loading]\ndelta = 6.0", "loading.delta: the plate travels up to 6 mm; at most 5 mm"),
        ("[loading]\nforce = 100.0\ntilt = 0.01", "loading.tilt: a tilted plate needs the plate travel delta"),
        ("[interface]\nmodel = 'glued'", "interface.model: must be one of tied, contact, bonded"),
        ("[camera]\nbits = 10", "camera.bits: must be 8, 12 or 16"),
        ("[camera]\nbinning = 2.5", "camera.binning: must be an integer"),
        ("[camera]\nled_power = [1.0, 1.0]", "camera.led_power: must be a list of four powers"),
        ("[camera]\nfootprint_mm = 20.0", "camera.footprint_mm: is the probe's footprint"),
        ("[camera]\nlens = 3", "camera.lens: unknown field"),
        ("[lesion]\nd = 3", "lesion: unknown section or field"),
        ("schema = 2", "schema: this elastimap reads sensor descriptions of schema 1"),
        ("name = ''", "name: must be a non-empty string"),
        ("[probe\nfootprint = 2", "not valid TOML"),
    ],
)
def test_bad_descriptions_name_the_field(tmp_path, text, message):
    p = write(tmp_path, text)
    with pytest.raises(UserError) as exc:
        load(p)
    assert exc.value.param == "sensor"
    assert exc.value.message.startswith(f"{p}: ") and message in exc.value.message, exc.value.message
    assert "\n" not in str(exc.value)


def test_missing_file_is_one_line(tmp_path):
    with pytest.raises(UserError, match="nope.toml: no such file"):
        load(tmp_path / "nope.toml")


def test_solve_cli_refuses_a_bad_description_with_one_line(tmp_path):
    p = write(tmp_path, "[probe]\nlayers = [{thickness = 2.0, E = -5.0}]")
    r = subprocess.run(
        [sys.executable, "-m", "elastimap.solver.cli", "--mesh", "tiny", "--sensor", str(p)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip() == f"error: --sensor: {p}: probe.layers[1].E: must be > 0 kPa (got -5)"
