"""The camera-frame benchmark's own pieces (workflows/benchmarks/frames, run as workflows/frames_benchmark.py) on plain records: the
session camera that drifts from the calibration's, and the scoring where the estimator itself
reports a quantity.  The benchmark's figures are in docs/camera.md, 'Inference'."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from elastimap.camera.optics import SensorModel
from elastimap.workflows.benchmarks.frames import lesions as fl
from elastimap.workflows.benchmarks.frames import report as frep
from elastimap.workflows.benchmarks.frames import run as frun

#: the benchmark's script, as docs/camera.md runs it
SCRIPT = Path(__file__).resolve().parents[2] / "workflows" / "frames_benchmark.py"


def test_session_sensor_drifts_only_leds_and_vignetting():
    nominal = SensorModel(seed=3)
    cams = [fl.session_sensor(nominal, np.random.default_rng(k)) for k in range(20)]
    for cam in cams:
        ratio = np.array(cam.led_power) / np.array(nominal.led_power)
        assert np.all((0.8 <= ratio) & (ratio <= 1.2)) and 0.05 <= cam.vignetting <= 0.3
        assert cam.replace(led_power=nominal.led_power, vignetting=nominal.vignetting) == nominal
        cam.validate()
    assert len({c.led_power for c in cams}) == 20  # drawn afresh per session


def test_region_stratified_lesions_lie_where_the_map_allows_and_are_reproducible(monkeypatch):
    """``draw_lesions(inside="E")``: every lesion is one the shipped map's frames set calls E
    identifiable at (decided from the truth), the draw is a function of (n, seed) alone, and
    asking for more such lesions than the overdrawn design holds is a one-line error naming n."""
    from elastimap.errors import UserError

    a = fl.draw_lesions(12, seed=7, inside="E")
    assert a.shape == (12, 3) and fl.identifiable_at(a, "frames")[:, 2].all()
    assert not fl.identifiable_at(fl.draw_lesions(200, seed=7), "frames")[:, 2].all()  # the plain design is not
    np.testing.assert_array_equal(a, fl.draw_lesions(12, seed=7, inside="E"))
    assert not np.array_equal(a, fl.draw_lesions(12, seed=8, inside="E"))
    monkeypatch.setattr(fl, "INSIDE_OVERDRAW", 1)  # ~3 % of a design of n points holds fewer than n
    with pytest.raises(UserError) as exc:
        fl.draw_lesions(50, seed=7, inside="E")
    assert exc.value.param == "n"


def test_outside_draw_is_the_mirror_of_inside_and_refuses_both():
    """``draw_lesions(outside="d")``: every lesion is one the map does NOT call d identifiable at,
    reproducible; inside and outside together are a one-line error; the ``--outside`` flag reaches
    the lesion record's design (and whole-design records read as before)."""
    from elastimap.errors import UserError

    b = fl.draw_lesions(15, seed=7, outside="d")
    assert b.shape == (15, 3) and not fl.identifiable_at(b, "frames")[:, 0].any()
    assert fl.identifiable_at(fl.draw_lesions(200, seed=7), "frames")[:, 0].any()  # the plain design is not
    np.testing.assert_array_equal(b, fl.draw_lesions(15, seed=7, outside="d"))
    with pytest.raises(UserError) as exc:
        fl.draw_lesions(3, seed=7, inside="E", outside="d")
    assert exc.value.param == "outside"
    assert fl.design_record(3, 7, None, "d") == {"n": 3, "seed": 7, "inside": None, "outside": "d"}
    assert fl.design_record(3, 7, "E", None) == {"n": 3, "seed": 7, "inside": "E"}
    assert "does not call d" in fl.drawn_note({"outside": "d"}) and fl.drawn_note(None) == ""


def _rec(truth, est, lo, hi, reportable, flags=""):
    part = {"flags": flags, "fit_chi2_red": 1.0}
    for j, q in enumerate("dhE"):
        part.update({q: est[j], f"{q}_lo": lo[j], f"{q}_hi": hi[j], f"{q}_reportable": reportable[j]})
    return {
        "truth": list(truth),
        "network": dict(part),
        "fit": dict(part),
        "seconds_fit": 1.0,
        "cpu_seconds_fit": 1.0,
        "seconds_camera_and_network": 0.1,
        **{f"{k}_level_solves": 0.0 for k in ("seconds_fit", "seconds_alt", "n_fit", "n_alt")},
    }


