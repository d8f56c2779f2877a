"""What the fresh bad-input sweep (``tests/contracts/badsweep_fresh.py``, issue 40's goal) found.

Each case was accepted, written over an input, or ended in a traceback before its fix; now it is
refused with exit code 2 and one line naming the flag, before any work, and nothing changes.
"""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest
from test_bad_inputs import BIN, assert_refused, invoke, make_calibration, make_dataset, make_model, snapshot

SOLVE = ["--d", "8", "--h", "8", "--E", "60", "--mesh", "tiny"]
SWEEP = ["run", "--mesh", "tiny", "--n", "1", "--jobs", "1", "--no-progress"]
INFER = ["--model", "{A}/model", "--calibration", "{A}/cal.json"]
FEATS = ["--features", "1", "2", "3", "--identifiability", "none"]
TRAIN = ["--synthetic", "30", "--repeats", "1", "--epochs", "2", "--hidden", "3", "--no-progress"]


class WorkStarted(BaseException):
    """A forward solve began before the bad input was refused."""


@pytest.fixture
def no_solves(monkeypatch):
    import gmsh

    def trap(*a, **k):
        raise WorkStarted("gmsh.initialize: a solve started before the input was checked")

    monkeypatch.setattr(gmsh, "initialize", trap)


@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    a = tmp_path_factory.mktemp("fresh")
    make_dataset(a / "ds")
    make_model(a / "model")
    make_calibration(a / "cal.json")
    (a / "feats.csv").write_text("id,O1,O2,O3\nA,1,2,3\n")
    (a / "sensor.toml").write_text('name = "lab"\n[tissue]\nE = 5.0\n')
    (a / "phantoms.csv").write_text("name,d,h,E\na,5,8,40\nb,6,8,50\nc,7,9,60\n")
    (a / "frames").mkdir()
    (a / "frames" / "mine.txt").write_text("my notes\n")
    code, _, err = invoke("gap", ["synth", "--backend", "toy", "--cache", "none", "--n", "4", "--frames", "2",
                                  "--no-progress", "--out", str(a / "meas")])  # fmt: skip
    assert code == 0, err
    return a


CASES = [
    # an output onto one of the command's inputs (it was overwritten)
    ("infer", [*INFER, *FEATS, "--out", "{A}/cal.json"], "--out"),
    ("infer", [*INFER, "--csv", "{A}/feats.csv", "--identifiability", "none", "--out", "{A}/feats.csv"], "--out"),
    ("infer", [*INFER, *FEATS, "--out", "{A}/model/model.json"], "--out"),
    ("infer", [*INFER, *FEATS, "--out", "r.txt"], "--out"),
    ("infer", [*INFER, *FEATS, "--background", "x*.png"], "--background"),
    (
        "calibrate",
        ["--mesh", "tiny", "--frames", "2", "--phantoms", "{A}/phantoms.csv", "--out", "{A}/phantoms.csv"],
        "--out",
    ),  # fmt: skip
    ("calibrate", ["--mesh", "tiny", "--frames", "2", "--out", "c.json", "--plot", "c.json"], "--plot"),
    ("calibrate", ["--mesh", "tiny", "--frames", "2", "--out", "c.json", "--plot", "c.toml"], "--plot"),
    ("solve", [*SOLVE, "--sensor", "{A}/sensor.toml", "--image", "{A}/sensor.toml"], "--image"),
    ("solve", [*SOLVE, "--image", "x.json"], "--image"),
    ("dataset", ["export", "{A}/ds", "--out", "{A}/ds/x.csv"], "--out"),
    ("dataset", ["plot", "{A}/ds", "--out", "{A}/ds"], "--out"),
    ("dataset", ["plot", "{A}/ds"], "--out"),
    # train --overwrite replaced any folder; --out inside --data mixed a run into the data
    ("train", [*TRAIN, "--out", "{A}/frames", "--overwrite"], "--out"),
    ("train", ["--data", "{A}/ds", *TRAIN[2:], "--out", "{A}/ds/run"], "--out"),
    ("train", [*TRAIN, "--workers", "99999", "--out", "tr"], "--workers"),
    # empty or malformed values that were taken for the default
    ("sweep", [*SWEEP, "--out", ""], "--out"),
    ("sweep", [*SWEEP, "--out", "s", "--ranges", ""], "--ranges"),
    ("sweep", [*SWEEP, "--out", "s", "--ranges", "d=2:15,,E=10:20"], "--ranges"),
    ("sweep", [*SWEEP, "--out", "s", "--dashboard", "127.0.0.1:99999"], "--dashboard"),
    ("sweep", [*SWEEP, "--out", "s", "--dashboard", "::::"], "--dashboard"),
    ("sweep", ["bench", "--mesh", "tiny", "--n", "1", "--jobs-list", "1,,2"], "--jobs-list"),
    # the --jobs note came before the error line
    ("sweep", [*SWEEP, "--out", "s", "--scheduler", "not a url", "--connect-timeout", "2"], "--scheduler"),
    ("elastimap", ["demo", "--mesh", "tiny", "--out", ""], "--out"),
    # sizes and fractions out of range
    ("camera", ["synth", *SOLVE, "--frames", "100000", "--out", "fr"], "--frames"),
    ("calibrate", ["--mesh", "tiny", "--frames", "100000", "--out", "c.json"], "--frames"),
    ("gap", ["bench", "--mesh", "tiny", "--data-cache", "{A}/cal.json"], "--data-cache"),
    ("elastimap", ["demo", "--mesh", "tiny", "--jobs", "1", "--n", "4", "--out", "dm"], "--n"),
    ("elastimap", ["study", "image_model", "--data", "{A}/feats.csv", "--out", "im"], "--data"),
    # the saved model replaced the sweep it was trained on
    (
        "elastimap",
        [
            "study",
            "image_model",
            "--data",
            "{A}/ds",
            "--validate",
            "none",
            "--k",
            "3",
            "--hidden",
            "3",
            "--repeats",
            "1",
            "--epochs",
            "2",
            "--save-model",
            "{A}/ds",
        ],
        "--save-model",
    ),  # fmt: skip
    (
        "gap",
        [
            "diagnose",
            "--measured",
            "{A}/meas",
            "--backend",
            "toy",
            "--mesh",
            "tiny",
            "--cache",
            "none",
            "--no-inverse",
            "--effects",
            "",
            "--out",
            "dg",
        ],
        "--effects",
    ),  # fmt: skip
]


