"""``gap synth|diagnose --sensor``: a lab's own sensor through the diagnosis, and the adopt loop.

The toy backend (SYNTHETIC analytic stand-in, not physics) checks the logic quickly; one run on
the tiny mesh of the forward model closes the loop with the real solver.  Data here are SYNTHETIC.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from elastimap.gap.adopt import ADOPTED
from elastimap.sensor import PAPER_HASH, load

ROOT = Path(__file__).resolve().parents[2]
LAB = (
    'name = "lab-A"\n[probe]\nfootprint = 20.0\n'
    "layers = [{thickness = 2.0, E = 200.0}, {thickness = 3.0, E = 150.0}, {thickness = 5.0, E = 50.0}]\n"
    "[camera]\nwindow_native = 800\n"
)


def gap(*args, timeout=600):
    r = subprocess.run(
        [sys.executable, "-m", "elastimap.gap.cli", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
    )
    return r


@pytest.fixture
def lab(tmp_path):
    p = tmp_path / "lab.toml"
    p.write_text(LAB)
    return p


TOY = ("--backend", "toy", "--cache", "none", "--no-progress")


def test_toy_adopt_loop_closes(tmp_path, lab):
    m = tmp_path / "m"
    r = gap(
        "synth",
        "--sensor",
        lab,
        "--effect",
        "probe_E1=150",
        "--n",
        8,
        "--mesh",
        "tiny",
        "--frames",
        4,
        "--out",
        m,
        *TOY,
    )
    assert r.returncode == 0, r.stderr
    side = json.loads((m / "measured.json").read_text())
    assert side["sensor_hash"] == load(lab).hash() and side["sensor"]["window_native"] == 800
    d1 = tmp_path / "d1"
    common = ("--effects", "probe_E1,friction,aspect", "--error-mesh", "none", "--no-inverse", *TOY)
    r = gap("diagnose", "--measured", m, "--out", d1, *common)  # the sensor comes from the measured set
    assert r.returncode == 0, r.stderr
    assert "explained by probe_E1" in r.stdout and f"-> {d1 / ADOPTED}" in r.stdout
    adopted = load(d1 / ADOPTED)
    assert adopted.probe.layers[0].E == pytest.approx(150.0, rel=0.03) and adopted.probe.footprint == 20.0
    assert adopted.probe.layers[1:] == load(lab).probe.layers[1:] and adopted.camera == load(lab).camera
    doc = json.loads((d1 / "diagnosis.json").read_text())
    assert doc["sensor_hash"] == load(lab).hash() and doc["adoption"]["adopted"]["sensor_hash"] == adopted.hash()
    assert set(doc["provenance"]["versions"]) == {"dolfinx", "petsc", "gmsh", "torch", "numpy"}
    assert "adopted probe_E1 = " in (d1 / "report.md").read_text()
    d2 = tmp_path / "d2"
    r = gap("diagnose", "--measured", m, "--sensor", d1 / ADOPTED, "--out", d2, *common)
    assert r.returncode == 0, r.stderr
    assert "no gap beyond the model-form level" in r.stdout and not (d2 / ADOPTED).exists()
    assert json.loads((d2 / "diagnosis.json").read_text())["sensor_hash"] == adopted.hash()


def test_lesion_effects_are_reported_not_adopted(tmp_path, lab):
    m, d = tmp_path / "m", tmp_path / "d"
    r = gap(
        "synth", "--sensor", lab, "--effect", "aspect=0.7", "--n", 8, "--mesh", "tiny", "--frames", 4, "--out", m, *TOY
    )
    assert r.returncode == 0, r.stderr
    r = gap(
        "diagnose",
        "--measured",
        m,
        "--out",
        d,
        "--effects",
        "aspect,probe_E1",
        "--error-mesh",
        "none",
        "--no-inverse",
        *TOY,
    )
    assert r.returncode == 0, r.stderr
    assert "explained by aspect" in r.stdout and "reported, not adopted: aspect" in r.stdout
    assert not (d / ADOPTED).exists()
    rows = json.loads((d / "diagnosis.json").read_text())["adoption"]["rows"]
    assert [(x["effect"], x["adopted"]) for x in rows] == [("aspect", False)]


def test_bad_sensor_and_effects_that_do_not_apply(tmp_path, lab):
    bad = tmp_path / "bad.toml"
    bad.write_text("[tissue]\nnu = 0.7\n")
    r = gap("synth", "--sensor", bad, "--n", 5, "--out", tmp_path / "x", *TOY)
    assert (
        r.returncode == 2 and r.stderr.strip() == f"error: --sensor: {bad}: tissue.nu: must be in (-1, 0.5) (got 0.7)"
    )
    assert not (tmp_path / "x").exists()
    two = tmp_path / "two.toml"
    two.write_text("[probe]\nlayers = [{thickness = 4.0, E = 200.0}, {thickness = 6.0, E = 50.0}]\n")
    r = gap("synth", "--sensor", two, "--effect", "probe_E3=40", "--n", 5, "--out", tmp_path / "y", *TOY)
    assert r.returncode == 2 and "probe_E3 does not apply to this sensor" in r.stderr


def test_paper_measured_sets_diagnose_with_the_papers_sensor(tmp_path):
    m, d = tmp_path / "m", tmp_path / "d"
    assert (
        gap("synth", "--effect", "friction=0.4", "--n", 8, "--mesh", "tiny", "--frames", 4, "--out", m, *TOY).returncode
        == 0
    )
    assert "sensor_description" not in json.loads((m / "measured.json").read_text())  # as before
    r = gap(
        "diagnose",
        "--measured",
        m,
        "--out",
        d,
        "--effects",
        "friction,probe_E1",
        "--error-mesh",
        "none",
        "--no-inverse",
        *TOY,
    )
    assert r.returncode == 0, r.stderr
    doc = json.loads((d / "diagnosis.json").read_text())
    assert doc["sensor_hash"] == PAPER_HASH and doc["adoption"]["rows"][0]["effect"] == "friction"
    assert load(d / ADOPTED).interface.friction_kt == pytest.approx(0.4, rel=0.05)


@pytest.mark.slow
def test_fem_tiny_adopt_loop(tmp_path, lab):
    """The loop with the forward model (tiny mesh): a SYNTHETIC lab whose probe's first layer is
    150 kPa where its description says 200; the diagnosis adopts it, the next one finds no gap."""
    m, d1, d2 = tmp_path / "m", tmp_path / "d1", tmp_path / "d2"
    cache = tmp_path / "cache"
    r = gap(
        "synth",
        "--sensor",
        lab,
        "--effect",
        "probe_E1=150",
        "--n",
        6,
        "--mesh",
        "tiny",
        "--frames",
        4,
        "--out",
        m,
        "--cache",
        cache,
        "--no-progress",
    )
    assert r.returncode == 0, r.stderr
    common = (
        "--effects",
        "probe_E1,friction",
        "--error-mesh",
        "none",
        "--no-inverse",
        "--cache",
        cache,
        "--no-progress",
    )
    r = gap("diagnose", "--measured", m, "--sensor", lab, "--out", d1, *common)
    assert r.returncode == 0, r.stderr
    assert "explained by probe_E1" in r.stdout
    assert load(d1 / ADOPTED).probe.layers[0].E == pytest.approx(150.0, rel=0.03)
    r = gap("diagnose", "--measured", m, "--sensor", d1 / ADOPTED, "--out", d2, *common)
    assert r.returncode == 0, r.stderr
    assert "no gap beyond the model-form level" in r.stdout