def test_summary_scores_where_the_estimator_reports():
    """MRE and coverage over the records whose estimate says 'reportable', whatever the map says at
    the truth; none reported gives None, not 0."""
    truth = (8.0, 7.0, 50.0)
    recs = [
        _rec(truth, (8.8, 7.0, 55.0), (7.0, 6.0, 40.0), (9.0, 8.0, 60.0), (True, True, True)),  # d +10 %, E +10 %
        _rec(truth, (8.0, 7.7, 100.0), (7.5, 7.5, 20.0), (8.5, 8.0, 200.0), (True, True, False)),  # E not reported
    ]
    sm = frep.summarise(recs)
    fit = sm["fit"]
    assert fit["E"]["n_reported"] == 1 and fit["E"]["mre_reported"] == pytest.approx(0.10)
    assert fit["d"]["n_reported"] == 2 and fit["d"]["mre_reported"] == pytest.approx(0.05)
    assert fit["h"]["coverage_reported"] == pytest.approx(0.5)  # 7.0 outside [7.5, 8.0]
    recs[0]["fit"]["E_reportable"] = False
    assert frep.summarise(recs)["fit"]["E"]["mre_reported"] is None
    assert "reports the quantity as a number" in frep.table(sm)
    recs[1]["fit_message"] = "ftol; still moving after 2 passes"
    sm = frep.summarise(recs)
    assert sm["not_converged"] == 1 and sm["fit"]["d"]["n_reported_converged"] == 1
    assert sm["fit"]["d"]["mre_reported_converged"] == pytest.approx(0.10)  # lesion 0 alone
    assert "fit_gauss_coverage" not in sm  # older records carry no Gauss–Newton interval
    recs[0]["fit_interval_gauss"] = {"lo": [8.9, 6.0, 40.0], "hi": [9.5, 8.0, 60.0]}  # misses d = 8
    recs[1]["fit_interval_gauss"] = None  # no fit ran (no signal): its reported interval stands for both
    g = frep.summarise(recs)["fit_gauss_coverage"]
    inside = fl.identifiable_at(np.array([truth, truth]))[0]
    assert g["d"]["inside" if inside[0] else "outside"] == pytest.approx(0.5)
    assert g["h"]["inside" if inside[1] else "outside"] == pytest.approx(0.5)  # 7.0 outside [7.5, 8.0] again
    assert "Gauss–Newton interval" in frep.table(frep.summarise(recs))


def test_the_fits_cost_is_averaged_over_the_lesions_a_fit_ran_for():
    """A lesion without a signal (no fit, 0 solves) does not lower the fit's mean CPU time."""
    truth = (8.0, 7.0, 50.0)
    recs = [_rec(truth, truth, truth, truth, (True, True, True)) for _ in range(3)]
    for r, cpu, n in zip(recs, (20.0, 40.0, 0.0), (30, 30, 0)):
        r["cpu_seconds_fit"], r["n_fit_level_solves"] = cpu, n
    sm = frep.summarise(recs)
    assert sm["cpu_seconds_fit"]["mean"] == pytest.approx(30.0) and sm["cpu_seconds_fit"]["n"] == 2
    assert sm["n_fit_level_solves"] == pytest.approx(30.0)
    assert sm["seconds_fit_level_solves"] == pytest.approx(0.0)  # the records carry no split here


@pytest.mark.parametrize(
    ("args", "says", "existing"),
    [
        (["--sweep", "{tmp}/none"], "--sweep: no such file or directory", False),
        (["--sweep", "{tmp}", "--repeats", "0"], "--repeats: must be >= 1", False),
        (["--sweep", "{tmp}"], "image-model exists", True),  # never overwrites a network
    ],
)
def test_network_stage_answers_bad_input_in_one_line(tmp_path, args, says, existing):
    import subprocess
    import sys

    if existing:
        (tmp_path / "image-model").mkdir()
    script = SCRIPT
    cmd = [sys.executable, str(script), "network", *[a.format(tmp=tmp_path) for a in args], "--out", str(tmp_path)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and says in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--fit-mesh", "huge"], "--fit-mesh: must be one of tiny, coarse"),
        (["--correct-mesh", "tiny"], "--correct-mesh: must be a mesh level finer than coarse"),
    ],
)
def test_run_stage_names_a_bad_level_before_any_work(tmp_path, args, says):
    """The levels are checked by the library's check_correct, its errors named by this command's flags,
    before anything is written."""
    import subprocess
    import sys

    out = tmp_path / "bench"
    cmd = [sys.executable, str(SCRIPT), "run", "--model", "m", "--out", str(out), *args]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and says in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not out.exists()


