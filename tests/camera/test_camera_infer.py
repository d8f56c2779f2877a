"""Inference: API, flags, batch CSV, CLI, and end-to-end from synthetic frames."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from elastimap.camera import calibration as C
from elastimap.camera.features import FeatureSettings
from elastimap.camera.frames import write_frames
from elastimap.camera.infer import estimate, estimate_images, read_lesions_csv
from elastimap.camera.optics import SensorModel, render_pair
from elastimap.errors import UserError
from elastimap.solver.synthetic import solve_dhe as toy_solve  # SYNTHETIC stand-in, not physics

# its module fixture is costly: under pytest-xdist (make test) this module runs on one worker
pytestmark = pytest.mark.xdist_group("test_camera_infer")

REPO = Path(__file__).resolve().parents[2]
PHANTOMS = [
    ("size-1", 5, 8, 80),
    ("size-2", 8, 8, 80),
    ("size-3", 12, 8, 80),
    ("depth-1", 8, 6, 80),
    ("depth-2", 8, 9, 80),
    ("depth-3", 8, 12, 80),
    ("hardness-1", 8, 8, 30),
    ("hardness-2", 8, 8, 60),
    ("hardness-3", 8, 8, 120),
]
TRUTH = (7.0, 9.5, 70.0)  # the test lesion: not on the training grid, not a phantom


def toy_fem(d, h, E, tissue_E=5.0, thickness=20.0):
    return toy_solve(d, h, E, tissue_E=tissue_E)


def toy_table():
    rows = []
    for d in np.linspace(4, 12, 7):
        for h in np.linspace(5, 13, 7):
            if not (1 + d / 2 <= h <= 18 - d / 2):
                continue
            for E in np.linspace(20, 150, 7):
                r = toy_solve(d, h, E)
                rows.append((d, h, E, r.O1, r.O2, r.O3))
    return np.array(rows)


class OracleEnsemble:
    """Stand-in for elastimap.training.model.Ensemble: least-squares inversion of the TOY forward model.

    Members start from the 3 nearest table rows (log-feature distance), so their spread reflects
    how well the features pin (d, h, E) down.  It isolates the camera chain's own error.
    """

    input_kind = "features"  # an elastimap.training.model.InverseModel
    target_range = None  # intervals are not clipped to a training range

    def __init__(self, table, members=3):
        self.table = table
        self.members = members
        self.feature_range = np.vstack([table[:, 3:].min(axis=0), table[:, 3:].max(axis=0)])

    def outside_training(self, X):
        X = np.atleast_2d(np.asarray(X, dtype=float))
        out = (X < self.feature_range[0]) | (X > self.feature_range[1])
        return [[k for j, k in enumerate(("O1", "O2", "O3")) if row[j]] for row in out]

    def _one(self, f, x0):
        from scipy.optimize import least_squares

        lf = np.log(np.clip(f, 1e-9, None))

        def res(x):
            r = toy_solve(*x)
            return np.log(np.clip([r.O1, r.O2, r.O3], 1e-9, None)) - lf

        return least_squares(res, x0, bounds=([2, 2, 10], [16, 17, 300]), x_scale=[1, 1, 10], diff_step=1e-3).x

    def predict(self, X):
        X = np.atleast_2d(np.asarray(X, dtype=float))
        lt = np.log(self.table[:, 3:])
        out = np.empty((self.members, len(X), 3))
        for i, f in enumerate(X):
            near = np.argsort(np.sum((lt - np.log(np.clip(f, 1e-9, None))) ** 2, axis=1))[: self.members]
            for m, j in enumerate(near):
                out[m, i] = self._one(f, self.table[j, :3])
        return out


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    import pandas as pd

    ph = pd.DataFrame(PHANTOMS, columns=["name", "d", "h", "E"]).astype({"d": float, "h": float, "E": float})
    m = SensorModel(seed=11)
    s = FeatureSettings()
    pairs = []
    fem, cam, res = C.simulate_phantoms(ph, toy_fem, m, s, frames=10, seed=11, frames_out=pairs)
    cal = C.fit_calibration(
        ph, fem, cam, s.to_dict(), m.to_dict(), True, deflection=C.deflection_calibration(res, pairs, m)
    )
    d = tmp_path_factory.mktemp("chain")
    cal.save(d / "cal.json")
    return {"cal": cal, "ens": OracleEnsemble(toy_table()), "dir": d, "sensor": m}


def test_estimate_shapes_flags_and_uncertainty(chain):
    cal, ens = chain["cal"], chain["ens"]
    mid = cal.cam.mean(axis=0)
    far = cal.cam.max(axis=0) * 3
    # range flags only: the shipped identifiability map describes the FEM, not the TOY model
    est = estimate(np.vstack([mid, far, [-0.01, -1, 0]]), cal, ens, ids=["a", "b", "c"], identifiability=None)
    assert [e.id for e in est] == ["a", "b", "c"]
    assert est[0].ok and est[0].n_members == 3 and np.all(est[0].sd >= 0)
    assert "outside_calibration:O1" in est[1].flags and not est[1].ok
    assert any(f.startswith("outside_training") for f in est[1].flags)
    assert est[2].flags[0] == "no_signal"
    np.testing.assert_array_equal(np.c_[est[2].lo, est[2].hi], np.c_[[2.0, 2.0, 10.0], [15.0, 17.0, 200.0]])
    row = est[0].to_dict()
    assert {"d", "d_sd", "h", "E_sd", "cam_O1", "fem_O3", "flags", "ok"} <= set(row)
    with pytest.raises(UserError, match="three camera features"):
        estimate([[1.0, 2.0]], cal, ens)


def test_end_to_end_synthetic_frames(chain, tmp_path):
    """30 SYNTHETIC frames of a lesion not in the training table -> (d, h, E) within tolerance.

    Toy forward model (fast), the real camera chain: sensor model -> PNG files -> camera features
    -> calibration -> inverse ensemble.  Tolerance: 10 % on d, 15 % on h, 35 % on E (the toy's E is
    weakly determined: 1 % in O3 moves E by ~8 %, and the linear calibration leaves 1-3 % feature error).
    """
    m = chain["sensor"].replace(seed=99)
    r = toy_solve(*TRUTH)
    F, B = render_pair(m, r.image_raw, r.image, r.pixel, 30)
    pf = write_frames(F, tmp_path, "lesion", "png")
    pb = write_frames(B, tmp_path, "lesion_background", "png")
    est = estimate_images(pf, pb, chain["cal"], chain["ens"], id="lesion", identifiability=None)  # TOY: no FEM map
    assert est.ok, est.flags
    d, h, E = TRUTH
    assert est.d == pytest.approx(d, rel=0.10), est.to_dict()
    assert est.h == pytest.approx(h, rel=0.15), est.to_dict()
    assert est.E == pytest.approx(E, rel=0.35), est.to_dict()


def test_batch_csv(chain, tmp_path):
    cal = chain["cal"]
    p = tmp_path / "lesions.csv"
    c = cal.cam
    p.write_text("id,O1,O2,O3\n" + "".join(f"L{i},{c[i, 0]},{c[i, 1]},{c[i, 2]}\n" for i in range(3)))
    ids, cam = read_lesions_csv(p, cal)
    assert ids == ["L0", "L1", "L2"] and np.allclose(cam, c[:3])
    p.write_text("id,foo\n1,2\n")
    with pytest.raises(UserError, match="O1,O2,O3 or images,background"):
        read_lesions_csv(p, cal)


def _fake_training_ensemble(directory, table):
    """A real elastimap.training.model.Ensemble on disk (random weights, toy scaling) for CLI plumbing tests."""
    model = pytest.importorskip("elastimap.training.model", reason="elastimap.training.model not available")
    from elastimap.training.net import Arch

    arch = Arch()
    rng = np.random.default_rng(0)
    ens = model.Ensemble(
        arch=arch,
        theta=0.1 * rng.normal(size=(3, arch.n_params)),
        x_min=table[:, 3:].min(axis=0),
        x_max=table[:, 3:].max(axis=0),
        y_min=table[:, :3].min(axis=0),
        y_max=table[:, :3].max(axis=0),
    )
    ens.save(str(directory))
    return directory


def test_cli_infer_features_csv_json(chain, tmp_path):
    mdir = _fake_training_ensemble(tmp_path / "model", toy_table())
    cal = chain["dir"] / "cal.json"
    c = chain["cal"].cam.mean(axis=0)
    base = [sys.executable, "-m", "elastimap.camera.cli", "infer", "--model", str(mdir), "--calibration", str(cal)]
    r = subprocess.run(base + ["--features", *map(str, c), "--json"], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr
    rows = json.loads(r.stdout)
    assert len(rows) == 1 and {"d", "d_sd", "flags"} <= set(rows[0]) and rows[0]["n_members"] == 3
    lesions = tmp_path / "lesions.csv"
    lesions.write_text(f"id,O1,O2,O3\nA,{c[0]},{c[1]},{c[2]}\nB,{10 * c[0]},{c[1]},{c[2]}\n")
    out = tmp_path / "est.csv"
    r = subprocess.run(base + ["--csv", str(lesions), "--out", str(out)], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr
    import pandas as pd

    df = pd.read_csv(out)
    assert list(df["id"]) == ["A", "B"] and "outside_calibration:O1" in df["flags"][1]
    assert "FLAGGED" in r.stdout
    r = subprocess.run(
        base + ["--features", "1", "2", "3", "--csv", str(lesions)], capture_output=True, text=True, cwd=REPO
    )
    assert r.returncode == 2 and r.stderr.startswith("error: input:")


def test_infer_api_does_not_import_solver_fem():
    code = (
        "import sys, elastimap.camera.infer, elastimap.camera.optics, elastimap.camera.features, elastimap.camera.calibration; "
        "bad=[m for m in sys.modules if m.startswith(('dolfinx','elastimap.solver.fem','elastimap.solver.api','gmsh'))]; "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stdout + r.stderr


@pytest.mark.slow
def test_end_to_end_with_trained_ensemble_cli_images(chain, tmp_path):
    """Train a small real ensemble (elastimap.training.api.fit_ensemble, LM) on the TOY table, save it, and run
    ``infer --images`` on 30 SYNTHETIC frames of a lesion not in the table.  Same tolerances as above."""
    api = pytest.importorskip("elastimap.training.api", reason="elastimap.training.api not available")
    import pandas as pd

    tab = toy_table()
    ens = api.fit_ensemble(
        pd.DataFrame(tab, columns=["d", "h", "E", "O1", "O2", "O3"]), algo="lm", repeats=2, epochs=60, seed=0
    )
    ens.save(str(tmp_path / "model"))
    m = chain["sensor"].replace(seed=7)
    r = toy_solve(*TRUTH)
    F, B = render_pair(m, r.image_raw, r.image, r.pixel, 30)
    write_frames(F, tmp_path / "f", "lesion", "tiff")
    write_frames(B, tmp_path / "f", "lesion_background", "tiff")
    out = tmp_path / "est.json"
    cmd = [
        sys.executable,
        "-m",
        "elastimap.camera.cli",
        "infer",
        "--model",
        str(tmp_path / "model"),
        "--calibration",
        str(chain["dir"] / "cal.json"),
        "--images",
        str(tmp_path / "f" / "synthetic_lesion_f*.tif"),
        "--background",
        str(tmp_path / "f" / "synthetic_lesion_background_f*.tif"),
        "--out",
        str(out),
        "--identifiability",
        "none",
    ]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=300)
    assert res.returncode == 0, res.stderr
    [row] = json.loads(out.read_text())
    d, h, E = TRUTH
    assert row["ok"], row
    assert row["d"] == pytest.approx(d, rel=0.10), row
    assert row["h"] == pytest.approx(h, rel=0.15), row
    assert row["E"] == pytest.approx(E, rel=0.35), row


def test_image_model_from_synthetic_camera_frames(chain, toy_image_model, tmp_path):
    """Camera frames -> difference image on the FEM grid (inverse sensor response) -> image model.
    TOY forward model, SYNTHETIC camera; the image model is a small SCG ensemble (ln E target) on
    the toy table's images.  Tolerance 25 % on d and h (a 2-member, 8-neuron net).  The real-FEM
    version of this chain is tests/camera/test_camera_frames_fem.py."""
    from elastimap.camera.infer import difference_of_frames
    from elastimap.identify.image_model import ImageModel

    model = ImageModel.load(str(toy_image_model))  # the module's toy image model (fixture below)
    m = chain["sensor"].replace(seed=5)
    r = toy_solve(*TRUTH)
    F, B = render_pair(m, r.image_raw, r.image, r.pixel, 30)
    pf = write_frames(F, tmp_path, "lesion", "png")
    pb = write_frames(B, tmp_path, "lesion_background", "png")
    cal = chain["cal"]
    di = difference_of_frames(pf, pb, cal, model)
    assert di.image.shape == model.shape and (di.sigma > 0).all()
    assert di.peak == pytest.approx(r.image.max(), rel=0.02)  # the recovered peak vs the truth
    est = estimate_images(pf, pb, cal, model, "lesion", identifiability=None)
    assert est.input == "frames" and est.n_members == 2 and np.isfinite(est.cam).all()
    assert est.sigma is not None and est.image.shape == (model.shape[0] * model.shape[1],)
    d, h, _ = TRUTH
    assert est.d == pytest.approx(d, rel=0.25), est.to_dict()
    assert est.h == pytest.approx(h, rel=0.25), est.to_dict()


@pytest.fixture(scope="module")
def toy_image_model(chain):
    from elastimap.identify.image_model import fit_image_model
    from elastimap.identify.measure import Data
    from elastimap.training.experiment import TrainConfig

    tab = toy_table()
    res = [toy_solve(*row[:3]) for row in tab]
    n = len(tab)
    data = Data(
        theta=tab[:, :3],
        features=tab[:, 3:],
        images=np.stack([r.image.ravel() for r in res]),
        dforce=np.zeros(n),
        force_ref=np.ones(n),
        tags=np.array(["design"] * n),
        ids=np.array([f"t{i:04d}" for i in range(n)]),
        shape=res[0].image.shape,
        pixel=res[0].pixel,
        source="TOY",
    )
    model = fit_image_model(
        data, "scg", repeats=2, cfg=TrainConfig(hidden=((8, "tansig"),), epochs=200, progress=False), k=6, log_e=True
    )
    d = chain["dir"] / "toy-image-model"
    d.mkdir(exist_ok=True)
    model.save(str(d))
    return d


def test_cli_csv_batch_of_frames_with_an_image_model(chain, toy_image_model, tmp_path):
    """``infer --csv`` with an image model: the CSV names each lesion's frame globs (TOY forward model)."""
    m = chain["sensor"]
    lines = ["id,images,background"]
    for i, truth in enumerate([(7.0, 9.5, 70.0), (9.0, 8.0, 40.0)]):
        r = toy_solve(*truth)
        F, B = render_pair(m.replace(seed=20 + i), r.image_raw, r.image, r.pixel, 5)
        write_frames(F, tmp_path / f"L{i}", "lesion", "png")
        write_frames(B, tmp_path / f"L{i}", "lesion_background", "png")
        lines.append(f"L{i},L{i}/synthetic_lesion_f*.png,L{i}/synthetic_lesion_background_f*.png")
    (tmp_path / "lesions.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "est.json"
    cmd = [
        sys.executable,
        "-m",
        "elastimap.camera.cli",
        "infer",
        "--model",
        str(toy_image_model),
        "--calibration",
        str(chain["dir"] / "cal.json"),
        "--csv",
        str(tmp_path / "lesions.csv"),
        "--identifiability",
        "none",
        "--out",
        str(out),
    ]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=300)
    assert res.returncode == 0, res.stderr
    rows = json.loads(out.read_text())
    assert [r["id"] for r in rows] == ["L0", "L1"] and all(r["input"] == "frames" for r in rows)
    assert all(r["image_peak_sigma_mm"] > 0 for r in rows)
    # an image model cannot take camera features
    (tmp_path / "feat.csv").write_text("id,O1,O2,O3\n1,0.03,3.0,300\n")
    cmd[cmd.index("--csv") + 1] = str(tmp_path / "feat.csv")
    res = subprocess.run(cmd[:-2], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert res.returncode == 2 and "images,background" in res.stderr


def test_impossible_or_outside_interval_is_not_printed_as_a_number():
    from elastimap.camera.cli import _quantity
    from elastimap.camera.infer import Estimate, _plausibility

    def est(mean, lo, hi):
        m = np.array(mean, float)
        return Estimate(
            "1", np.zeros(3), np.zeros(3), m, np.zeros(3), m, m, 1, [], lo=np.array(lo, float), hi=np.array(hi, float)
        )

    ok, bad = _plausibility(
        [est((8, 7, 50), (7, 6, 40), (9, 8, 60)), est((12.9, 6.66, 6.2), (11, 5, 10), (14, 8, 15.4))]
    )
    assert ok.ok and all(ok.reportable(q) for q in "dhE")
    assert "outside_interval:E" in bad.flags and not bad.reportable("E") and bad.reportable("d")
    assert "6.2" not in _quantity(bad.to_dict(), "E", "kPa") and "10-15.4" in _quantity(bad.to_dict(), "E", "kPa")
    [imp] = _plausibility([est((8, 2.0, -3), (7, 1, 1), (9, 3, 5))])  # h < 1 + d/2: crosses the surface
    assert {"impossible:h", "impossible:E"} <= set(imp.flags)


def test_no_visible_inclusion_in_frames_is_not_reported(toy_image_model):
    """From frames, an image whose largest pixel is below DETECT_SIGMA standard errors is no_signal."""
    from elastimap.camera.infer import DETECT_SIGMA, estimate_fem_images, load_model

    model = load_model(str(toy_image_model))
    img = toy_solve(*TRUTH).image
    loud = estimate_fem_images(img[None], model, identifiability=None, sigma=np.full((1,) + img.shape, img.max() / 50))[
        0
    ]
    quiet = estimate_fem_images(
        img[None], model, identifiability=None, sigma=np.full((1,) + img.shape, img.max() / (DETECT_SIGMA - 1))
    )[0]
    assert "no_signal" not in loud.flags
    assert "no_signal" in quiet.flags and not any(quiet.reportable(q) for q in "dhE")
    # what cannot be seen may be anywhere in the design: its interval is the box, not the model's guess
    from elastimap.camera.infer import design_box_interval

    lo, hi = design_box_interval()
    np.testing.assert_allclose(lo, [2.0, 2.0, 10.0])
    np.testing.assert_allclose(hi, [15.0, 17.0, 200.0])
    np.testing.assert_array_equal(quiet.lo, lo)
    np.testing.assert_array_equal(quiet.hi, hi)
    # with the shipped identifiability map too (it sets every estimate's interval first), and only
    # for the estimate that shows nothing
    both = estimate_fem_images(
        np.stack([img, img]),
        model,
        sigma=np.stack([np.full(img.shape, img.max() / 50), np.full(img.shape, img.max() / (DETECT_SIGMA - 1))]),
    )
    assert "no_signal" not in both[0].flags and "no_signal" in both[1].flags
    np.testing.assert_array_equal(np.c_[both[1].lo, both[1].hi], np.c_[lo, hi])
    assert not np.array_equal(np.c_[both[0].lo, both[0].hi], np.c_[lo, hi])
