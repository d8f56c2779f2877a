"""workflows/adopt_loop.py, the adopt loop on a SYNTHETIC lab (docs/howto/your-own-sensor.md, "The
loop on a SYNTHETIC lab"), on the tiny mesh with tiny sizes: the true sensor is the lab's with the
withheld effect, round 0 adopts what its diagnosis found, round 1 runs the ordinary commands on the
adopted file, and a second run of the study resumes without solving again."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from elastimap.sensor import Sensor, load
from elastimap.workflows.adopt_loop import WITHHELD, table_md, write_sensors

SCRIPT = Path(__file__).resolve().parents[2] / "workflows" / "adopt_loop.py"


def test_the_true_sensor_is_the_lab_with_the_withheld_effect(tmp_path):
    lab, true = write_sensors(tmp_path, None, "probe_E1=200")
    assert load(lab).hash() == Sensor().hash()  # the lab says the paper's sensor
    t = load(true)
    assert t.probe.layers[0].E == 200.0 and t.replace(probe=Sensor().probe, name="lab") == load(lab)
    assert WITHHELD == "probe_E1=200"
    (tmp_path / "none").mkdir()
    none_lab, none_true = write_sensors(tmp_path / "none", None, "none")
    assert load(none_true).hash() == load(none_lab).hash()


def study(out: Path) -> subprocess.CompletedProcess:
    args = (
        "--out", out, "--mesh", "tiny", "--data-mesh", "tiny", "--n", 12, "--phantoms", 6, "--lesions", 2,
        "--frames", 3, "--hidden", 3, "--repeats", 1, "--effects", "probe_E1,tissue_nu", "--error-mesh", "none",
        "--rounds", 2, "--jobs", 1,
    )  # fmt: skip
    # six phantoms: with four, the model-form level (gap/model_form.py) leaves probe_E1 and tissue_nu
    # ambiguous (nothing adopted, as it should be); six separate them
    r = subprocess.run(
        [sys.executable, str(SCRIPT), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=1800,
        cwd=SCRIPT.parents[1],
    )
    assert r.returncode == 0, r.stdout + r.stderr
    return r


@pytest.mark.slow
def test_adopt_loop_adopts_the_winner_and_the_next_round_sweeps_it(tmp_path):
    out = tmp_path / "loop"
    study(out)
    doc = json.loads((out / "loop.json").read_text())
    assert doc["synthetic"] and doc["withheld"] == WITHHELD
    r0, r1, none = doc["rounds"]
    assert (r0["round"], r1["round"], none["round"]) == (0, 1, "no-effect")
    # round 0: the diagnosis explains the gap, and the adopted file holds its winner at the fitted magnitude
    diag = json.loads((out / "round0" / "diagnosis" / "diagnosis.json").read_text())
    ev = diag["evaluation"]
    assert ev["outcome"] == "explained" and r0["winner"] == ev["winner"]
    adopted = load(out / "round0" / "diagnosis" / "adopted-sensor.toml")
    [row] = r0["adopted"]
    assert row["effect"] == ev["winner"] == "probe_E1"
    assert adopted.probe.layers[0].E == pytest.approx(ev["reported"]["probe_E1"]["magnitude"][0])
    assert adopted.probe.layers[0].E == pytest.approx(row["magnitude"])
    assert adopted.replace(probe=Sensor().probe, name="lab") == load(out / "lab.toml")  # only the winner changed
    # round 1 is the ordinary commands on the adopted file: its sweep, model and estimates record its hash
    man = json.loads((out / "round1" / "sweep" / "_sweep.json").read_text())
    assert man["sensor_hash"] == adopted.hash() == r1["sensor_hash"] != r0["sensor_hash"]
    model = json.loads((out / "round1" / "model" / "model-scg" / "model.json").read_text())
    assert model["training"]["sensor_hash"] == adopted.hash()
    assert {e["sensor_hash"] for e in json.loads((out / "round1" / "infer.json").read_text())} == {adopted.hash()}
    # the adopted sensor leaves less gap than the lab's description, the no-effect case none significant
    assert r1["chi2_baseline"] < r0["chi2_baseline"] and r0["chi2_baseline"] > r0["chi2_threshold"]
    assert none["outcome"] == "no significant gap" and none["sensor_hash"] == r0["sensor_hash"]
    for r in (r0, r1, none):
        assert r["n"] == 2 and all(r[f"{q}_n"] == 2 and r[f"{q}_mre"] >= 0 for q in "dhE")
    assert (out / "loop.md").read_text().startswith("SYNTHETIC") and table_md(doc) in (out / "loop.md").read_text()
    # a second run resumes: nothing is synthesised, trained, calibrated or diagnosed again
    before = (out / "commands.log").read_text()
    study(out)
    new = [x for x in (out / "commands.log").read_text()[len(before) :].splitlines() if x.startswith("$ elastimap")]
    assert new and all(x.startswith("$ elastimap sweep run") for x in new), new  # the sweeps resume themselves
    again = json.loads((out / "loop.json").read_text())
    assert again["rounds"][1]["sensor_hash"] == adopted.hash()
    assert [r["wall_s"] for r in again["rounds"]] == [r["wall_s"] for r in doc["rounds"]]  # the first run's times
    assert again["data_s"] == doc["data_s"] and again["date"] == doc["date"] and again["date"].endswith("UTC")


@pytest.mark.parametrize(
    "args, flag",
    [(["--n", "0"], "--n"), (["--withheld", "probe_E9=3"], "--withheld"), (["--lab", "missing.toml"], "--lab")],
)
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, args, flag):
    out = tmp_path / "loop"
    r = subprocess.run(
        [sys.executable, str(SCRIPT), "--out", str(out), *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert r.returncode == 2 and r.stderr.startswith(f"error: {flag}: ") and r.stderr.count("\n") == 1, r.stderr
    assert not out.exists()
