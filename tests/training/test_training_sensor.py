"""The trained model records the sensor of its sweep (and the library versions): ``train`` on a
``sweep run --sensor`` folder (SYNTHETIC stand-in solver: not physics)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from elastimap.sensor import PAPER_HASH, load

ROOT = Path(__file__).resolve().parents[2]


def run_sweep(args):
    """``sweep ARGS`` with the SYNTHETIC stand-in solver (the hidden ``--solver synthetic``)."""
    return subprocess.run(
        [sys.executable, "-m", "elastimap.sweep.cli", *args], capture_output=True, text=True, timeout=600, cwd=ROOT
    )


LAB = (
    'name = "lab-A"\n[probe]\nfootprint = 20.0\n'
    "layers = [{thickness = 2.0, E = 200.0}, {thickness = 3.0, E = 150.0}, {thickness = 5.0, E = 50.0}]\n"
    "[camera]\nwindow_native = 800\n"
)


def _train(data, out):
    args = ["--data", data, "--out", out, "--hidden", "2", "--repeats", "1", "--epochs", "5", "--no-progress"]
    r = subprocess.run(
        [sys.executable, "-m", "elastimap.training.cli", *map(str, args), "--test-split", "0.25"],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr
    found = sorted(out.rglob("model.json"))
    assert found, list(out.rglob("*"))
    return json.loads(found[0].read_text())


def test_model_records_the_sensor_of_its_sweep(tmp_path):
    lab = tmp_path / "lab.toml"
    lab.write_text(LAB)
    data, paper = tmp_path / "lab", tmp_path / "paper"
    common = ["run", "--solver", "synthetic", "--n", "16", "--mesh", "tiny", "--jobs", "1", "--no-progress"]
    assert run_sweep([*common, "--sensor", str(lab), "--out", str(data)]).returncode == 0
    assert run_sweep([*common, "--out", str(paper)]).returncode == 0
    m = _train(data, tmp_path / "train-lab")["training"]
    assert m["sensor_hash"] == load(lab).hash() and m["sensor"]["probe"]["footprint"] == 20.0
    assert set(m["versions"]) == {"dolfinx", "petsc", "gmsh", "torch", "numpy"} and m["code_version"]
    assert _train(paper, tmp_path / "train-paper")["training"]["sensor_hash"] == PAPER_HASH
