"""Command-line checks that came after the work, or not at all (issue 40, items 5 and 6).

Every case must be refused with exit code 2 and one line naming the flag, *before* any forward
solve: ``gmsh.initialize`` (every solve meshes first) is replaced by a trap that stops the test.
Cases that were tracebacks, or checks that came after nine solves, before the fix: a modulus of
1e308 kPa or a diameter of 1e-300 mm (the solver failed), a symbolic-link loop as ``--image``,
a negative camera seed, a ``--name`` with ``/``.
"""

from __future__ import annotations

import os

import pytest
from test_bad_inputs import assert_refused, invoke, snapshot

SOLVE = ["--d", "8", "--h", "8", "--E", "60", "--mesh", "tiny"]
CSYN = ["synth", "--d", "8", "--h", "8", "--E", "60", "--mesh", "tiny", "--frames", "2", "--out", "fr"]


class WorkStarted(BaseException):
    """A forward solve began before the bad input was refused."""


@pytest.fixture
def no_solves(monkeypatch):
    import gmsh

    def trap(*a, **k):
        raise WorkStarted("gmsh.initialize: a solve started before the input was checked")

    monkeypatch.setattr(gmsh, "initialize", trap)


CASES = [
    ("solve", [*SOLVE, "--E", "1e308"], "--E"),
    ("solve", [*SOLVE, "--E", "1e-300"], "--E"),
    ("solve", [*SOLVE, "--d", "1e-300"], "--d"),
    ("solve", [*SOLVE, "--layers", "2:1e12"], "--layers"),
    ("solve", [*SOLVE, "--image", "loop.png"], "--image"),
    ("camera", [*CSYN, "--seed", "-1"], "--seed"),
    ("camera", [*CSYN, "--noise-scale", "1e308"], "--noise-scale"),
    ("camera", [*CSYN, "--name", "a/b"], "--name"),
    ("camera", [*CSYN, "--name", ".."], "--name"),
    ("camera", [*CSYN, "--sensor", "sensor.json"], "--sensor"),
    ("calibrate", ["--mesh", "tiny", "--out", "cal.json", "--frames", "1"], "--frames"),
    ("calibrate", ["--mesh", "tiny", "--out", "nodir/cal.json"], "--out"),
    ("sweep", ["bench", "--out", "afile"], "--out"),
    ("elastimap", ["study", "region_score", "--pred", "afile"], "--pred"),
    ("solve", [*SOLVE, "--image", ""], "--image"),
    ("camera", [*CSYN, "--sensor", "seed.json"], "--sensor"),
]


@pytest.mark.parametrize(("script", "args", "flag"), CASES, ids=[f"{s}{f}-{i}" for i, (s, _, f) in enumerate(CASES)])
def test_refused_before_any_solve(script, args, flag, tmp_path, monkeypatch, no_solves):
    monkeypatch.chdir(tmp_path)
    os.symlink("loop.png", "loop.png")
    (tmp_path / "sensor.json").write_text('{"binning": "four"}')
    (tmp_path / "afile").write_text("a file")
    (tmp_path / "seed.json").write_text('{"seed": -3}')
    before = snapshot(tmp_path)
    code, out, err = invoke(script, args)
    assert_refused(code, out, err, (flag,))
    assert snapshot(tmp_path) == before


# ----------------------------------------------------------------------------- infer / features
@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    import numpy as np
    from test_bad_inputs import make_calibration, make_model

    from elastimap.camera.frames import write_frames

    a = tmp_path_factory.mktemp("assets")
    make_model(a / "model")
    make_calibration(a / "cal.json")
    rng = np.random.default_rng(0)
    write_frames(rng.integers(0, 200, (2, 40, 40), dtype=np.uint8), a / "frames", "l", synthetic=False)
    (a / "dupO3.csv").write_text("id,O1,O2,O3,O3\nA,1,2,3,4\n")
    (a / "etc.csv").write_text("id,images,background\nA,/etc/*,/etc/*\n")
    (a / "up.csv").write_text("id,fem_image\nA,../x.npy\n")
    return a


INF = ["--model", "{A}/model", "--calibration", "{A}/cal.json", "--identifiability", "none"]
LATE = [
    ("infer", [*INF, "--csv", "{A}/dupO3.csv"], "--csv"),
    ("infer", [*INF, "--csv", "{A}/etc.csv"], "--allow-outside"),
    ("infer", [*INF, "--csv", "{A}/up.csv"], "--allow-outside"),
    ("infer", [*INF[:4], "--identifiability", "", "--features", "1", "2", "3"], "--identifiability"),
    ("camera", ["features", "--images", "{A}/frames/*.png", "--background", "{A}/nomatch*.png"], "--background"),
    ("camera", ["features", "--images", "{A}/cal.json", "--background", "{A}/frames/*.png"], "--images"),
]


