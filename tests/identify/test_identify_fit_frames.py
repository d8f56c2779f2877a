"""The maximum-likelihood fit on the smooth (morphed) forward map, from camera frames.

Everything here is SYNTHETIC and on the tiny mesh.  The lesion data never come from the fit's own
forward map: they are made by the remeshing solver (a gmsh mesh of that lesion) at another mesh
level (coarse) or, for the CLI test, on the tiny level's remeshed mesh, while the fit uses the
morphed map on the tiny mesh and measures its own error against the coarse level.  The tiny mesh is
far from converged (its E along the larger-softer valley moves by tens of per cent between
reference meshes), so these tests check that the interval is honest about it, not accuracy;
accuracy is measured by workflows/frames_benchmark.py (docs/camera.md).
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("elastimap.solver.morph", reason="the morphed forward map is not available")

TRUTH = np.array([9.0, 7.5, 45.0])  # d mm, h mm, E kPa: not a phantom, not a bin reference


def _world(d, h, E, mesh):
    """The lesion's data: the remeshing solver at ``mesh`` (not the fit's map)."""
    from elastimap.solver import solve
    from elastimap.solver.params import Discretisation, SolveParams

    return solve(SolveParams(disc=Discretisation(mesh=mesh)).with_inclusion(d=d, h=h, E=E))


def test_fit_holds_a_lesion_from_another_mesh_level_in_its_interval():
    """Data: coarse-mesh remeshing solve + 0.3 %-of-peak Gaussian noise (about what 30 frames give at
    the peak).  Fit: tiny morphed map, model error against the coarse morphed map, start 15 % off."""
    from elastimap.identify.fit import fit_forward

    w = _world(*TRUTH, "coarse")
    sig = 0.003 * w.image.max()
    img = w.image + sig * np.random.default_rng(5).standard_normal(w.image.shape)
    r = fit_forward(img, sig, TRUTH * [1.15, 0.9, 1.5], mesh="tiny")
    print(r)
    assert r.n_solves >= 7 and r.n_alt >= 1 and np.isfinite(r.relstd).all()
    assert np.all(r.lo <= TRUTH) and np.all(TRUTH <= r.hi), (r.theta, r.lo, r.hi)
    assert abs(r.theta[0] / TRUTH[0] - 1) < 0.1 and abs(r.theta[1] / TRUTH[1] - 1) < 0.1, r.theta
    assert r.chi2_red < r.chi2_red0


def test_defect_corrected_fit_stands_for_the_finer_level():
    """The same lesion (coarse-mesh remeshing solve, 0.3 % noise), fitted on the tiny morphed map
    defect-corrected by the coarse morphed map (``correct="coarse"``; model error then against
    tiny): the corrected map is the finer level at each pass's start, so the fit lands closer to the
    truth in d than the tiny map alone, and in E where it calls E identifiable (sd of ln E ≤ 0.1;
    on this lesion E lies along the flat d–E valley and the corrected fit says so: its interval
    spans most of the box), and its interval still holds the truth."""
    from elastimap.identify.fit import fit_forward

    w = _world(*TRUTH, "coarse")
    sig = 0.003 * w.image.max()
    img = w.image + sig * np.random.default_rng(5).standard_normal(w.image.shape)
    start = TRUTH * [1.15, 0.9, 1.5]
    plain = fit_forward(img, sig, start, mesh="tiny")
    r = fit_forward(img, sig, start, mesh="tiny", correct="coarse")
    print(plain, r)
    assert r.n_fine >= 1 and plain.n_fine == 0
    assert np.all(r.lo <= TRUTH) and np.all(TRUTH <= r.hi), (r.theta, r.lo, r.hi)
    err, err0 = np.abs(r.theta / TRUTH - 1), np.abs(plain.theta / TRUTH - 1)
    assert err[0] < err0[0], (r.theta, plain.theta)
    assert r.relstd[2] > 0.1 or err[2] < err0[2], (r.theta, r.relstd, plain.theta)


def test_fit_of_its_own_noise_free_map_returns_the_truth():
    """Self-consistency only (the data come from the same tiny morphed map, pinned at the truth;
    the fit pins at its start, so its reference press is linearised about another point): the fit
    is exact with the map's derivative and with central differences + Broyden, and the derivative
    needs fewer evaluations (measured 19 against 38)."""
    from elastimap.identify.fit import fit_image
    from elastimap.identify.forward_maps import forward_map

    f = forward_map("tiny", "morph").pin(TRUTH[0], TRUTH[1])
    img = f(*TRUTH).image
    n = {}
    for tangent in (True, False):
        r = fit_image(img, 1e-3 * img.max(), TRUTH * [1.05, 0.97, 1.25], f, tangent=tangent)
        np.testing.assert_allclose(r.theta, TRUTH, rtol=2e-3)
        n[tangent] = r.n_solves
    assert n[True] < n[False], n


@pytest.fixture(scope="module")
def frames_case(tmp_path_factory):
    """A calibration (three phantoms; frames from the remeshing solver, FEM side from the tiny
    morphed map), a small feature ensemble (LM, trained on the SYNTHETIC toy model: a rough start)
    and one lesion's 30 + 30 PNG frames."""
    import pandas as pd

    from elastimap.camera import calibration as C
    from elastimap.camera.features import FeatureSettings, camera_features
    from elastimap.camera.frames import write_frames
    from elastimap.camera.optics import SensorModel, render_pair
    from elastimap.identify.forward_maps import forward_map
    from elastimap.solver.synthetic import solve_dhe as toy_solve
    from elastimap.training.api import fit_ensemble

    tmp = tmp_path_factory.mktemp("frames")
    sensor = SensorModel(seed=21)
    fwd = forward_map("tiny", "morph")
    ph = pd.DataFrame(
        [("size-2", 8.0, 8.0, 80.0), ("depth-2", 8.0, 9.0, 80.0), ("hardness-1", 8.0, 8.0, 30.0)],
        columns=["name", "d", "h", "E"],
    )
    rng = np.random.default_rng(21)
    pairs, cam, res = [], [], []
    for _, p in ph.iterrows():
        w = _world(p["d"], p["h"], p["E"], "tiny")
        F, B = render_pair(sensor, w.image_raw, w.image, w.pixel, 10, rng)
        pairs.append((F, B))
        cam.append(camera_features(F, B, sensor.full_scale, sensor.window, sensor.pixel_mm, FeatureSettings()).values)
        res.append(fwd(p["d"], p["h"], p["E"]))
    fem = np.array([[r.O1, r.O2, r.O3] for r in res])
    defl = C.deflection_calibration(res, pairs, sensor)
    cal = C.fit_calibration(ph, fem, np.array(cam), FeatureSettings().to_dict(), sensor.to_dict(), True, None, defl)
    cal.save(tmp / "cal.json")
    rows = []
    for d in np.linspace(4, 12, 5):
        for h in np.linspace(5, 13, 5):
            if 1 + d / 2 <= h <= 18 - d / 2:
                for E in np.linspace(20, 150, 5):
                    t = toy_solve(d, h, E)
                    rows.append((d, h, E, t.O1, t.O2, t.O3))
    ens = fit_ensemble(pd.DataFrame(rows, columns=["d", "h", "E", "O1", "O2", "O3"]), "lm", 1, 40, (6,), 0)
    ens.save(str(tmp / "model"))
    w = _world(*TRUTH, "tiny")
    F, B = render_pair(sensor, w.image_raw, w.image, w.pixel, 30, rng)
    write_frames(F, tmp / "lesion", "lesion", "png")
    write_frames(B, tmp / "lesion", "lesion_background", "png")
    return tmp


