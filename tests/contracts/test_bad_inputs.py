"""Every command answers a bad input with exit code 2 and ONE line on stderr naming the parameter
or file, no traceback, and nothing written or changed on disk.

The cases run in one process through the installed console-script entry points (``solve``,
``sweep``, ``dataset``, ``train``, ``camera``, ``calibrate``, ``infer``, ``gap``, ``elastimap``),
the same functions the ``.venv/bin`` scripts call, with ``sys.argv`` set; a handful run as real
subprocesses of the scripts.  Every case snapshots its working folder and the shared inputs before
and after.  Inputs are chosen so that a case that is NOT refused finishes quickly (tiny mesh, toy
backend, a few networks) instead of hanging the suite.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import pytest

from elastimap.dataset.phantoms import read_phantoms

# its module fixture is costly: under pytest-xdist (make test) this module runs on one worker
pytestmark = pytest.mark.xdist_group("test_bad_inputs")

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent


# ----------------------------------------------------------------------------- helpers
def _entry(name: str):
    (ep,) = [e for e in entry_points(group="console_scripts") if e.name == name]
    return ep.load()


def invoke(name: str, args: list[str]) -> tuple[int, str, str]:
    """Run the console script ``name`` in this process; (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    argv = sys.argv
    sys.argv = [name, *args]
    code = 0
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                _entry(name)()
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        sys.argv = argv
    return code, out.getvalue(), err.getvalue()


def snapshot(*roots: Path) -> dict:
    """Every file and folder under ``roots``: kind, size, mtime and content hash."""
    snap = {}
    for root in roots:
        for dirpath, dirnames, filenames in os.walk(root):
            for d in dirnames:
                p = Path(dirpath, d)
                snap[str(p)] = ("dir",)
            for f in filenames:
                p = Path(dirpath, f)
                st = p.lstat()
                h = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else ""
                snap[str(p)] = ("file", st.st_size, st.st_mtime_ns, h)
    return snap


def assert_refused(code: int, out: str, err: str, names: tuple[str, ...]):
    assert "Traceback" not in err + out, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, f"exit {code}, stderr: {err!r}, stdout tail: {out[-300:]!r}"
    assert len(lines) == 1, f"expected one line on stderr, got {lines!r}"
    assert any(n.lower() in lines[0].lower() for n in names), f"{lines[0]!r} names none of {names}"


# ----------------------------------------------------------------------------- shared inputs
def _sample_rows(n: int, seed: int = 0, prefix: str = "s"):
    from elastimap.training.data import synthetic_features

    rng = np.random.default_rng(seed)
    d, h, E = rng.uniform(4, 10, n), rng.uniform(6, 12, n), rng.uniform(20, 200, n)
    O1, O2, O3 = synthetic_features(d, h, E)
    return [
        {
            "sample_id": f"{prefix}{i:04d}",
            "tag": "design",
            "d": d[i],
            "h": h[i],
            "E": E[i],
            "O1": O1[i],
            "O2": O2[i],
            "O3": O3[i],
            "status": "ok",
            "error": "",
            "ndofs": 1,
            "newton_iterations": 1,
            "seconds": 0.1,
            "force": 1.0,
            "force_ref": 1.0,
        }
        for i in range(n)
    ]


def make_dataset(path: Path, n: int = 30, seed: int = 0, prefix: str = "s") -> Path:
    """A SYNTHETIC sample dataset (analytic features, no solver) landed as the sweep lands it."""
    from elastimap.dataset import io as dio

    path.mkdir(parents=True, exist_ok=True)
    rows = _sample_rows(n, seed, prefix)
    for i in range(0, n, 10):
        dio.land_rows(path, rows[i : i + 10])
    return path


def make_model(path: Path) -> Path:
    from elastimap.training.api import fit_ensemble
    from elastimap.training.data import synthetic_table

    ens = fit_ensemble(synthetic_table(40, seed=1), algo="scg", repeats=2, epochs=3, hidden=(3,), seed=0)
    ens.save(str(path))
    return path


def make_calibration(path: Path) -> Path:
    from elastimap.camera import calibration as C

    ph = read_phantoms(None, min_rows=3, why="to fit a calibration line")
    rng = np.random.default_rng(0)
    fem = np.abs(rng.normal(1, 0.3, (len(ph), 3))) + np.arange(len(ph))[:, None]
    cam = 2 * fem + 0.1 + rng.normal(0, 0.01, fem.shape)
    C.fit_calibration(ph, fem, cam, {}, None, True).save(path)
    return path


@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    """Inputs the bad cases point at; none of them may change."""
    a = tmp_path_factory.mktemp("assets")
    make_dataset(a / "ds")
    import pandas as pd

    pd.DataFrame({"x": [1.0, 2.0], "y": [3.0, 4.0]}).to_parquet(a / "foreign.parquet")
    (a / "notes.txt").write_text("not data\n")
    (a / "a-file").write_text("a file, not a folder\n")
    (a / "notjson.json").write_text("{ nope\n")
    model = make_model(a / "model")
    make_calibration(a / "cal.json")
    (a / "dup.csv").write_text("id,O1,O2,O3\nA,1,2,3\nA,1,2,3\n")
    (a / "feats.csv").write_text("id,O1,O2,O3\nA,1,2,3\n")
    # damaged copies of the model, one defect each
    for name in ("truncated", "garbage", "renamed", "arch", "noscaling", "nan", "edited"):
        shutil.copytree(model, a / f"model-{name}")
    w = a / "model-truncated" / "ensemble.safetensors"
    w.write_bytes(w.read_bytes()[: w.stat().st_size // 2])
    (a / "model-garbage" / "ensemble.safetensors").write_bytes(b"\x00garbage" * 50)
    from safetensors.numpy import load_file, save_file

    t = load_file(str(model / "ensemble.safetensors"))
    save_file(
        {k.replace("layer0", "layerX"): v for k, v in t.items()}, str(a / "model-renamed" / "ensemble.safetensors")
    )
    t2 = {k: v.copy() for k, v in t.items()}
    t2["layer0.weight"][0, 0, 0] = np.nan
    save_file(t2, str(a / "model-nan" / "ensemble.safetensors"))
    t3 = {k: v.copy() for k, v in t.items()}
    t3["layer1.bias"][0, 0] += 0.5
    save_file(t3, str(a / "model-edited" / "ensemble.safetensors"))
    mj = json.loads((model / "model.json").read_text())
    mj2 = json.loads(json.dumps(mj))
    mj2["architecture"]["hidden"][0]["size"] = 5  # the weights are for 3 neurons
    (a / "model-arch" / "model.json").write_text(json.dumps(mj2))
    mj3 = dict(mj)
    mj3.pop("scaling")
    (a / "model-noscaling" / "model.json").write_text(json.dumps(mj3))
    # a real (not synthetic) measured dataset: a generator must never replace it
    r = invoke(
        "gap",
        [
            "synth",
            "--out",
            str(a / "M"),
            "--backend",
            "toy",
            "--cache",
            "none",
            "--n",
            "4",
            "--frames",
            "2",
            "--mesh",
            "tiny",
            "--no-progress",
        ],
    )
    assert r[0] == 0, r
    side = json.loads((a / "M" / "measured.json").read_text())
    side["synthetic"] = False
    (a / "M" / "measured.json").write_text(json.dumps(side))
    r = invoke(
        "gap",
        [
            "synth",
            "--out",
            str(a / "S"),
            "--backend",
            "toy",
            "--cache",
            "none",
            "--n",
            "4",
            "--frames",
            "2",
            "--mesh",
            "tiny",
            "--no-progress",
        ],
    )
    assert r[0] == 0, r
    (a / "run").mkdir()
    (a / "run" / "results.csv").write_text("an earlier run\n")
    return a


# ----------------------------------------------------------------------------- the cases
# (console script, arguments with {A} = the shared inputs folder, words of which the error line names one)
TINY = ["--mesh", "tiny"]
TRAIN = ["--synthetic", "30", "--repeats", "1", "--epochs", "2", "--hidden", "3", "--no-progress", "--out", "tr"]
SYNTH = ["--backend", "toy", "--cache", "none", "--n", "4", "--frames", "2", "--mesh", "tiny", "--no-progress"]
DIAG = ["--measured", "{A}/S", "--backend", "toy", "--cache", "none", "--no-inverse", "--no-progress", "--out", "dg"]
INFER = ["--calibration", "{A}/cal.json", "--features", "1", "2", "3", "--identifiability", "none"]
SIN = ["--d", "8", "--h", "8", "--E", "60", "--frames", "1", "--mesh", "tiny", "--out", "fr"]

CASES = [
    # ---- solve
    ("solve", ["--E", "inf", *TINY], ("--E", "E:")),
    ("solve", ["--E", "nan", *TINY], ("--E", "E:")),
    ("solve", ["--E", "-5", *TINY], ("--E", "E:")),
    ("solve", ["--tissue-E", "inf", *TINY], ("tissue",)),
    ("solve", ["--tissue-E", "0", *TINY], ("tissue",)),
    ("solve", ["--d", "-1", *TINY], ("--d", "d:")),
    ("solve", ["--d", "inf", *TINY], ("--d", "d:")),
    ("solve", ["--h", "100", *TINY], ("--h", "h:")),
    ("solve", ["--delta", "0", *TINY], ("delta",)),
    ("solve", ["--delta", "100", *TINY], ("delta",)),
    ("solve", ["--force", "-5", *TINY], ("force",)),
    ("solve", ["--force", "inf", *TINY], ("force",)),
    ("solve", ["--thickness", "1e6", *TINY], ("thickness",)),
    ("solve", ["--thickness", "0", *TINY], ("thickness",)),
    ("solve", ["--nu", "0.5", *TINY], ("nu",)),
    ("solve", ["--pixel", "0", *TINY], ("pixel",)),
    ("solve", ["--pixel", "0.7", *TINY], ("pixel",)),
    ("solve", ["--pixel", "1e-5", *TINY], ("pixel",)),
    ("solve", ["--layers", "abc", *TINY], ("layers",)),
    ("solve", ["--layers", "2:-1", *TINY], ("layer",)),
    ("solve", ["--layers", "1e6:300", *TINY], ("layer",)),
    ("solve", ["--mesh", "huge"], ("mesh",)),
    ("solve", ["--degree", "3", *TINY], ("degree",)),
    ("solve", ["--threshold", "-1", *TINY], ("threshold",)),
    ("solve", ["--vtx", "{A}/a-file", *TINY], ("--vtx", "a-file")),
    ("solve", ["--image", "nodir/x.png", *TINY], ("--image", "nodir")),
    ("solve", ["--image-npy", "nodir/x.npy", *TINY], ("--image-npy", "nodir")),
    ("solve", ["--image", "{A}/ds", *TINY], ("--image", "ds")),
    ("solve", ["--bogus"], ("--bogus",)),
    # ---- sweep
    ("sweep", ["run", "--seed", "-1", "--n", "2", *TINY, "--out", "sw"], ("seed",)),
    ("sweep", ["run", "--n", "-3", *TINY, "--out", "sw"], ("--n", "n:")),
    ("sweep", ["run", "--jobs", "0", "--n", "2", *TINY, "--out", "sw"], ("jobs",)),
    ("sweep", ["run", "--n", "2", "--mesh", "huge", "--out", "sw"], ("mesh",)),
    ("sweep", ["run", "--n", "2", "--design", "foo", *TINY, "--out", "sw"], ("design",)),
    ("sweep", ["run", "--n", "2", "--ranges", "d=5:1", *TINY, "--out", "sw"], ("ranges", "d")),
    ("sweep", ["run", "--samples", "missing.csv", *TINY, "--out", "sw"], ("samples", "missing.csv")),
    ("sweep", ["run", "--n", "2", "--batch-rows", "0", *TINY, "--out", "sw"], ("batch",)),
    ("sweep", ["run", "--n", "2", "--timeout", "-1", *TINY, "--out", "sw"], ("timeout",)),
    ("sweep", ["run", "--n", "2", "--interface", "foo", *TINY, "--out", "sw"], ("interface",)),
    ("sweep", ["run", "--n", "2", *TINY, "--out", "{A}/a-file"], ("out", "a-file")),
    ("sweep", ["run", "--n", "2", *TINY, "--out", "{A}/a-file/sub"], ("out", "a-file")),
    ("sweep", ["bench", "--jobs-list", "a,b", *TINY], ("jobs-list", "jobs_list")),
    ("sweep", ["nope"], ("nope",)),
    # ---- dataset
    ("dataset", ["inspect", "missing"], ("missing",)),
    ("dataset", ["inspect", "{A}/foreign.parquet"], ("foreign.parquet",)),
    ("dataset", ["inspect", "{A}/notes.txt"], ("notes.txt",)),
    ("dataset", ["inspect", "{A}/ds", "--top", "-1"], ("top",)),
    ("dataset", ["plot", "{A}/ds", "--out", "{A}/a-file"], ("out", "a-file")),
    ("dataset", ["plot", "{A}/ds", "--out", "{A}/a-file/sub"], ("out", "a-file")),
    ("dataset", ["plot", "{A}/ds", "--out", "figs", "--n-images", "-1"], ("--n-images",)),
    ("dataset", ["plot", "{A}/foreign.parquet", "--out", "figs"], ("foreign.parquet",)),
    ("dataset", ["export", "{A}/ds", "--out", "nodir/x.csv"], ("out", "nodir")),
    ("dataset", ["export", "{A}/ds", "--out", "{A}/ds"], ("out",)),
    ("dataset", ["export", "{A}/foreign.parquet", "--out", "x.csv"], ("foreign.parquet",)),
    ("dataset", ["export", "{A}/ds", "--status", "bogus", "--out", "x.csv"], ("status",)),
    ("dataset", ["compact", "missing"], ("missing",)),
    ("dataset", ["compact", "{A}/ds", "--batch-rows", "0"], ("batch",)),
    # ---- train
    ("train", [*TRAIN, "--epochs", "0"], ("epochs",)),
    ("train", [*TRAIN, "--threads", "-1"], ("threads",)),
    ("train", [*TRAIN, "--repeats", "0"], ("repeats",)),
    ("train", [*TRAIN, "--algo", "foo"], ("algo",)),
    ("train", [*TRAIN, "--validate", "foo"], ("validate",)),
    ("train", [*TRAIN[2:], "--data", "missing"], ("data", "missing")),
    ("train", [*TRAIN[2:], "--data", "{A}/foreign.parquet"], ("foreign.parquet",)),
    ("train", [*TRAIN[2:], "--data", "{A}/notes.txt"], ("notes.txt",)),
    ("train", [*TRAIN[2:]], ("data",)),
    ("train", [*TRAIN, "--data", "{A}/ds"], ("data",)),
    ("train", [*TRAIN[:1], "5", *TRAIN[2:]], ("synthetic",)),
    ("train", [*TRAIN, "--feature-noise", "2"], ("noise",)),
    ("train", [*TRAIN, "--val-fraction", "1"], ("val",)),
    ("train", [*TRAIN, "--test-split", "1.5"], ("split",)),
    ("train", [*TRAIN[:4], "--epochs", "2", "--hidden", "0", "--no-progress", "--out", "tr"], ("hidden",)),
    ("train", [*TRAIN[:4], "--epochs", "2", "--hidden", "3:foo", "--no-progress", "--out", "tr"], ("hidden", "foo")),
    ("train", [*TRAIN, "--activation", "foo"], ("activation", "foo")),
    ("train", [*TRAIN, "--device", "tpu"], ("device",)),
    ("train", [*TRAIN, "--workers", "-1"], ("workers",)),
    ("train", [*TRAIN[:-1], "{A}/a-file"], ("out", "a-file")),
    ("train", [*TRAIN[:-1], "{A}/run"], ("out", "run")),
    ("train", [*TRAIN[:-1], "{A}/a-file/sub"], ("out", "a-file")),
    # ---- camera
    ("camera", ["synth", *SIN[:1], "-1", *SIN[2:]], ("--d", "d:")),
    ("camera", ["synth", *SIN[:7], "0", *SIN[8:]], ("frames",)),
    ("camera", ["synth", *SIN, "--sensor", "missing.json"], ("sensor", "missing.json")),
    ("camera", ["synth", *SIN, "--sensor", "{A}/notjson.json"], ("sensor", "notjson")),
    ("camera", ["synth", *SIN, "--bits", "12"], ("bits",)),
    ("camera", ["synth", *SIN[:-1], "{A}/a-file"], ("out", "a-file")),
    ("camera", ["features", "--images", "missing.png", "--background", "missing-bg.png"], ("missing",)),
    ("camera", ["features", "--images", "{A}/notes.txt", "--background", "{A}/notes.txt"], ("notes.txt",)),
    ("camera", ["detect", "--repeats", "0", *TINY, "--out", "det"], ("repeats",)),
    ("camera", ["detect", "--noise-scales", "a,b", *TINY, "--out", "det"], ("noise",)),
    ("camera", ["detect", "--sensor", "{A}/notjson.json", *TINY, "--out", "det"], ("sensor", "notjson")),
    ("camera", ["detect", *TINY, "--out", "{A}/a-file"], ("out", "a-file")),
    (
        "camera",
        ["calibrate", "--fem-features", "missing.csv", *TINY, "--frames", "2", "--out", "c.json"],
        ("fem", "missing.csv"),
    ),
    # ---- calibrate
    ("calibrate", ["--fem-features", "missing.csv", *TINY, "--frames", "2", "--out", "c.json"], ("fem", "missing.csv")),
    (
        "calibrate",
        ["--fem-features", "{A}/foreign.parquet", *TINY, "--frames", "2", "--out", "c.json"],
        ("foreign.parquet",),
    ),
    ("calibrate", ["--phantoms", "missing.csv", *TINY, "--frames", "2", "--out", "c.json"], ("phantoms", "missing")),
    ("calibrate", [*TINY, "--frames", "0", "--out", "c.json"], ("frames",)),
    ("calibrate", [*TINY, "--frames", "2", "--out", "{A}/a-file/c.json"], ("out", "a-file")),
    ("calibrate", [*TINY, "--frames", "2", "--out", "{A}/ds"], ("out", "ds")),
    (
        "calibrate",
        [*TINY, "--frames", "2", "--out", "c.json", "--write-frames", "{A}/a-file"],
        ("write-frames", "write_frames", "a-file"),
    ),
    # ---- infer
    ("infer", ["--model", "missing", *INFER], ("model", "missing")),
    ("infer", ["--model", "{A}/model", "--features", "1", "2", "3", "--identifiability", "none"], ("calibration",)),
    ("infer", ["--model", "{A}/model-truncated", *INFER], ("ensemble.safetensors",)),
    ("infer", ["--model", "{A}/model-garbage", *INFER], ("ensemble.safetensors",)),
    ("infer", ["--model", "{A}/model-renamed", *INFER], ("ensemble.safetensors",)),
    ("infer", ["--model", "{A}/model-arch", *INFER], ("model.json", "ensemble.safetensors")),
    ("infer", ["--model", "{A}/model-noscaling", *INFER], ("model.json",)),
    ("infer", ["--model", "{A}/model-nan", *INFER], ("ensemble.safetensors",)),
    ("infer", ["--model", "{A}/model-edited", *INFER], ("ensemble.safetensors",)),
    (
        "infer",
        ["--model", "{A}/model", "--calibration", "{A}/cal.json", "--csv", "{A}/dup.csv", "--identifiability", "none"],
        ("dup.csv",),
    ),
    ("infer", ["--model", "{A}/model", *INFER, "--crb-limit", "0"], ("crb-limit",)),
    ("infer", ["--model", "{A}/model", "--fem-image", "missing.npy", "--identifiability", "none"], ("fem-image",)),
    ("infer", ["--model", "{A}/model", "--identifiability", "none"], ("input", "features")),
    (
        "infer",
        [
            "--model",
            "{A}/model",
            "--calibration",
            "{A}/notjson.json",
            "--features",
            "1",
            "2",
            "3",
            "--identifiability",
            "none",
        ],
        ("notjson",),
    ),
    ("infer", ["--model", "{A}/model", *INFER, "--out", "nodir/r.csv"], ("out", "nodir")),
    # ---- gap
    ("gap", ["synth", "--out", "{A}/M", *SYNTH], ("--out", "M")),
    ("gap", ["synth", "--out", "{A}/M", "--overwrite", *SYNTH], ("--out", "M")),
    ("gap", ["synth", "--out", "{A}/S", *SYNTH], ("--out", "S")),
    ("gap", ["synth", "--out", "{A}/ds", *SYNTH], ("--out", "ds")),
    ("gap", ["synth", "--out", "{A}/a-file", *SYNTH], ("out", "a-file")),
    ("gap", ["synth", "--out", "m2", *SYNTH, "--n", "2"], ("--n", "n:")),
    ("gap", ["synth", "--out", "m2", "--effect", "bogus=1", *SYNTH], ("bogus",)),
    ("gap", ["synth", "--out", "m2", *SYNTH, "--frames", "0"], ("frames",)),
    ("gap", ["synth", "--out", "m2", *SYNTH, "--jobs", "0"], ("jobs",)),
    ("gap", ["synth", "--out", "m2", "--phantoms", "missing.csv", *SYNTH], ("phantoms", "missing")),
    ("gap", ["diagnose", *DIAG, "--jobs", "0"], ("jobs",)),
    ("gap", ["diagnose", *DIAG, "--model-floor", "-1"], ("floor",)),
    ("gap", ["diagnose", *DIAG, "--n-train", "0"], ("train",)),
    ("gap", ["diagnose", *DIAG, "--effects", "bogus"], ("bogus",)),
    ("gap", ["diagnose", *DIAG[2:], "--measured", "missing"], ("measured", "missing")),
    ("gap", ["diagnose", *DIAG[:-1], "{A}/a-file"], ("out", "a-file")),
    ("gap", ["diagnose", *DIAG[:-1], "{A}/a-file/sub"], ("out", "a-file")),
    ("gap", ["selftest", "--trials", "0", "--backend", "toy", "--cache", "none"], ("trials",)),
    ("gap", ["selftest", "--trials", "1", "--n-phantoms", "1", "--backend", "toy", "--cache", "none"], ("phantoms",)),
    (
        "gap",
        ["selftest", "--trials", "1", "--backend", "toy", "--cache", "none", "--out", "{A}/a-file"],
        ("out", "a-file"),
    ),
    # ---- elastimap
    ("elastimap", ["demo", "--n", "0"], ("--n", "n:")),
    ("elastimap", ["demo", "--jobs", "0"], ("jobs",)),
    ("elastimap", ["demo", "--out", "{A}/a-file"], ("out", "a-file")),
    ("elastimap", ["nope"], ("nope",)),
    # the same refusals through the one command
    ("elastimap", ["solve", "--E", "inf", *TINY], ("--E", "E:")),
    ("elastimap", ["train", *TRAIN, "--epochs", "0"], ("epochs",)),
    ("elastimap", ["train", *TRAIN[:-1], "{A}/run"], ("out", "run")),
    ("elastimap", ["dataset", "inspect", "{A}/ds", "--top", "-1"], ("top",)),
    ("elastimap", ["gap", "synth", "--out", "{A}/M", "--overwrite", *SYNTH], ("out", "real")),
    ("elastimap", ["sweep", "run", "--seed", "-1", "--n", "2", *TINY, "--out", "sw"], ("seed",)),
]


def _ids():
    seen: dict[str, int] = {}
    out = []
    for name, args, _ in CASES:
        key = f"{name} {' '.join(a.replace('{A}/', '') for a in args[:4])}"
        seen[key] = seen.get(key, 0) + 1
        out.append(key if seen[key] == 1 else f"{key} #{seen[key]}")
    return out


def test_enough_cases():
    assert len(CASES) >= 80
    assert {c[0] for c in CASES} >= {
        "solve",
        "sweep",
        "dataset",
        "train",
        "camera",
        "calibrate",
        "infer",
        "gap",
        "elastimap",
    }


@pytest.mark.timeout(300)
@pytest.mark.parametrize("name,args,names", CASES, ids=_ids())
def test_bad_input(name, args, names, assets, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("ELASTIMAP_GAP_CACHE", str(tmp_path / "cache"))
    argv = [a.replace("{A}", str(assets)) for a in args]
    before = snapshot(tmp_path, assets)
    code, out, err = invoke(name, argv)
    assert_refused(code, out, err, names)
    assert snapshot(tmp_path, assets) == before, "a refused command changed the disk"


# a few of the same through the real console scripts
SUBPROCESS = [
    ("solve", ["--E", "inf", "--mesh", "tiny"], ("E",)),
    ("train", ["--synthetic", "30", "--epochs", "0", "--out", "tr"], ("epochs",)),
    ("dataset", ["inspect", "{A}/ds", "--top", "-1"], ("top",)),
    ("gap", ["synth", "--out", "{A}/M", "--overwrite", *SYNTH], ("out", "real")),
    ("infer", ["--model", "{A}/model-truncated", *INFER], ("ensemble.safetensors",)),
]


@pytest.mark.timeout(300)
@pytest.mark.parametrize("name,args,names", SUBPROCESS, ids=[f"{c[0]}-{i}" for i, c in enumerate(SUBPROCESS)])
def test_bad_input_console_script(name, args, names, assets, tmp_path):
    argv = [a.replace("{A}", str(assets)) for a in args]
    before = snapshot(tmp_path, assets)
    env = dict(os.environ, ELASTIMAP_GAP_CACHE=str(tmp_path / "cache"), OMP_NUM_THREADS="1")
    r = subprocess.run([str(BIN / name), *argv], cwd=tmp_path, capture_output=True, text=True, env=env, timeout=280)
    assert_refused(r.returncode, r.stdout, r.stderr, names)
    assert snapshot(tmp_path, assets) == before