@pytest.mark.parametrize(("script", "args", "word"), LATE, ids=[f"{s}-{i}" for i, (s, _, _) in enumerate(LATE)])
def test_inputs_refused_naming_the_flag(script, args, word, assets, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = invoke(script, [a.replace("{A}", str(assets)) for a in args])
    assert_refused(code, out, err, (word,))
    assert snapshot(tmp_path) == {}


def test_compact_on_a_read_only_file_system_is_one_line(tmp_path, monkeypatch):
    import errno

    from test_bad_inputs import make_dataset

    from elastimap.dataset import io

    ds = make_dataset(tmp_path / "ds", n=20)
    before = snapshot(tmp_path)

    def read_only(*a, **k):  # what a read-only mount answers (root passes permission checks)
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(io, "compact", read_only)
    code, out, err = invoke("dataset", ["compact", str(ds)])
    assert_refused(code, out, err, ("Read-only",))
    assert snapshot(tmp_path) == before


def test_sweep_on_a_full_disk_is_one_line_and_leaves_no_lock(tmp_path, monkeypatch):
    import errno

    from elastimap.dataset import io

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(io, "write_manifest", full)
    out = tmp_path / "sw"
    args = ["run", "--solver", "synthetic", "--mesh", "tiny", "--n", "2", "--jobs", "1", "--no-progress"]
    code, o, e = invoke("sweep", [*args, "--out", str(out)])
    assert_refused(code, o, e, ("--out",))
    assert "No space left" in e and not (out / io.LOCK).exists()


GAP = ["--backend", "toy", "--cache", "none", "--no-progress"]
GAP_CASES = [
    (["synth", *GAP, "--n", "4", "--frames", "2", "--mesh", "tiny", "--out", "S2", "--cache", "afile"], "--cache"),
    (["synth", *GAP, "--n", "4", "--frames", "2", "--mesh", "tiny", "--out", "S2", "--jobs", "99999"], "--jobs"),
    (["synth", *GAP, "--n", "4", "--frames", "2", "--mesh", "tiny", "--out", "S2", "--seed", "-1"], "--seed"),
    (["selftest", *GAP, "--seed", "-1"], "--seed"),
    (["diagnose", *GAP, "--no-inverse", "--measured", "{S}", "--out", "dg", "--seed", "-1"], "--seed"),
    (["diagnose", *GAP, "--no-inverse", "--measured", "{S}", "--out", "dg", "--effects", "nope"], "--effects"),
]


@pytest.fixture(scope="module")
def measured_set(tmp_path_factory):
    s = tmp_path_factory.mktemp("gap") / "S"
    assert invoke("gap", ["synth", *GAP, "--n", "4", "--frames", "2", "--mesh", "tiny", "--out", str(s)])[0] == 0
    return s


@pytest.mark.parametrize(("args", "flag"), GAP_CASES, ids=[f"{a[0]}{f}" for a, f in GAP_CASES])
def test_gap_refuses_before_work(args, flag, measured_set, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("a file")
    before = snapshot(tmp_path)
    code, out, err = invoke("gap", [a.replace("{S}", str(measured_set)) for a in args])
    assert_refused(code, out, err, (flag,))
    assert snapshot(tmp_path) == before


def test_calibrate_reads_fem_features_from_a_sweep_folder(tmp_path, monkeypatch):
    """docs/errors.md and --help say --fem-features takes a sweep's folder; click refused folders."""
    from elastimap.camera import calibration as C
    from elastimap.dataset.phantoms import read_phantoms

    ds = tmp_path / "ds"
    args = ["run", "--solver", "synthetic", "--n", "2", "--phantoms", "--mesh", "tiny", "--jobs", "1", "--no-progress"]
    code, _, err = invoke("sweep", [*args, "--out", str(ds)])
    assert code == 0, err
    fem = C.fem_features_from_csv(ds, read_phantoms())
    assert fem.shape == (9, 3)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "empty-sweep").mkdir()
    code, out, err = invoke("calibrate", ["--fem-features", str(tmp_path / "empty-sweep"), "--out", "c.json"])
    assert_refused(code, out, err, ("--fem-features",))
    assert "is a directory" not in err