def test_report_refuses_to_mix_lesion_designs(tmp_path):
    """A fits folder holding lesions of the whole-design draw and of a region-stratified one
    (``--inside``) is one line naming --out, not a table over both."""
    import json
    import subprocess
    import sys

    fits = tmp_path / "fits-x"
    fits.mkdir()
    for i, inside in enumerate((None, "E")):
        rec = _rec([8, 7, 50], [8, 7, 50], [7, 6, 40], [9, 8, 60], [True] * 3)
        rec.update(design={"n": 2, "seed": 1, "inside": inside}, frames=30, world="w", fit_map="f")
        (fits / f"lesion-{i:04d}.json").write_text(json.dumps(rec))
    cmd = [sys.executable, str(SCRIPT), "report", "--out", str(tmp_path)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--out" in r.stderr and "mixes lesion designs" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "benchmark.md").exists()


def test_run_stage_refuses_a_folder_of_another_design_before_any_work(tmp_path):
    """``run`` skips lesions it finds; a fits folder holding a lesion of another design (here another
    --seed) would be silently mixed into the new one, so it is one line naming --out, and nothing is
    added (no calibration written)."""
    import json
    import subprocess
    import sys

    fits = tmp_path / "fits-morph-coarse"
    fits.mkdir()
    other = fl.draw_lesions(3, seed=11)
    (fits / "lesion-0000.json").write_text(json.dumps({"i": 0, "truth": list(map(float, other[0]))}))
    cmd = [sys.executable, str(SCRIPT), "run", "--model", "m", "--n", "3", "--seed", "12"]
    cmd += ["--geometry", "morph", "--out", str(tmp_path)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--out" in r.stderr and "another design" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fits-morph-coarse"]


def test_a_kept_calibration_of_another_camera_or_world_is_refused(tmp_path, monkeypatch):
    """The calibration is kept per forward map in OUT; one made with another camera seed or another
    world is a one-line error naming --out, not silently reused; this run's own is returned."""
    from types import SimpleNamespace

    from elastimap.camera import calibration as C
    from elastimap.errors import UserError

    (tmp_path / "cal-x.json").write_text("{}")
    world = fl.world_label("fine", "by_d")

    def kept(seed, w):
        return SimpleNamespace(sensor=SensorModel(seed=seed).to_dict(), meta={"world": w})

    for seed, w, ok in ((5, world, True), (6, world, False), (5, fl.world_label("default", "fixed"), False)):
        monkeypatch.setattr(C.Calibration, "load", staticmethod(lambda path, s=seed, w=w: kept(s, w)))
        if ok:
            assert frun.calibrate(str(tmp_path), "fine", None, 30, 5, "x", "by_d").meta["world"] == world
        else:
            with pytest.raises(UserError) as exc:
                frun.calibrate(str(tmp_path), "fine", None, 30, 5, "x", "by_d")
            assert exc.value.param == "--out"


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--lesions", "120"], "--lesions: comma-separated indices in 0..119"),
        (["--lesions", "a,b"], "--lesions: comma-separated indices"),
        (["--lesions", "2"], "cal-morph-coarse-corr-fine.json not found"),
        (["--lesions", "2", "--maps", "coarse"], "--maps"),
    ],
)
def test_valley_study_answers_bad_input_in_one_line(tmp_path, args, says):
    """The re-fit study (docs/camera.md 4i) checks its lesions and the benchmark folder before any solve."""
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "elastimap.workflows.studies.valleyfit", "--out", str(tmp_path), "--n", "120"]
    r = subprocess.run([*cmd, "--seed", "2029", *args], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and says in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_valley_study_refuses_lesions_of_another_design(tmp_path):
    """A --seed (or --n) that draws other lesions than the folder's records is refused before any solve,
    so a re-fit never pairs one lesion's truth with another's world solve and camera."""
    import json
    import subprocess
    import sys

    (tmp_path / "cal-morph-coarse-corr-fine.json").write_text("{}")
    fits = tmp_path / "fits-morph-coarse-corr-fine-drift"
    fits.mkdir()
    other = fl.draw_lesions(120, 2030)[2]
    (fits / "lesion-0002.json").write_text(json.dumps({"truth": [float(v) for v in other]}))
    cmd = [sys.executable, "-m", "elastimap.workflows.studies.valleyfit", "--out", str(tmp_path), "--n", "120"]
    r = subprocess.run([*cmd, "--seed", "2029", "--lesions", "2"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--seed: lesion 2 of" in r.stderr and "Traceback" not in r.stderr, r.stderr
    r = subprocess.run([*cmd, "--seed", "2029", "--lesions", "3"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--lesions: lesion 3 has no record" in r.stderr, r.stderr