def test_cli_refine_from_camera_frames(frames_case):
    """``infer --images ... --background ... --refine`` end to end: PNG frames -> difference image and
    its noise -> feature network -> the fit on the tiny morphed map (model error vs coarse).

    Measured (2026-11-24): d 10.14 [9.50, 10.78] mm, h 7.20 [7.12, 7.29] mm, E 19.3 [15.3, 24.5] kPa
    (flagged non_identifiable:E) for a true 9.0 / 7.5 / 45; the network alone gave d 9.20 with a
    flagged 4-12 mm interval.  The intervals MISS the truth: the calibration's reference press
    (three phantoms of the tiny morphed map) differs from the world's (remeshed) press, which
    distorts the recovered image, and that error is not in the fit's error model (docs/camera.md
    4c).  So this test checks the path and the size of the d and h errors, not coverage."""
    tmp = frames_case
    cmd = [
        sys.executable,
        "-m",
        "elastimap.camera.cli",
        "infer",
        "--model",
        str(tmp / "model"),
        "--calibration",
        str(tmp / "cal.json"),
        "--images",
        str(tmp / "lesion" / "synthetic_lesion_f*.png"),
        "--background",
        str(tmp / "lesion" / "synthetic_lesion_background_f*.png"),
        "--refine",
        "--mesh",
        "tiny",
        "--json",
    ]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    (e,) = json.loads(r.stdout)
    print(json.dumps(e, indent=1))
    assert e["input"] == "frames+fem_refined" and e["fit_solves"] >= 8
    assert np.isfinite(e["fit_chi2_red"]) and e["fit_model_error"] > 0
    assert isinstance(e["fit_converged"], bool)
    assert (e["fit_moving"] == "") == e["fit_converged"]  # which parameters still moved, when it did not settle
    assert "non_identifiable:E" in e["flags"]  # measured: sd(ln E) 0.12 > 0.10
    assert abs(e["d"] / TRUTH[0] - 1) < 0.15 and abs(e["h"] / TRUTH[1] - 1) < 0.1, e
