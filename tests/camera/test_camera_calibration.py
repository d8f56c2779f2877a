"""FEM <-> camera calibration (paper 3.3): phantom spec, line fits, JSON, plot, CLI."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from elastimap.camera import calibration as C
from elastimap.camera.features import FeatureSettings
from elastimap.camera.optics import SensorModel
from elastimap.dataset.phantoms import read_phantoms
from elastimap.dataset.schema import PHANTOMS_CSV
from elastimap.errors import UserError
from elastimap.solver.synthetic import solve_dhe as toy_solve  # SYNTHETIC stand-in, not physics

# its module fixture is costly: under pytest-xdist (make test) this module runs on one worker
pytestmark = pytest.mark.xdist_group("test_camera_calibration")

REPO = Path(__file__).resolve().parents[2]
PHANTOMS_FALLBACK = """# temporary copy for tests
name,phantom,d,h,E,tissue_E,tissue_thickness
size-1,size,5.0,8.0,80.0,5.0,20.0
size-2,size,8.0,8.0,80.0,5.0,20.0
size-3,size,12.0,8.0,80.0,5.0,20.0
depth-1,depth,8.0,6.0,80.0,5.0,20.0
depth-2,depth,8.0,9.0,80.0,5.0,20.0
depth-3,depth,8.0,12.0,80.0,5.0,20.0
hardness-1,hardness,8.0,8.0,30.0,5.0,20.0
hardness-2,hardness,8.0,8.0,60.0,5.0,20.0
hardness-3,hardness,8.0,8.0,120.0,5.0,20.0
"""


@pytest.fixture(scope="module")
def phantoms_csv(tmp_path_factory):
    if PHANTOMS_CSV.exists():
        return PHANTOMS_CSV
    p = tmp_path_factory.mktemp("ph") / "phantoms.csv"
    p.write_text(PHANTOMS_FALLBACK)
    return p


def toy_fem(d, h, E, tissue_E=5.0, thickness=20.0):
    return toy_solve(d, h, E, tissue_E=tissue_E)


def test_phantom_spec(phantoms_csv):
    ph = read_phantoms(phantoms_csv, min_rows=3, why="to fit a calibration line")
    assert len(ph) == 9 and ph["name"].is_unique
    assert set(ph["phantom"]) == {"size", "depth", "hardness"}
    assert (ph["tissue_E"] == 5.0).all() and (ph["tissue_thickness"] == 20.0).all()


def test_phantom_spec_errors(tmp_path):
    with pytest.raises(UserError, match="no such file"):
        read_phantoms(tmp_path / "nope.csv", min_rows=3, why="to fit a calibration line")
    bad = tmp_path / "bad.csv"
    bad.write_text("name,d,h\na,1,2\nb,1,2\nc,1,2\n")
    with pytest.raises(UserError, match="missing column"):
        read_phantoms(bad, min_rows=3, why="to fit a calibration line")
    neg = tmp_path / "neg.csv"
    neg.write_text("name,d,h,E\na,1,2,3\nb,-1,2,3\nc,1,2,x\n")
    with pytest.raises(UserError, match="positive"):
        read_phantoms(neg, min_rows=3, why="to fit a calibration line")


def test_fit_line_recovers_exact_line():
    x = np.array([1.0, 2.0, 4.0, 7.0])
    f = C.fit_line(x, 3.0 * x - 0.5)
    assert f.slope == pytest.approx(3.0) and f.intercept == pytest.approx(-0.5)
    assert f.r2 == pytest.approx(1.0) and max(map(abs, f.residuals)) < 1e-12
    with pytest.raises(UserError, match="identical"):
        C.fit_line(np.ones(3), np.arange(3.0))


def test_synthetic_calibration_roundtrip_and_plot(tmp_path, phantoms_csv):
    ph = read_phantoms(phantoms_csv, min_rows=3, why="to fit a calibration line")
    m = SensorModel(seed=1)
    fem, cam, _ = C.simulate_phantoms(ph, toy_fem, m, FeatureSettings(), frames=5, seed=1)
    cal = C.fit_calibration(ph, fem, cam, FeatureSettings().to_dict(), m.to_dict(), True)
    for k in ("O1", "O2"):
        assert cal.fits[k].r2 > 0.98, cal.report()
    # the map sends camera features onto the FEM ones
    err = np.abs(cal.apply(cam) - fem)
    assert np.all(err < 0.05 * np.ptp(fem, axis=0)), err
    p = tmp_path / "cal.json"
    cal.save(p)
    back = C.Calibration.load(p)
    np.testing.assert_allclose(back.cam, cal.cam)
    np.testing.assert_allclose(back.slopes, cal.slopes)
    assert back.synthetic and back.sensor == m.to_dict() and back.names == list(ph["name"])
    d = json.loads(p.read_text())
    assert d["synthetic"] is True and set(d["fits"]) == {"O1", "O2", "O3"}
    assert {"slope", "intercept", "r2", "residuals"} <= set(d["fits"]["O1"])
    png = tmp_path / "cal.png"
    C.plot_calibration(cal, png)
    assert png.stat().st_size > 10_000
    assert cal.outside(cam).sum() == 0 and cal.outside(cam * 10).any()
    assert "R^2" in cal.report()


def test_calibration_from_user_images_matches_synthetic(tmp_path, phantoms_csv):
    """Write the phantom frames as files, list them in a camera CSV, and get the same camera features."""
    ph = read_phantoms(phantoms_csv, min_rows=3, why="to fit a calibration line")
    m = SensorModel(seed=2)
    frames_dir = tmp_path / "frames"
    fem, cam, _ = C.simulate_phantoms(
        ph, toy_fem, m, FeatureSettings(), frames=2, seed=2, write_dir=frames_dir, fmt="tiff"
    )
    rows = ["name,images,background"]
    for n in ph["name"]:
        rows.append(f"{n},frames/synthetic_{n}_f*.tif,frames/synthetic_{n}_background_f*.tif")
    csv = tmp_path / "camera.csv"
    csv.write_text("\n".join(rows) + "\n")
    cam2 = C.camera_features_from_csv(csv, ph, m, FeatureSettings())
    np.testing.assert_allclose(cam2, cam, rtol=1e-12)
    csv.write_text("name,images,background\nsize-1,x.png,y.png\n")
    with pytest.raises(UserError, match="x.png: no such file"):
        C.camera_features_from_csv(csv, ph, m)


def test_fem_features_from_csv(tmp_path, phantoms_csv):
    ph = read_phantoms(phantoms_csv, min_rows=3, why="to fit a calibration line")
    p = tmp_path / "fem.csv"
    p.write_text("name,O1,O2,O3\n" + "".join(f"{n},{i},{2 * i},{3 * i}\n" for i, n in enumerate(ph["name"])))
    f = C.fem_features_from_csv(p, ph)
    assert f.shape == (9, 3) and f[4, 2] == 12
    p.write_text("name,O1,O2,O3\nsize-1,1,2,3\n")
    with pytest.raises(UserError, match="size-2"):
        C.fem_features_from_csv(p, ph)


def test_cli_errors_are_one_line(tmp_path):
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "elastimap.camera.cli",
            "calibrate",
            "--phantoms",
            str(tmp_path / "no.csv"),
            "--out",
            str(tmp_path / "c.json"),
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().startswith("error: --phantoms:") and len(r.stderr.strip().splitlines()) == 1
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "elastimap.camera.cli",
            "calibrate",
            "--bits",
            "8",
            "--noise-scale",
            "-1",
            "--out",
            str(tmp_path / "c.json"),
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert r.returncode == 2 and r.stderr.startswith("error: --noise-scale:"), r.stderr  # the library's noise_scale


def test_cli_calibrate_with_fem_tiny(tmp_path):
    """The real chain: nine tiny-mesh FEM solves + synthetic frames -> JSON + PNG (about 10 s)."""
    pytest.importorskip("elastimap.solver.api", reason="the DOLFINx solver is not available")
    out = tmp_path / "cal.json"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "elastimap.camera.cli",
            "calibrate",
            "--mesh",
            "tiny",
            "--frames",
            "3",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    cal = C.Calibration.load(out)
    assert (tmp_path / "cal.png").exists()
    assert all(cal.fits[k].r2 > 0.95 for k in ("O1", "O2", "O3")), r.stdout
    assert cal.meta["mesh"] == "tiny"
    # the deflection calibration (camera frames -> FEM difference images) comes with it
    assert cal.deflection["shape"] == [50, 50] and 0.9 < cal.deflection["scale"] < 1.1, cal.deflection["scale"]
    assert max(cal.deflection["rel_rms"]) < 0.25, cal.deflection["rel_rms"]  # 3 frames: noise-dominated
