"""Nothing lost, nothing silently mixed: output folders, the one sample reader, model files.

Each test reproduces one way a user's data was lost or mixed (or an answer was wrong) and
checks the fix; the property-based tests (hypothesis) throw random values at the parameter
checks and random damage at the readers of measured data, sample datasets and model files,
which must answer with a :class:`UserError` (one line) or a correct result, never anything else.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_bad_inputs import SYNTH, invoke, make_dataset, make_model, snapshot

from elastimap.constraints import check_range
from elastimap.errors import UserError

# its module fixture is costly: under pytest-xdist (make test) this module runs on one worker
pytestmark = pytest.mark.xdist_group("test_data_safety")

REPO = Path(__file__).resolve().parents[2]
ROOMS = ("solver", "sweep", "dataset", "training", "camera", "gap", "identify", "elastimap", "workflows")


# ----------------------------------------------------------------------------- gap synth --out
def test_gap_synth_refuses_existing_data_and_never_replaces_real_data(tmp_path):
    m = tmp_path / "M"
    assert invoke("gap", ["synth", "--out", str(m), *SYNTH])[0] == 0
    (m / "stray.txt").write_text("from before")
    before = snapshot(m)
    code, _, err = invoke("gap", ["synth", "--out", str(m), *SYNTH, "--seed", "3"])
    assert code == 2 and "--overwrite" in err and snapshot(m) == before
    # a file the user added is never deleted, not even with --overwrite (issue 40: it was)
    code, _, err = invoke("gap", ["synth", "--out", str(m), *SYNTH, "--seed", "3", "--overwrite"])
    assert code == 2 and "stray.txt" in err and snapshot(m) == before
    (m / "stray.txt").unlink()
    # a synthetic dataset is replaced whole with --overwrite (nothing of the old one remains)
    (m / "synthetic_difference_old.npy").write_bytes(b"")
    code, out, err = invoke("gap", ["synth", "--out", str(m), *SYNTH, "--seed", "3", "--overwrite"])
    assert code == 0, err
    assert not (m / "synthetic_difference_old.npy").exists() and (m / "measured.json").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging folder left
    # real data: never, not even with --overwrite
    side = json.loads((m / "measured.json").read_text())
    side["synthetic"] = False
    (m / "measured.json").write_text(json.dumps(side))
    before = snapshot(m)
    for extra in ([], ["--overwrite"]):
        code, _, err = invoke("gap", ["synth", "--out", str(m), *SYNTH, *extra])
        assert code == 2 and "real" in err and len(err.strip().splitlines()) == 1
    assert snapshot(m) == before


# ----------------------------------------------------------------------------- one sample reader
def _inspect_rows(path) -> int:
    code, out, err = invoke("dataset", ["inspect", str(path), "--json"])
    assert code == 0, err
    return json.loads(out)["rows"]


def test_training_reads_what_inspect_reads(tmp_path):
    from elastimap.training.data import load_samples

    ds = make_dataset(tmp_path / "ds", n=20)
    make_dataset(ds / "older-sweep", n=12, seed=1, prefix="old")  # another sweep in a subfolder
    # an interrupted compaction: its batch file landed, its inputs were not yet removed
    first = sorted(ds.glob("r-*.parquet"))[0]
    shutil.copy(first, ds / ("b-" + first.name[2:]))
    assert _inspect_rows(ds) == 20
    s = load_samples(str(ds))
    assert s.n == 20 and s.n_failed == 0 and not s.df["sample_id"].str.startswith("old").any()
    code, _, err = invoke(
        "train",
        [
            "--data",
            str(ds),
            "--repeats",
            "1",
            "--epochs",
            "2",
            "--hidden",
            "3",
            "--no-progress",
            "--out",
            str(tmp_path / "tr"),
            "--no-model",
        ],
    )
    assert code == 0, err
    assert "20 usable samples" in err
    assert json.loads((tmp_path / "tr" / "run.json").read_text())["n_samples"] == 20


def test_foreign_parquet_is_refused_naming_it(tmp_path):
    import pandas as pd

    from elastimap.camera.calibration import fem_features_from_csv
    from elastimap.dataset.phantoms import read_phantoms
    from elastimap.training.data import load_samples

    ds = make_dataset(tmp_path / "ds", n=12)
    pd.DataFrame(
        {"O1": [1.0], "O2": [2.0], "O3": [3.0], "d": [1.0], "h": [1.0], "E": [1.0], "status": ["ok"]}
    ).to_parquet(ds / "zz-foreign.parquet")
    for read in (
        lambda: load_samples(str(ds)),
        lambda: fem_features_from_csv(ds, read_phantoms(None, min_rows=3, why="to fit a calibration line")),
    ):
        with pytest.raises(UserError, match="zz-foreign.parquet"):
            read()
    code, _, err = invoke("dataset", ["inspect", str(ds)])
    assert code == 2 and "zz-foreign.parquet" in err


def test_no_other_sample_reader_in_the_rooms():
    """Sample datasets are read only by elastimap.dataset.io (no recursive pyarrow.dataset scan)."""
    hits = []
    for room in ROOMS:
        for f in (REPO / room).rglob("*.py"):
            text = f.read_text()
            if re.search(r"import pyarrow\.dataset|pyarrow\.dataset\.dataset|pads\.dataset", text):
                hits.append(str(f.relative_to(REPO)))
    assert hits == []


# ----------------------------------------------------------------------------- train --out
TRAIN = ["--synthetic", "30", "--repeats", "1", "--epochs", "2", "--hidden", "3", "--no-progress"]


def test_train_out_holds_exactly_one_run(tmp_path):
    out = tmp_path / "run"
    assert invoke("train", [*TRAIN, "--algo", "all", "--out", str(out)])[0] == 0
    assert {p.name for p in out.iterdir()} >= {"model-lm", "model-scg", "run.json"}
    before = snapshot(out)
    code, _, err = invoke("train", [*TRAIN, "--out", str(out)])
    assert code == 2 and "--overwrite" in err and snapshot(out) == before
    code, _, err = invoke("train", [*TRAIN, "--out", str(out), "--overwrite"])
    assert code == 0, err
    names = {p.name for p in out.iterdir()}
    assert "model-scg" in names and "model-lm" not in names  # nothing of the earlier run is left
    assert json.loads((out / "run.json").read_text())["algo"] == ["scg"]
    assert [p.name for p in tmp_path.iterdir()] == ["run"]  # no staging folder left


def test_failed_train_run_leaves_nothing(tmp_path):
    out = tmp_path / "run"
    # fails inside the validation (no rows left for training), after the run has started
    code, _, err = invoke(
        "train",
        [
            "--synthetic",
            "12",
            "--repeats",
            "1",
            "--epochs",
            "2",
            "--hidden",
            "3",
            "--no-progress",
            "--val-fraction",
            "0.95",
            "--out",
            str(out),
        ],
    )
    assert code == 2, err
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- outputs
def test_write_or_fallback_keeps_the_result(tmp_path, capsys):
    from elastimap.outputs import write_or_fallback

    def write(path):
        if "gone" in str(path):
            raise PermissionError(13, "Permission denied")
        Path(path).write_text("the result")

    with pytest.raises(UserError, match="saved to") as ei:
        write_or_fallback(write, tmp_path / "gone" / "x.csv", "--csv")
    fb = re.search(r"saved to (\S+) instead", str(ei.value)).group(1)
    assert Path(fb).read_text() == "the result"
    os.remove(fb)


def test_gap_diagnose_keeps_the_report_when_out_fails_late(tmp_path, monkeypatch):
    from elastimap.gap import report

    m = tmp_path / "M"
    assert invoke("gap", ["synth", "--out", str(m), *SYNTH])[0] == 0
    real = report.write
    calls = []

    def flaky(res, out):
        calls.append(str(out))
        if len(calls) == 1:
            raise PermissionError(13, "Permission denied", str(out))
        return real(res, out)

    monkeypatch.setattr(report, "write", flaky)
    code, _, err = invoke(
        "gap",
        [
            "diagnose",
            "--measured",
            str(m),
            "--backend",
            "toy",
            "--cache",
            "none",
            "--no-inverse",
            "--no-progress",
            "--effects",
            "friction",
            "--out",
            str(tmp_path / "dg"),
        ],
    )
    assert code == 2 and len(err.strip().splitlines()) == 1
    fb = Path(calls[1])
    assert str(fb) in err and (fb / "report.md").exists()
    shutil.rmtree(fb)


def test_solve_vtx_onto_a_file_is_refused_before_solving(tmp_path):
    f = tmp_path / "u.bp"
    f.write_text("a file")
    code, _, err = invoke("solve", ["--mesh", "tiny", "--vtx", str(f)])
    assert code == 2 and "--vtx" in err and f.read_text() == "a file"


# ----------------------------------------------------------------------------- force / geometry limits
def test_force_control_respects_the_travel_limit(tmp_path):
    code, out, err = invoke("solve", ["--mesh", "tiny", "--force", "1e9"])
    assert code == 2 and "force" in err and "plate travel" in err, err
    assert out == ""


@pytest.mark.parametrize("args", [["--thickness", "1e6"], ["--layers", "1e6:300"], ["--pixel", "1e-5"]])
def test_unreasonable_geometry_refused_up_front(args):
    import time

    t0 = time.perf_counter()
    code, _, err = invoke("solve", ["--mesh", "tiny", *args])
    assert code == 2 and time.perf_counter() - t0 < 10, err


# ----------------------------------------------------------------------------- model files
@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    return make_model(tmp_path_factory.mktemp("m") / "model")


def test_model_sidecar_records_the_weights_hash(model_dir):
    import hashlib

    from elastimap.training.model import Ensemble

    meta = json.loads((model_dir / "model.json").read_text())
    assert meta["weights_sha256"] == hashlib.sha256((model_dir / "ensemble.safetensors").read_bytes()).hexdigest()
    Ensemble.load(str(model_dir))


def test_model_save_is_atomic(model_dir, tmp_path, monkeypatch):
    import safetensors.numpy

    from elastimap.training.model import Ensemble

    ens = Ensemble.load(str(model_dir))
    dst = tmp_path / "m"
    ens.save(str(dst))
    (dst / "stray").write_text("old")
    ens.save(str(dst))  # replaces the folder whole
    assert sorted(p.name for p in dst.iterdir()) == ["ensemble.safetensors", "model.json"]
    before = snapshot(tmp_path)

    def boom(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(safetensors.numpy, "save_file", boom)
    with pytest.raises(OSError):
        ens.save(str(dst))
    assert snapshot(tmp_path) == before  # old model intact, no temporary folder left


def test_nan_weights_without_hash_are_refused(model_dir, tmp_path):
    from safetensors.numpy import load_file, save_file

    from elastimap.training.model import Ensemble

    d = tmp_path / "m"
    shutil.copytree(model_dir, d)
    t = load_file(str(d / "ensemble.safetensors"))
    t["layer0.bias"][0, 0] = np.nan
    save_file(t, str(d / "ensemble.safetensors"))
    meta = json.loads((d / "model.json").read_text())
    del meta["weights_sha256"]  # as written before hashes were recorded
    (d / "model.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match="ensemble.safetensors: holds NaN"):
        Ensemble.load(str(d))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(which=st.sampled_from(["ensemble.safetensors", "model.json"]), data=st.data())
def test_damaged_model_files_load_or_refuse(model_dir, tmp_path_factory, which, data):
    """Random damage (truncation, flipped bytes, appended junk) to either file: the load either
    refuses with a UserError naming a file of the model, or gives exactly the original model."""
    from elastimap.training.model import Ensemble

    d = tmp_path_factory.mktemp("dmg") / "m"
    shutil.copytree(model_dir, d)
    f = d / which
    raw = bytearray(f.read_bytes())
    kind = data.draw(st.sampled_from(["truncate", "flip", "append"]))
    if kind == "truncate":
        raw = raw[: data.draw(st.integers(0, len(raw) - 1))]
    elif kind == "flip":
        for _ in range(data.draw(st.integers(1, 8))):
            i = data.draw(st.integers(0, len(raw) - 1))
            raw[i] = data.draw(st.integers(0, 255))
    else:
        raw += data.draw(st.binary(min_size=1, max_size=64))
    f.write_bytes(bytes(raw))
    good = Ensemble.load(str(model_dir))
    try:
        ens = Ensemble.load(str(d))
    except UserError as exc:
        assert "\n" not in str(exc) and ("model.json" in str(exc) or "ensemble.safetensors" in str(exc))
        return
    np.testing.assert_array_equal(ens.theta, good.theta)
    x = good.feature_range.mean(axis=0, keepdims=True)
    np.testing.assert_allclose(ens.predict(x), good.predict(x))


# ----------------------------------------------------------------------------- parameter validation
finite_or_not = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-(10**6), 10**6))


@given(
    v=finite_or_not,
    lo=st.one_of(st.none(), st.floats(-1e6, 1e6)),
    hi=st.one_of(st.none(), st.floats(-1e6, 1e6)),
    lo_open=st.booleans(),
    hi_open=st.booleans(),
)
def test_check_range_accepts_exactly_the_interval(v, lo, hi, lo_open, hi_open):
    inside = math.isfinite(v)
    if lo is not None:
        inside &= v > lo if lo_open else v >= lo
    if hi is not None:
        inside &= v < hi if hi_open else v <= hi
    if inside:
        assert check_range("x", v, lo, hi, lo_open=lo_open, hi_open=hi_open) == float(v)
    else:
        with pytest.raises(UserError, match=r"^x: must be"):
            check_range("x", v, lo, hi, lo_open=lo_open, hi_open=hi_open)


@settings(max_examples=300, deadline=None)
@given(
    d=finite_or_not,
    h=finite_or_not,
    E=finite_or_not,
    tissue_E=finite_or_not,
    thickness=finite_or_not,
    delta=finite_or_not,
    force=st.one_of(st.none(), finite_or_not),
    pixel=finite_or_not,
)
def test_solve_params_validate_or_refuse(d, h, E, tissue_E, thickness, delta, force, pixel):
    """Any numbers: either a UserError naming a parameter, or parameters a mesh can be built for."""
    from elastimap.solver.params import (
        MAX_PIXELS,
        Discretisation,
        ImageSpec,
        Inclusion,
        Loading,
        SolveParams,
        Tissue,
        delta_limit,
    )

    p = SolveParams(
        inclusion=Inclusion(d=d, h=h, E=E),
        tissue=Tissue(E=tissue_E, thickness=thickness),
        loading=Loading(delta=delta, force=force),
        disc=Discretisation(mesh="tiny"),
        image=ImageSpec(pixel=pixel),
    )
    try:
        p.validate()
    except UserError as exc:
        assert "\n" not in str(exc) and exc.param
        return
    vals = [d, h, E, tissue_E, thickness, pixel] + ([delta] if force is None else [force])
    assert all(math.isfinite(v) and v > 0 for v in vals)
    assert thickness <= p.tissue.size and p.probe.size / pixel <= MAX_PIXELS + 1e-6
    assert force is not None or delta <= delta_limit(p)
    assert 0 < h - d / 2 and h + d / 2 < thickness


# ----------------------------------------------------------------------------- readers of measured data and datasets
@pytest.fixture(scope="module")
def measured_dir(tmp_path_factory):
    m = tmp_path_factory.mktemp("meas") / "M"
    assert invoke("gap", ["synth", "--out", str(m), *SYNTH])[0] == 0
    return m


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_measured_reader_loads_or_refuses(measured_dir, tmp_path_factory, data):
    """Random edits of a measured table's cells (numbers, text, blanks, NaN, duplicates) and of its
    sidecar: gap's reader gives a UserError of one line, or a dataset with positive d, h, E."""
    import pandas as pd

    from elastimap.gap import measured

    d = tmp_path_factory.mktemp("mm") / "M"
    shutil.copytree(measured_dir, d)
    df = pd.read_csv(d / "measured.csv", dtype=str)
    for _ in range(data.draw(st.integers(1, 4))):
        r = data.draw(st.integers(0, len(df) - 1))
        c = data.draw(st.sampled_from(list(df.columns)))
        df.loc[r, c] = data.draw(
            st.one_of(
                st.sampled_from(["", "nan", "-1", "0", "inf", "x", df.loc[0, c]]), st.floats(allow_nan=True).map(str)
            )
        )
    if data.draw(st.booleans()):
        df = df.drop(columns=[data.draw(st.sampled_from(list(df.columns)))])
    df.to_csv(d / "measured.csv", index=False)
    if data.draw(st.booleans()):
        (d / "measured.json").write_text(data.draw(st.sampled_from(["{", "[]", '{"kind": "x"}', "null"])))
    try:
        m = measured.load(d)
    except UserError as exc:
        assert "\n" not in str(exc)
        return
    assert np.isfinite(m.dhe).all() and (m.dhe > 0).all() and len(set(m.ids)) == len(m.ids)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_sample_reader_loads_or_refuses(tmp_path_factory, data):
    """Random damage to one file of a sample dataset: the one reader (and training through it)
    answers with a UserError naming that file, or with one row per sample id."""
    from elastimap.dataset import io as dio
    from elastimap.training.data import load_samples

    ds = make_dataset(tmp_path_factory.mktemp("ds") / "ds", n=20)
    f = data.draw(st.sampled_from(sorted(ds.glob("*.parquet"))))
    raw = bytearray(f.read_bytes())
    kind = data.draw(st.sampled_from(["truncate", "flip", "junk", "duplicate"]))
    if kind == "truncate":
        raw = raw[: data.draw(st.integers(0, len(raw) - 1))]
    elif kind == "flip":
        i = data.draw(st.integers(0, len(raw) - 1))
        raw[i] ^= data.draw(st.integers(1, 255))
    elif kind == "junk":
        raw = bytearray(data.draw(st.binary(max_size=200)))
    if kind == "duplicate":
        shutil.copy(f, ds / ("b-" + f.name[2:]))
    else:
        f.write_bytes(bytes(raw))
    for read in (lambda: dio.read_samples(ds, status=None), lambda: load_samples(str(ds)).df):
        try:
            df = read()
        except UserError as exc:
            assert "\n" not in str(exc) and f.name in str(exc)
            continue
        assert df["sample_id"].is_unique and len(df) <= 20
