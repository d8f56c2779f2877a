"""``solve --sensor FILE``: a non-default sensor gives the features of the same parameters given
by flags (or, for what no flag sets, such as the footprint, by the Python API), and leaves the
paper sensor's solve as it was."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from elastimap.sensor import PAPER_HASH, Sensor, load
from elastimap.solver.cli import sensor_with_flags
from elastimap.solver.params import (
    Discretisation,
    ImageSpec,
    Inclusion,
    Loading,
    Probe,
    SolveParams,
    Tissue,
    from_sensor,
)

LAYERS = "[probe]\nlayers = [{thickness = 2.0, E = 200.0}, {thickness = 3.0, E = 150.0}, {thickness = 5.0, E = 50.0}]\n"
LAB = LAYERS.replace("[probe]\n", "[probe]\nfootprint = 20.0\n") + "[camera]\nwindow_native = 800\n"
FEATURES = ("O1", "O2", "O3", "force", "force_ref", "delta", "ndofs")


def _solve(*args) -> dict:
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "elastimap.solver.cli",
            "--mesh",
            "tiny",
            "--d",
            "6",
            "--h",
            "6",
            "--E",
            "40",
            "--json",
            *args,
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


@pytest.mark.parametrize(
    "flags",
    [
        {},
        {"layers": "2:200,3:150,5:50", "nu": 0.45},
        {"tissue_E": 8.0, "thickness": 25.0, "delta": 2.0, "interface": "contact"},
        {"force": 300.0},
    ],
)
def test_without_sensor_the_flags_build_what_they_always_built(flags):
    """The parameters `solve` built before the sensor description, for the same flags."""
    v = {
        "layers": None,
        "nu": 0.49,
        "tissue_E": 5.0,
        "thickness": 20.0,
        "delta": 3.0,
        "force": None,
        "interface": "tied",
    }
    v.update(flags)
    old = SolveParams(
        inclusion=Inclusion(d=6, h=6, E=40, nu=v["nu"]),
        tissue=Tissue(E=v["tissue_E"], thickness=v["thickness"], nu=v["nu"]),
        probe=Probe(
            layers=tuple(tuple(map(float, l.split(":"))) for l in v["layers"].split(","))
            if v["layers"]
            else Probe().layers,
            nu=v["nu"],
        ),
        loading=Loading(delta=v["delta"], force=v["force"]),
        disc=Discretisation(mesh="tiny", interface=v["interface"]),
        image=ImageSpec(),
    )
    s = sensor_with_flags(None, v, lambda k: k in flags)
    new = from_sensor(s, Inclusion(d=6, h=6, E=40, nu=v["nu"]), Discretisation(mesh="tiny"), ImageSpec())
    assert new == old
    assert s.is_paper == (not flags)


def test_sensor_file_gives_the_features_of_the_same_flags(tmp_path):
    p = tmp_path / "layers.toml"
    p.write_text(LAYERS)
    by_file = _solve("--sensor", str(p))
    by_flags = _solve("--layers", "2:200,3:150,5:50")
    paper = _solve()
    assert {k: by_file[k] for k in FEATURES} == {k: by_flags[k] for k in FEATURES}
    assert by_file["sensor_hash"] == by_flags["sensor_hash"] == load(p).hash() != PAPER_HASH
    assert paper["sensor_hash"] == PAPER_HASH and paper["sensor"] == Sensor().to_dict()
    # a softer first layer presses the lesion less: the features differ where they should
    assert by_file["O1"] != paper["O1"] and by_file["force"] < paper["force"]


def test_non_default_footprint_matches_the_api_and_flags_override_the_file(tmp_path):
    from elastimap.solver.api import solve

    p = tmp_path / "lab.toml"
    p.write_text(LAB)
    out = _solve("--sensor", str(p))
    api = solve(
        SolveParams(
            inclusion=Inclusion(d=6, h=6, E=40),
            probe=Probe(size=20.0, layers=((2.0, 200.0), (3.0, 150.0), (5.0, 50.0))),
            disc=Discretisation(mesh="tiny"),
        ).validate()
    )
    assert [out[k] for k in ("O1", "O2", "O3", "force")] == [api.O1, api.O2, api.O3, api.force]
    assert out["image_shape"] == [40, 40]  # 20 mm at 0.5 mm
    assert out["sensor"]["probe"]["footprint"] == 20.0 and out["sensor_hash"] == load(p).hash()
    over = _solve("--sensor", str(p), "--delta", "2")
    assert over["delta"] == 2.0 and over["sensor"]["loading"]["delta"] == 2.0
    assert over["sensor"]["probe"]["footprint"] == 20.0 and over["sensor_hash"] != out["sensor_hash"]


def test_text_summary_names_the_model_solved_for_a_tilted_sensor(tmp_path):
    """A tilted plate needs the full model (``from_sensor``); the text summary says which model
    was solved, not whether ``--full`` was given."""
    p = tmp_path / "tilted.toml"
    p.write_text("[loading]\ndelta = 3.0\ntilt = 0.01\n")
    r = subprocess.run(
        [sys.executable, "-m", "elastimap.solver.cli", "--mesh", "tiny", "--d", "6", "--h", "6", "--E", "40"]
        + ["--sensor", str(p)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert "full model" in r.stdout and "quarter model" not in r.stdout
