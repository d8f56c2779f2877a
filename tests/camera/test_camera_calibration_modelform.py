"""``camera calibrate`` from a lab's own frames produces what ``infer --refine`` needs in every form it
accepts: the deflection calibration also when the FEM features come from a sweep (``--fem-features``),
and the model-form error learnt from the phantoms with its leave-one-phantom-out check
(``--report-loo``).  SYNTHETIC frames, tiny mesh."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from elastimap.camera import calibration as C
from elastimap.dataset.schema import FEATURES

pytestmark = pytest.mark.xdist_group("camera_calibration_modelform")
REPO = Path(__file__).resolve().parents[2]


def _calibrate(*args, timeout=600):
    return subprocess.run(
        [sys.executable, "-m", "elastimap.camera.cli", "calibrate", "--mesh", "tiny", *args],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=timeout,
    )


def test_frames_with_sweep_features_calibrate_refine_and_the_model_form_error(tmp_path):
    """Frames of the nine phantoms (written by a SYNTHETIC calibration) and their FEM features from a
    CSV (as a sweep gives them): the calibration carries the deflection calibration (it was refused by
    --refine with "no deflection calibration" before) and the model-form error learnt for the tiny fit,
    and --report-loo fits each phantom with the term learnt from the other eight."""
    pytest.importorskip("elastimap.solver.morph", reason="the morphed forward map is not available")
    frames = tmp_path / "frames"
    first = tmp_path / "first.json"
    r = _calibrate("--frames", "3", "--write-frames", str(frames), "--refine-level", "none", "--out", str(first))
    assert r.returncode == 0, r.stderr
    cal0 = C.Calibration.load(first)
    assert cal0.discrepancy is None  # --refine-level none: nothing learnt
    rows = ["name,images,background"]
    fem = ["name," + ",".join(FEATURES)]
    for i, n in enumerate(cal0.names):
        rows.append(f"{n},frames/synthetic_{n}_f*.png,frames/synthetic_{n}_background_f*.png")
        fem.append(f"{n}," + ",".join(f"{v:.9g}" for v in cal0.fem[i]))
    (tmp_path / "camera.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "fem.csv").write_text("\n".join(fem) + "\n")
    out = tmp_path / "lab.json"
    r = _calibrate(
        "--camera-csv",
        str(tmp_path / "camera.csv"),
        "--fem-features",
        str(tmp_path / "fem.csv"),
        "--report-loo",
        "--out",
        str(out),
    )
    assert r.returncode == 0, r.stderr
    cal = C.Calibration.load(out)
    assert cal.deflection is not None and cal.deflection["shape"] == [50, 50]
    ref, pixel = cal.reference_image()  # what --refine reads: no "no deflection calibration" refusal
    assert ref.shape == (50, 50) and pixel == 0.5
    disc, level, px = cal.model_form()
    assert level == "tiny" and px == 0.5 and disc.n_phantoms == 9
    # the morphed map's exact derivative gives the depth mode (h dm/dh), carried by --refine as a shift of h
    assert disc.modes == ("amplitude", "width", "depth") and disc.depth_shift() is not None
    assert all(len(r["z"]) == 3 for r in cal.discrepancy["loo"]) and "depth mean" in r.stdout
    assert len(cal.discrepancy["loo"]) == 9
    fits = cal.discrepancy["fits"]
    assert fits["n"] == 9 and len(fits["rows"]) == 9 and all(0 <= c <= 9 for c in fits["covered"])
    assert "leave-one-phantom-out fits" in r.stdout and "model-form error (level tiny" in r.stdout


def test_refine_level_and_report_loo_are_checked_before_any_work(tmp_path):
    r = _calibrate("--refine-level", "huge", "--out", str(tmp_path / "c.json"), timeout=60)
    assert r.returncode == 2 and r.stderr.startswith("error: --refine-level: must be auto, none or one of"), r.stderr
    r = _calibrate("--refine-level", "none", "--report-loo", "--out", str(tmp_path / "c.json"), timeout=60)
    assert r.returncode == 2 and r.stderr.startswith("error: --report-loo:"), r.stderr
    assert not (tmp_path / "c.json").exists()
