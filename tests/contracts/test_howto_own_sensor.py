"""docs/howto/your-own-sensor.md, step by step on the tiny mesh with a non-default sensor
(layers 2:200,3:150,5:50, a 20 mm footprint): describe → sweep → train → calibrate from the
phantoms' frames → infer from lesion frames.  The frames are SYNTHETIC (``camera synth``); the
diagnose-and-adopt steps are tests/test_gap_sensor.py."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from elastimap.sensor import load

ROOT = Path(__file__).resolve().parents[2]
LAB = (
    'name = "lab-A"\n[probe]\nfootprint = 20.0\n'
    "layers = [{thickness = 2.0, E = 200.0}, {thickness = 3.0, E = 150.0}, {thickness = 5.0, E = 50.0}]\n"
    "[camera]\nwindow_native = 800\n"
)


def elastimap(*args, timeout=900):
    r = subprocess.run(
        [sys.executable, "-m", "elastimap.cli", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
    )
    assert r.returncode == 0, f"elastimap {' '.join(map(str, args))}\n{r.stdout}\n{r.stderr}"
    return r.stdout


@pytest.mark.slow
def test_describe_sweep_train_calibrate_infer(tmp_path):
    lab = tmp_path / "lab-A.toml"
    lab.write_text(LAB)
    h = load(lab).hash()
    # describe: one solve checks the description
    one = json.loads(elastimap("solve", "--sensor", lab, "--mesh", "tiny", "--json"))
    assert one["sensor_hash"] == h and one["image_shape"] == [40, 40]
    # sweep it (with the calibration phantoms) and train
    data = tmp_path / "sweeps" / "lab-A"
    elastimap(
        "sweep",
        "run",
        "--sensor",
        lab,
        "--n",
        24,
        "--mesh",
        "tiny",
        "--jobs",
        1,
        "--phantoms",
        "--out",
        data,
        "--no-progress",
    )
    elastimap(
        "train",
        "--data",
        data,
        "--hidden",
        4,
        "--repeats",
        2,
        "--epochs",
        30,
        "--out",
        tmp_path / "runs" / "lab-A",
        "--no-progress",
    )
    model = next((tmp_path / "runs" / "lab-A").rglob("model.json")).parent
    assert json.loads((model / "model.json").read_text())["training"]["sensor_hash"] == h
    # calibrate from the phantoms' frames (SYNTHETIC camera of the described sensor)
    cal = tmp_path / "lab-A-calibration.json"
    elastimap("camera", "calibrate", "--sensor", lab, "--mesh", "tiny", "--frames", 2, "--out", cal)
    assert json.loads(cal.read_text())["meta"]["sensor_hash"] == h
    # infer from a lesion's frames
    frames = tmp_path / "lesion"
    elastimap(
        "camera",
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
        frames,
    )
    infer = (
        "camera", "infer", "--model", model, "--calibration", cal, "--json",
        "--images", frames / "synthetic_d8_h7_E60_f*.png",
        "--background", frames / "synthetic_d8_h7_E60_background_f*.png",
    )  # fmt: skip
    [est] = json.loads(elastimap(*infer, "--sensor", lab))
    assert set(est) >= {"d", "h", "E", "code_version", "versions"} and est["sensor_hash"] == h, est
    assert [est[q] for q in "dhE"] == [r[q] for r in json.loads(elastimap(*infer)) for q in "dhE"]
    # --refine: the FEM fit presses with the lab's probe (identify/forward_maps.py, fit_maps(sensor=))
    [ref] = json.loads(elastimap(*infer, "--sensor", lab, "--refine", "--mesh", "tiny"))
    assert ref["input"].endswith("+fem_refined") and ref["sensor_hash"] == h and ref["fit_solves"] > 0, ref
    assert all(ref[f"{q}_lo"] <= ref[q] <= ref[f"{q}_hi"] for q in "dhE"), ref
    # another sensor's lesion is refused before any work, with one line
    paper = tmp_path / "paper.toml"
    paper.write_text("")
    r = subprocess.run(
        [sys.executable, "-m", "elastimap.cli", *map(str, infer), "--sensor", str(paper)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "was made with another sensor" in r.stderr, r.stderr


@pytest.mark.slow
def test_demo_with_a_sensor(tmp_path):
    lab = tmp_path / "lab-A.toml"
    lab.write_text(LAB)
    out = tmp_path / "demo"
    elastimap("demo", "--sensor", lab, "--n", 20, "--mesh", "tiny", "--jobs", 1, "--out", out)
    h = load(lab).hash()
    assert json.loads((out / "data" / "_sweep.json").read_text())["sensor_hash"] == h
    assert json.loads(next((out / "train").rglob("model.json")).read_text())["training"]["sensor_hash"] == h
    bad = tmp_path / "bad.toml"
    bad.write_text("[loading]\ndelta = 9.0\n")
    r = subprocess.run(
        [sys.executable, "-m", "elastimap.cli", "demo", "--sensor", str(bad), "--out", str(tmp_path / "x")],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert r.returncode == 2 and "loading.delta" in r.stderr and not (tmp_path / "x").exists()
