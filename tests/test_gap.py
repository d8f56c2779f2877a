"""Sim-to-real gap diagnosis.  Most tests use the analytic TOY backend (not physics:
it only exercises the gap logic); one runs real tiny-mesh FEM solves through the cache."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # `gap` is not yet in the installed package list (pyproject is the lead's)
    sys.path.insert(0, str(ROOT))

import numpy as np
import pandas as pd
import pytest

from elastimap.errors import UserError
from elastimap.gap import effects as fx
from elastimap.gap import measured, synth
from elastimap.gap.diagnose import Settings, diagnose
from elastimap.gap.simulate import Simulator


@pytest.fixture(scope="module")
def toy():
    return Simulator(None, "tiny", "toy")


@pytest.fixture(scope="module")
def dhe():
    return synth.phantom_design(10, 0)


# ---------------------------------------------------------------- effects and format
def test_effect_spec_parsing_and_switches():
    (e, m), = fx.parse_spec("friction=0.3")
    assert e.name == "friction" and m == 0.3
    for bad in ("friction", "nope=1", "friction=x", "friction=0.1,friction=0.2", "skin=1000"):
        with pytest.raises(UserError):
            fx.parse_spec(bad)
    from elastimap.solver.params import SolveParams
    p = SolveParams()
    assert fx.get("friction").apply_params(p, 0.0) is p                       # nominal = baseline
    assert fx.get("friction").apply_params(p, 0.5).disc.friction_kt == 0.5
    assert fx.get("skin").apply_params(p, 20.0).tissue.skin_thickness == fx.SKIN_THICKNESS
    assert fx.get("probe_moduli").apply_params(p, 2.0).probe.layers[0][1] == 600.0
    assert fx.get("offaxis").apply_params(p, 2.0).disc.symmetry == "full"
    from elastimap.camera.optics import SensorModel
    assert fx.get("saturation").apply_sensor(SensorModel(), 0.2).w_sat == 0.2
    assert "offaxis" not in fx.DEFAULT_CANDIDATES


def test_phantom_design_is_valid_for_every_effect():
    from elastimap.solver.params import SolveParams
    from elastimap.gap.simulate import base_params
    for row in synth.phantom_design(30, 3):
        for e in fx.EFFECTS.values():
            for m in e.grid:
                e.apply_params(base_params("tiny", *row), m).validate()


def test_measured_roundtrip_and_validation(tmp_path, toy, dhe):
    meas, truth = synth.synthesize(dhe, [(fx.get("skin"), 30.0)], toy, frames=4, seed=1)
    assert meas.synthetic and "SYNTHETIC" in meas.description
    for fmt in ("csv", "parquet"):
        d = tmp_path / fmt
        tp = measured.write(meas, d, fmt)
        synth.seal(truth, d)
        back = measured.load(d)
        assert back.ids == meas.ids and np.allclose(back.y, meas.y) and np.allclose(back.se, meas.se)
        assert back.difference[0].shape == meas.difference[0].shape and back.synthetic
        assert any(p.name.startswith("synthetic_") for p in d.iterdir())
        assert synth.unseal(d)["effects"][0]["name"] == "skin"
        assert "skin" not in tp.read_text() if fmt == "csv" else True          # the label is not in the table
    d = tmp_path / "csv"
    df = pd.read_csv(d / "measured.csv")

    def bad(frame, word, sidecar=None):
        b = tmp_path / f"bad{abs(hash(word)) % 10000}"
        b.mkdir(exist_ok=True)
        frame.to_csv(b / "measured.csv", index=False)
        if sidecar is not None:
            (b / "measured.json").write_text(sidecar)
        with pytest.raises(UserError) as err:
            measured.load(b)
        assert word in str(err.value) and "\n" not in str(err.value)

    bad(df.drop(columns=["E"]), "missing column")
    bad(pd.concat([df, df.iloc[:1]]), "duplicate id")
    bad(df.assign(d=-1.0), "positive")
    bad(df.drop(columns=["O1"]), "O1,O2,O3")
    bad(df.assign(difference="nothere.npy"), "does not exist")
    bad(df.iloc[:3], "at least 4")
    bad(df, "not valid JSON", sidecar="{")
    bad(df, "not an elastimap", sidecar=json.dumps({"kind": "other"}))
    with pytest.raises(UserError, match="no such"):
        measured.load(tmp_path / "nowhere")


def test_simulator_cache_reuses_solves(tmp_path, dhe):
    from elastimap.gap.simulate import base_params
    ps = [base_params("tiny", *r) for r in dhe[:3]]
    a = Simulator(tmp_path, "tiny", "toy")
    ra = a.run(ps)
    assert a.stats["solved"] == 3
    b = Simulator(tmp_path, "tiny", "toy")
    rb = b.run(ps + ps[:1])
    assert b.stats["solved"] == 0 and b.stats["hits"] == 4
    assert np.array_equal(ra[0].image, rb[0].image) and rb[3].key == ra[0].key
    # the cache is a solve store: the same rows read through SolveStore, labelled SYNTHETIC,
    # and they never answer for the FEM
    from elastimap.dataset.store import SolveStore
    got = SolveStore(tmp_path, solver="synthetic").get(ps[1], need_raw=True)
    assert got is not None and np.array_equal(got.image, ra[1].image) and np.array_equal(got.image_raw, ra[1].image_raw)
    assert SolveStore(tmp_path).get(ps[1]) is None


# ---------------------------------------------------------------- diagnosis (TOY backend)
def test_diagnosis_identifies_fits_and_shrinks(toy, dhe, tmp_path):
    meas, _ = synth.synthesize(dhe, [(fx.get("friction"), 0.6)], toy, frames=6, seed=2)
    res = diagnose(meas, fx.parse_list(None), toy, Settings(inverse=True, n_train=30, train_repeats=2,
                                                            train_epochs=150, bootstrap=50))
    ev = res["evaluation"]
    assert ev["outcome"] == "explained" and ev["winner"] == "friction"
    top = ev["ranking"][0]
    assert top["magnitude"] == pytest.approx(0.6, rel=0.1)
    assert top["magnitude_ci"][0] <= top["magnitude"] <= top["magnitude_ci"][1]
    assert res["shrink_features"]["shrink"] > 0.7
    si = res["shrink_inverse"]
    assert si["mean_error_after"] < si["mean_error_before"]
    from elastimap.gap import report
    doc = report.write(res, tmp_path / "rep")
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "SYNTHETIC" in md and "Winner: `friction`" in md and "Runner-up" in md
    for f in doc["figures"]:
        assert (tmp_path / "rep" / f).stat().st_size > 1000
    js = json.loads((tmp_path / "rep" / "diagnosis.json").read_text())
    assert js["summary"]["winner"] == "friction"


def test_no_gap_and_unexplained_outcomes(toy, dhe):
    st = Settings(inverse=False, bootstrap=20)
    clean, _ = synth.synthesize(dhe, [], toy, frames=6, seed=3)
    assert diagnose(clean, fx.parse_list("friction,skin"), toy, st)["evaluation"]["outcome"] == "no significant gap"
    meas, _ = synth.synthesize(dhe, [(fx.get("skin"), 40.0)], toy, frames=6, seed=4)
    ev = diagnose(meas, fx.parse_list("friction,saturation,vignetting"), toy, st)["evaluation"]
    assert ev["outcome"] == "unexplained" and ev["winner"] is None


def test_tiny_blind_selftest_toy(toy):
    from elastimap.gap import selftest
    res = selftest.run(4, toy, fx.parse_list(None), n_phantoms=10, frames=6, seed=5,
                       st=Settings(inverse=False, bootstrap=20), log=None)
    assert res["top1_accuracy"] >= 0.75
    assert res["feature_gap_shrink_median"] >= 0.7
    assert res["withheld_confident_wrong_rate"] <= 0.5
    assert sum(sum(r.values()) for r in res["confusion"].values()) == 4
    md = selftest.markdown(res)
    assert "SYNTHETIC" in md and "Confusion matrix" in md


# ---------------------------------------------------------------- real FEM solves (tiny mesh)
def test_fem_backend_small_diagnosis(tmp_path):
    """4 phantoms, a 2-point friction sweep and an optics candidate, real tiny-mesh solves."""
    sim = Simulator(tmp_path / "cache", "tiny", "fem")
    fr = dataclasses.replace(fx.get("friction"), grid=(0.0, 0.3))
    dhe = np.array([[8.0, 8.0, 80.0], [6.0, 7.0, 50.0], [10.0, 10.0, 120.0], [7.0, 11.0, 60.0]])
    meas, _ = synth.synthesize(dhe, [(fr, 0.3)], sim, frames=4, seed=0)
    n_true = sim.stats["solved"]
    res = diagnose(meas, [fr, fx.get("saturation")], sim, Settings(inverse=False, bootstrap=20))
    ev = res["evaluation"]
    assert ev["winner"] == "friction" and ev["ranking"][0]["magnitude"] == pytest.approx(0.3, rel=0.05)
    assert sim.stats["solved"] == n_true + 4            # only the baseline was new: friction=0.3 came from the cache


# ---------------------------------------------------------------- CLI
def test_cli_end_to_end_and_errors(tmp_path):
    py = [sys.executable, "-m", "elastimap.gap.cli"]
    m = tmp_path / "m"
    r = subprocess.run(py + ["synth", "--out", str(m), "--effect", "saturation=0.2", "--backend", "toy",
                             "--mesh", "tiny", "--n", "8", "--cache", "none", "--quiet"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert "SYNTHETIC" in r.stdout
    out = tmp_path / "d"
    r = subprocess.run(py + ["diagnose", "--measured", str(m), "--out", str(out), "--backend", "toy", "--cache", "none",
                             "--no-inverse", "--quiet", "--json"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["winner"] == "saturation"
    assert (out / "report.md").exists() and (out / "candidates.png").exists()
    for args, word in ((["diagnose", "--measured", str(tmp_path / "none"), "--out", str(out)], "no such"),
                       (["synth", "--out", str(m), "--effect", "bogus=1"], "unknown effect"),
                       (["diagnose", "--measured", str(m), "--out", str(out), "--effects", "x"], "unknown effect")):
        r = subprocess.run(py + args, capture_output=True, text=True, cwd=ROOT)
        assert r.returncode == 2 and word in r.stderr and r.stderr.count("\n") == 1, r.stderr
