"""``camera synth|features|calibrate --sensor FILE`` (SYNTHETIC camera): the description's camera
renders the frames and its probe, slab and loading make the solves, recorded in the outputs;
camera-only JSON files of earlier versions still work."""

from __future__ import annotations

import glob
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from elastimap.sensor import load

ROOT = Path(__file__).resolve().parents[2]
LAB = (
    'name = "lab-A"\n[probe]\nfootprint = 20.0\n'
    "layers = [{thickness = 2.0, E = 200.0}, {thickness = 3.0, E = 150.0}, {thickness = 5.0, E = 50.0}]\n"
    "[camera]\nwindow_native = 800\n"
)


def cli(module, *args):
    r = subprocess.run(
        [sys.executable, "-m", module, *map(str, args)], capture_output=True, text=True, timeout=600, cwd=ROOT
    )
    return r


@pytest.fixture
def lab(tmp_path):
    p = tmp_path / "lab.toml"
    p.write_text(LAB)
    return p


def solve_json(lab, d, h, E, *extra):
    r = cli("elastimap.solver.cli", "--sensor", lab, "--mesh", "tiny", "--json", "--d", d, "--h", h, "--E", E, *extra)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_synth_and_features_with_a_lab_sensor(tmp_path, lab):
    out = tmp_path / "frames"
    r = cli(
        "elastimap.camera.cli",
        "synth",
        "--sensor",
        lab,
        "--d",
        8,
        "--h",
        7,
        "--E",
        60,
        "--mesh",
        "tiny",
        "--frames",
        3,
        "--out",
        out,
    )
    assert r.returncode == 0, r.stderr
    assert "footprint window 80x80 px" in r.stdout  # 800 native pixels binned 10
    meta = json.loads((out / "synthetic_d8_h7_E60.json").read_text())
    assert meta["sensor_hash"] == load(lab).hash() and meta["sensor"]["footprint_mm"] == 20.0
    one = solve_json(lab, 8, 7, 60)
    assert [meta[f"fem_{k}"] for k in ("O1", "O2", "O3")] == [one[k] for k in ("O1", "O2", "O3")]
    frame = np.array(Image.open(sorted(glob.glob(str(out / "synthetic_d8_h7_E60_f*.png")))[0]))
    assert frame.shape == (104, 139)
    r = cli(
        "elastimap.camera.cli", "features", "--sensor", lab, "--json",
        "--images", str(out / "synthetic_d8_h7_E60_f*.png"),
        "--background", str(out / "synthetic_d8_h7_E60_background_f*.png"),
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["O1"] > 0


def test_calibrate_solves_the_lab_sensor_and_records_it(tmp_path, lab):
    out = tmp_path / "cal.json"
    r = cli("elastimap.camera.cli", "calibrate", "--sensor", lab, "--mesh", "tiny", "--frames", 2, "--out", out)
    assert r.returncode == 0, r.stderr
    cal = json.loads(out.read_text())
    assert cal["meta"]["sensor_hash"] == load(lab).hash() and cal["meta"]["sensor_description"]["name"] == "lab-A"
    assert set(cal["meta"]["versions"]) == {"dolfinx", "petsc", "gmsh", "torch", "numpy"}
    assert cal["sensor"]["window_native"] == 800
    first = cal["phantoms"][0]  # size-1 of dataset/phantoms.csv: on the 5 kPa, 20 mm slab of the sensor
    one = solve_json(lab, first["d"], first["h"], first["E"])
    assert [first[f"fem_{k}"] for k in ("O1", "O2", "O3")] == [one[k] for k in ("O1", "O2", "O3")]


def test_camera_only_json_of_earlier_versions(tmp_path):
    cam = tmp_path / "camera.json"
    cam.write_text(json.dumps({"binning": 5, "seed": 3}))
    out = tmp_path / "f"
    r = cli(
        "elastimap.camera.cli",
        "synth",
        "--sensor",
        cam,
        "--d",
        8,
        "--h",
        7,
        "--E",
        60,
        "--mesh",
        "tiny",
        "--frames",
        1,
        "--out",
        out,
    )
    assert r.returncode == 0, r.stderr
    meta = json.loads((out / "synthetic_d8_h7_E60.json").read_text())
    assert meta["sensor"]["binning"] == 5 and "sensor_hash" not in meta
    bad = tmp_path / "bad.toml"
    bad.write_text("[camera]\nbits = 10\n")
    r = cli("elastimap.camera.cli", "synth", "--sensor", bad, "--d", 8, "--h", 7, "--E", 60, "--out", tmp_path / "g")
    assert (
        r.returncode == 2 and r.stderr.strip() == f"error: --sensor: {bad}: camera.bits: must be 8, 12 or 16 (got 10)"
    )
