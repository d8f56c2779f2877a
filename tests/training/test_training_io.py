"""Training stage: data loading and errors, ensemble save/load, validation runner, CLI.

All tables here are the SYNTHETIC analytic toy table, not FEM results.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
import torch

from elastimap.cli_util import run
from elastimap.dataset import io as dio
from elastimap.errors import UserError
from elastimap.training.api import fit_ensemble
from elastimap.training.cli import cli as train_cli
from elastimap.training.data import data_hash, load_samples, prepare, synthetic_table
from elastimap.training.experiment import TrainConfig, run_validation, summarize
from elastimap.training.model import Ensemble

torch.set_num_threads(1)
SMALL = dict(hidden=(5, 3), epochs=20)


def write_samples(df: pd.DataFrame, path) -> None:
    """Write rows as a sample-dataset Parquet file (the schema the one reader checks)."""
    dio.write_atomic(dio.to_table(df.to_dict("records")), path)


@pytest.fixture(scope="module")
def toy():
    return synthetic_table(60, seed=4, n_failed=3)


def test_import_does_not_pull_solver():
    code = (
        "import sys, elastimap.training, elastimap.training.api, elastimap.training.model, elastimap.training.cli, elastimap.training.experiment;"
        "heavy = ('dolfinx', 'gmsh', 'elastimap.solver.api', 'elastimap.solver.fem', 'elastimap.solver.geometry', 'elastimap.sweep');"
        "bad = [m for m in sys.modules if m.startswith(heavy)];"
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_load_directory_of_parquet_and_failed_rows(tmp_path, toy):
    d = tmp_path / "ds"
    d.mkdir()
    write_samples(toy.iloc[:30], d / "part-0.parquet")
    write_samples(toy.iloc[30:], d / "part-1.parquet")
    s = load_samples(str(d))
    assert s.n == 60 and s.n_failed == 3 and s.n_total == 63
    assert "3 failed sample(s) excluded" in s.report() and "9 calibration-phantom" in s.report()
    assert list(s.df["sample_id"]) == sorted(s.df["sample_id"])
    # row order in the files does not change the hash
    write_samples(toy.iloc[::-1], tmp_path / "rev.parquet")
    assert data_hash(load_samples(str(tmp_path / "rev.parquet")).df) == data_hash(s.df)


def test_bad_data_errors(tmp_path, toy):
    p = tmp_path / "noO2.parquet"
    toy.drop(columns=["O2"]).to_parquet(p)  # a foreign file (pandas, no sample schema)
    with pytest.raises(UserError, match="noO2.parquet is not an elastimap sample file"):
        load_samples(str(p))
    with pytest.raises(UserError, match="does not exist"):
        load_samples(str(tmp_path / "missing"))
    (tmp_path / "junk.parquet").write_text("not parquet")
    with pytest.raises(UserError, match="junk.parquet is not a readable Parquet file"):
        load_samples(str(tmp_path / "junk.parquet"))
    nan = toy.copy()
    nan.loc[5, "O3"] = np.nan
    with pytest.raises(UserError, match=r"1 'ok' row\(s\).*NaN/inf in O3"):
        prepare(nan)
    with pytest.raises(UserError, match="too few samples for the network"):
        fit_ensemble(toy.iloc[:40], repeats=1, epochs=1)  # 393 weights, 40 usable rows
    allfail = toy.assign(status="failed")
    with pytest.raises(UserError, match="no usable samples"):
        prepare(allfail)


def test_fit_save_load_roundtrip(tmp_path, toy):
    ens = fit_ensemble(toy, algo="lm", repeats=3, seed=1, **SMALL)
    X = toy[toy.status == "ok"][["O1", "O2", "O3"]].to_numpy()[:7]
    Y = ens.predict(X)
    assert Y.shape == (3, 7, 3)
    d = ens.save(str(tmp_path / "model"))
    assert sorted(os.listdir(d)) == ["ensemble.safetensors", "model.json"]
    with open(os.path.join(d, "ensemble.safetensors"), "rb") as f:
        assert b"pickle" not in f.read(200)
    back = Ensemble.load(d)
    np.testing.assert_array_equal(back.predict(X), Y)
    assert back.feature_names == ("O1", "O2", "O3") and back.target_names == ("d", "h", "E")
    assert back.feature_range.shape == (2, 3) and back.target_range.shape == (2, 3)
    ok = toy[toy.status == "ok"]
    np.testing.assert_allclose(back.feature_range, [ok[["O1", "O2", "O3"]].min(), ok[["O1", "O2", "O3"]].max()])
    meta = json.load(open(os.path.join(d, "model.json")))
    assert meta["training"]["data_sha256"] == data_hash(prepare(toy).df)
    assert meta["training"]["n_failed_excluded"] == 3 and meta["units"]["E"] == "kPa"
    assert meta["scaling"]["method"] == "mapminmax"
    # the networks learnt something: ensemble mean beats predicting the mean target
    T = ok[["d", "h", "E"]].to_numpy()[:7]
    err = np.abs(Y.mean(0) - T).mean(0)
    assert (err < np.abs(T - ok[["d", "h", "E"]].to_numpy().mean(0)).mean(0)).all()
    with pytest.raises(UserError):
        back.predict(np.ones((2, 4)))
    with pytest.raises(UserError, match="not a trained model"):
        Ensemble.load(str(tmp_path))
    # torch-side forward agrees with the NumPy predict
    from elastimap.training.net import forward
    from elastimap.training.problem import mapminmax_apply, mapminmax_reverse

    Xs = torch.as_tensor(mapminmax_apply(X, back.x_min, back.x_max))[None].expand(3, -1, -1)
    Yt = forward(torch.as_tensor(back.theta), Xs, back.arch).numpy()
    np.testing.assert_allclose(mapminmax_reverse(Yt, back.y_min, back.y_max), Y, rtol=1e-12)


def test_literal_variant_trains_and_roundtrips(tmp_path, toy):
    ens = fit_ensemble(toy, algo="scg", repeats=2, epochs=5, hidden="4,3,2:purelin")
    back = Ensemble.load(ens.save(str(tmp_path / "m")))
    assert back.arch.hidden == ((4, "tansig"), (3, "tansig"), (2, "purelin"))
    np.testing.assert_allclose(
        back.predict(toy[["O1", "O2", "O3"]].to_numpy()[:3]), ens.predict(toy[["O1", "O2", "O3"]].to_numpy()[:3])
    )


def test_validation_runner_metrics(toy):
    s = prepare(toy)
    cfg = TrainConfig(hidden=((5, "tansig"), (3, "tansig")), epochs=10, progress=False)
    hov = run_validation(s, "scg", "hov", 2, cfg, seed=0)
    assert hov.row["n_test_per_repeat"] == 9 and hov.row["n_train"] == 51 and hov.row["trainings"] == 2
    loo = run_validation(s, "lm", "loocv", 2, cfg, seed=0)
    assert loo.row["trainings"] == 120 and loo.row["n_test_per_repeat"] == 60
    for r in (hov, loo):
        for m in ("mse100", "mre", "rmse"):
            assert r.per_repeat[m].shape == (2, 3) and np.isfinite(r.per_repeat[m]).all()
            assert r.row[f"{m}_d_lo"] <= r.row[f"{m}_d_mean"] <= r.row[f"{m}_d_hi"]
    # test split instead of phantoms
    sp = run_validation(s, "scg", "hov", 1, cfg, seed=0, test_split=0.25)
    assert sp.row["n_test_per_repeat"] == 15
    # noise is applied and the run stays finite
    noisy = TrainConfig(hidden=((5, "tansig"),), epochs=5, feature_noise=0.01, progress=False)
    assert np.isfinite(run_validation(s, "scg", "hov", 2, noisy).per_repeat["mse100"]).all()
    st = summarize(np.array([1.0, 2.0, 3.0]))
    assert st["mean"] == 2 and st["ci_lo"] < 2 < st["ci_hi"] and st["lo"] == pytest.approx(1.05)


def _cli(args, capsys):
    with pytest.raises(SystemExit) as exc:
        run(train_cli, args=args, prog_name="train")
    cap = capsys.readouterr()
    return exc.value.code, cap.out, cap.err


@pytest.mark.parametrize(
    "args, msg",
    [
        (["--synthetic", "60", "--algo", "adam"], "--algo"),
        (["--synthetic", "60", "--validate", "kfold"], "--validate"),
        (["--synthetic", "60", "--hidden", "25,x"], "--hidden"),
        (["--synthetic", "60", "--repeats", "0"], "--repeats"),
        (["--synthetic", "60", "--workers", "-1"], "--workers"),
        (["--synthetic", "60", "--feature-noise", "-1"], "--feature-noise"),
        (["--synthetic", "60", "--test-split", "1.5"], "--test-split"),
        ([], "--data"),
        (["--data", "/nonexistent/x.parquet"], "does not exist"),
        (["--synthetic", "60", "--bogus"], "no such option"),
    ],
)
def test_cli_bad_options_exit_2(args, msg, capsys):
    code, out, err = _cli(args + ["--no-progress"], capsys)
    assert code == 2
    assert err.startswith("error: ") and msg.lower() in err.lower() and len(err.strip().splitlines()) == 1


def test_cli_run_writes_tables_curves_and_models(tmp_path, toy, capsys):
    data = tmp_path / "toy.parquet"
    write_samples(toy, data)
    out = tmp_path / "out"
    code, stdout, err = _cli(
        [
            "--data",
            str(data),
            "--algo",
            "all",
            "--validate",
            "hov",
            "--repeats",
            "2",
            "--epochs",
            "8",
            "--hidden",
            "5,3",
            "--out",
            str(out),
            "--no-progress",
            "--threads",
            "1",
        ],
        capsys,
    )
    assert code == 0, err
    files = sorted(os.listdir(out))
    for f in (
        "results.csv",
        "results.md",
        "run.json",
        "curves-lm-hov.png",
        "curves-scg-hov.png",
        "model-lm",
        "model-scg",
    ):
        assert f in files
    tab = pd.read_csv(out / "results.csv")
    assert list(tab["algo"]) == ["lm", "scg"] and (tab["repeats"] == 2).all()
    assert "| LM | HOV | 2 |" in stdout and "MSE×100 d (%)" in stdout
    assert "3 failed sample(s) excluded" in err
    ens = Ensemble.load(str(out / "model-scg"))
    assert ens.n_members == 2 and ens.meta["n_train"] == 51  # HOV only: phantom rows held out


def test_files_vanishing_during_read_are_read_again(tmp_path, toy, monkeypatch):
    """A running sweep's compaction replaces files while training reads: the one reader lists again."""
    d = tmp_path / "ds"
    d.mkdir()
    write_samples(toy, d / "r-part-0.parquet")
    real = dio._meta
    calls = []

    def racing(f):
        if not calls:
            calls.append(f)
            os.replace(d / "r-part-0.parquet", d / "b-part-0.parquet")  # compaction meanwhile
        return real(f)

    monkeypatch.setattr(dio, "_meta", racing)
    assert load_samples(str(d)).n == 60
