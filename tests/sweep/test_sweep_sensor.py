"""``sweep run --sensor FILE``: the sweep solves the described sensor (its rows are what ``solve
--sensor`` gives), records the description and its hash in the manifest, and refuses to mix
sensors in one folder; the paper's sweeps keep their sample ids and old folders resume."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pandas as pd
from sweep_helpers import run_sweep, synthetic

from elastimap.sensor import PAPER_HASH, load
from elastimap.sweep.run import SweepConfig, default_out

LAB = (
    'name = "lab-A"\n[probe]\nfootprint = 20.0\n'
    "layers = [{thickness = 2.0, E = 200.0}, {thickness = 3.0, E = 150.0}, {thickness = 5.0, E = 50.0}]\n"
    "[camera]\nwindow_native = 800\n"
)


def _lab(tmp_path, text=LAB, name="lab.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _manifest(out):
    return json.loads((out / "_sweep.json").read_text())


def test_rows_are_the_solves_of_the_described_sensor(tmp_path):
    lab, out = _lab(tmp_path), tmp_path / "lab"
    r = run_sweep(
        ["run", "--sensor", str(lab), "--n", "2", "--mesh", "tiny", "--jobs", "1", "--out", str(out), "--no-progress"]
    )
    assert r.returncode == 0, r.stderr
    man = _manifest(out)
    assert man["sensor_hash"] == load(lab).hash() != PAPER_HASH and man["sensor"]["name"] == "lab-A"
    assert man["base_params"]["probe"]["size"] == 20.0 and man["base_params"]["probe"]["layers"][0] == [2.0, 200.0]
    assert set(man["runs"][-1]["versions"]) == {"dolfinx", "petsc", "gmsh", "torch", "numpy"}
    row = pd.read_parquet(out).sort_values("sample_id").iloc[0]
    assert row["status"] == "ok" and json.loads(row["params_json"])["probe"]["size"] == 20.0
    s = subprocess.run(
        [sys.executable, "-m", "elastimap.solver.cli", "--sensor", str(lab), "--mesh", "tiny", "--json"]
        + ["--d", repr(float(row["d"])), "--h", repr(float(row["h"])), "--E", repr(float(row["E"]))],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert s.returncode == 0, s.stderr
    one = json.loads(s.stdout)
    assert [one[k] for k in ("O1", "O2", "O3", "force")] == [float(row[k]) for k in ("O1", "O2", "O3", "force")]


def test_one_folder_holds_one_sensor(tmp_path):
    lab, out = _lab(tmp_path), tmp_path / "mix"
    args = ["run", *synthetic(), "--n", "3", "--mesh", "tiny", "--jobs", "1", "--out", str(out), "--no-progress"]
    assert run_sweep([*args, "--sensor", str(lab)]).returncode == 0
    before = sorted(p.name for p in out.iterdir())
    r = run_sweep(args)  # the paper's sensor into the lab's folder
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert "holds a sweep of another sensor ('lab-A', hash" in r.stderr and "use another --out" in r.stderr
    other = _lab(tmp_path, LAB.replace("E = 200.0", "E = 250.0").replace("lab-A", "lab-B"), "other.toml")
    r = run_sweep([*args, "--sensor", str(other)])
    assert r.returncode == 2 and "another sensor ('lab-A'" in r.stderr and "'lab-B'" in r.stderr
    assert sorted(p.name for p in out.iterdir()) == before  # nothing written
    # the same sensor under another file name (same physics, same hash) resumes
    same = _lab(tmp_path, LAB.replace("lab-A", "renamed"), "same.toml")
    r = run_sweep([*args, "--sensor", str(same)])
    assert r.returncode == 0 and "3 skipped" in r.stdout, r.stdout + r.stderr


def test_interface_comes_from_the_sensor_unless_given(tmp_path):
    lab = _lab(tmp_path, LAB + "[interface]\nmodel = 'contact'\n")
    out = tmp_path / "contact"
    args = ["run", *synthetic(), "--n", "2", "--mesh", "tiny", "--jobs", "1", "--no-progress"]
    assert run_sweep([*args, "--sensor", str(lab), "--out", str(out)]).returncode == 0
    man = _manifest(out)
    assert man["base_params"]["disc"]["interface"] == "contact" and man["sensor"]["interface"]["model"] == "contact"
    out2 = tmp_path / "tied"
    assert run_sweep([*args, "--sensor", str(lab), "--interface", "tied", "--out", str(out2)]).returncode == 0
    man2 = _manifest(out2)
    assert man2["base_params"]["disc"]["interface"] == "tied" and man2["sensor"]["interface"]["model"] == "tied"
    assert man2["sensor_hash"] != man["sensor_hash"]


def test_paper_sweeps_keep_their_ids_and_old_folders_resume(tmp_path):
    out = tmp_path / "paper"
    args = ["run", *synthetic(), "--n", "5", "--mesh", "tiny", "--jobs", "1", "--phantoms", "--out", str(out)]
    assert run_sweep([*args, "--no-progress"]).returncode == 0
    man = _manifest(out)
    # the ids the code before the sensor description gave this command (main at c1a9e14)
    assert man["planned"][:3] == ["lhs-s0-b43416-00000", "lhs-s0-b43416-00001", "lhs-s0-b43416-00002"]
    assert man["sensor_hash"] == PAPER_HASH
    assert default_out(SweepConfig(mesh="tiny"), 5) == str(Path("sweeps") / "tiny-tied-lhs5-s0")
    # a folder written before manifests recorded the sensor is the paper's: it resumes
    for k in ("sensor", "sensor_hash"):
        del man[k]
    (out / "_sweep.json").write_text(json.dumps(man))
    r = run_sweep([*args, "--no-progress"])
    assert r.returncode == 0 and "14 skipped" in r.stdout, r.stdout + r.stderr
    assert _manifest(out)["sensor_hash"] == PAPER_HASH