@pytest.mark.parametrize(("script", "args", "flag"), CASES, ids=[f"{s}-{i}" for i, (s, _, _) in enumerate(CASES)])
def test_refused_before_work(script, args, flag, assets, tmp_path, monkeypatch, no_solves):
    monkeypatch.chdir(tmp_path)
    before = snapshot(assets, tmp_path)
    code, out, err = invoke(script, [a.replace("{A}", str(assets)) for a in args])
    assert_refused(code, out, err, (flag,))
    assert snapshot(assets, tmp_path) == before


def _frames(folder, kind: str):
    from elastimap.camera.frames import write_frames

    rng = np.random.default_rng(0)
    return write_frames(rng.integers(0, 200, (2, 40, 40), dtype=np.uint8), folder, kind, synthetic=False)


def test_features_o3_threshold_is_a_fraction_of_full_scale(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _frames(tmp_path / "f", "l")
    _frames(tmp_path / "b", "b")
    code, out, err = invoke(
        "camera", ["features", "--images", "f/*", "--background", "b/*", "--o3-threshold", "2"]
    )  # fmt: skip
    assert_refused(code, out, err, ("--o3-threshold",))


def test_corrupt_tiff_is_one_line(tmp_path):
    """tifffile logged its own parse error as a second stderr line (a subprocess: pytest captures logs)."""
    _frames(tmp_path / "b", "b")
    (tmp_path / "c.tif").write_bytes(b"II*\x00" + b"\xff\xff\xff\x7f" + bytes(300))
    p = subprocess.run(
        [str(BIN / "camera"), "features", "--images", "c.tif", "--background", "b/*"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert_refused(p.returncode, p.stdout, p.stderr, ("c.tif",))


@pytest.fixture(scope="module")
def image_model(tmp_path_factory):
    """A small SYNTHETIC image model (Gaussian bumps, no solver) on a 12 x 12 grid."""
    from elastimap.identify.image_model import fit_image_model
    from elastimap.identify.measure import Data
    from elastimap.training.experiment import TrainConfig

    rng = np.random.default_rng(0)
    n = 30
    d, h, E = rng.uniform(3, 12, n), rng.uniform(4, 12, n), rng.uniform(10, 200, n)
    y, x = np.mgrid[0:12, 0:12] * 0.5
    amp, width = 1e-3 * d**2 / h * (E / (E + 20)), 0.5 * d + 0.3 * h
    images = amp[:, None] * np.exp(-(x.ravel() ** 2 + y.ravel() ** 2)[None] / (2 * width[:, None] ** 2))
    data = Data(
        theta=np.column_stack([d, h, E]),
        features=np.column_stack([amp, images.sum(1), np.full(n, 10.0)]),
        images=images,
        dforce=amp * 100,
        force_ref=np.full(n, 1400.0),
        tags=np.array(["design"] * n),
        ids=np.array([f"s{i}" for i in range(n)]),
        shape=(12, 12),
        pixel=0.5,
    )
    cfg = TrainConfig(hidden=((3, "tansig"),), epochs=3, progress=False)
    model = fit_image_model(data, "scg", repeats=1, cfg=cfg, k=3)
    return model.save(str(tmp_path_factory.mktemp("imodel") / "m"))


@pytest.mark.parametrize(
    "bad",
    [np.zeros((3, 3)), np.zeros((1, 1, 3, 3)), np.zeros((0, 12, 12)), np.full((12, 12), np.nan)],
    ids=["shape", "4d", "empty", "nan"],
)
def test_fem_image_of_the_wrong_shape_is_one_line(bad, image_model, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    np.save(tmp_path / "x.npy", bad)
    code, out, err = invoke("infer", ["--model", str(image_model), "--fem-image", "x.npy", "--identifiability", "none"])
    assert_refused(code, out, err, ("--fem-image",))


def test_train_overwrite_still_replaces_an_earlier_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert invoke("train", [*TRAIN, "--no-model", "--out", "tr"])[0] == 0
    code, out, err = invoke("train", [*TRAIN, "--no-model", "--out", "tr", "--overwrite"])
    assert code == 0, err
    shutil.rmtree(tmp_path / "tr")
