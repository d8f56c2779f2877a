"""Identifiability helpers and the image-based inverse, on SYNTHETIC arrays only."""

from __future__ import annotations

import numpy as np
import pytest

from elastimap.identify.image_model import ImageModel, fit_image_model, run_image_validation
from elastimap.identify.measure import Data, ShapePCA, add_image_noise, image_inputs
from elastimap.workflows.studies import STUDIES


def _synthetic_data(n: int = 48, seed: int = 0, phantoms: int = 6) -> Data:
    """SYNTHETIC lesions: a Gaussian bump whose width follows d, depth-damped amplitude, E saturating."""
    rng = np.random.default_rng(seed)
    d = rng.uniform(3, 12, n)
    h = rng.uniform(4, 12, n)
    E = np.exp(rng.uniform(np.log(10), np.log(200), n))
    y, x = np.mgrid[0:12, 0:12] * 0.5
    r2 = x.ravel() ** 2 + y.ravel() ** 2
    amp = 1e-3 * d**2 / h * (E / (E + 20))
    width = 0.5 * d + 0.3 * h
    images = amp[:, None] * np.exp(-r2[None] / (2 * width[:, None] ** 2))
    feats = np.column_stack([amp, images.sum(1), (images > 0.5 * amp[:, None]).sum(1) + 1.0])
    tags = np.array([f"phantom:p{i}" if i < phantoms else "design" for i in range(n)])
    ids = np.array([f"s{i:04d}" for i in range(n)])
    return Data(
        theta=np.column_stack([d, h, E]),
        features=feats,
        images=images,
        dforce=amp * 100,
        force_ref=np.full(n, 1400.0),
        tags=tags,
        ids=ids,
        shape=(12, 12),
        pixel=0.5,
        source="SYNTHETIC",
    )


def test_shape_pca_separates_amplitude_from_shape():
    data = _synthetic_data()
    pca = ShapePCA.fit(data.images, k=4)
    Z = pca.transform(data.images)
    assert Z.shape == (data.n, 4)
    np.testing.assert_allclose(Z[:, 0], np.log(data.images.max(1)), rtol=1e-12)
    # scaling an image changes only ln(peak), never the shape scores
    Z2 = pca.transform(3.0 * data.images)
    np.testing.assert_allclose(Z2[:, 0], Z[:, 0] + np.log(3.0), rtol=1e-12)
    np.testing.assert_allclose(Z2[:, 1:], Z[:, 1:], atol=1e-12)
    assert np.all(np.diff(pca.explained) <= 1e-15) and pca.explained.sum() <= 1 + 1e-12
    back = ShapePCA.from_json(pca.to_json())
    np.testing.assert_allclose(back.transform(data.images), Z)
    F = image_inputs(data.images, pca, data.dforce, data.force_ref)
    np.testing.assert_allclose(F[:, -1], 100 * data.dforce / data.force_ref)


def test_relative_image_noise_scales_with_each_peak():
    data = _synthetic_data(n=200)
    noisy = add_image_noise(data.images, 0.01, np.random.default_rng(1))
    ratio = (noisy - data.images).std(axis=1) / data.images.max(axis=1)
    assert abs(ratio.mean() - 0.01) < 0.001
    assert add_image_noise(data.images, 0.0, np.random.default_rng(1)) is not None


def test_image_validation_rows_match_the_training_table_layout():
    from elastimap.training.experiment import TrainConfig

    data = _synthetic_data()
    cfg = TrainConfig(hidden=((6, "tansig"),), epochs=30, progress=False)
    r = run_image_validation(data, "scg", "hov", 3, cfg, seed=0, k=4, image_noise=0.01)
    row = r.row
    assert row["algo"] == "scg-image" and row["validate"] == "hov" and row["n_test_per_repeat"] == 6
    for m in ("mse100", "mre", "rmse"):
        for t in "dhE":
            assert np.isfinite(row[f"{m}_{t}_mean"])
    # the network learns something: d from a bump whose width follows d
    assert row["mre_d_mean"] < 40.0
    pred = r.extra["pred"]
    assert pred.shape == (3, data.n, 3) and np.isnan(pred[:, ~r.extra["test"]]).all()


def test_image_model_save_load_predict(tmp_path):
    from elastimap.training.experiment import TrainConfig

    data = _synthetic_data()
    model = fit_image_model(
        data, "scg", repeats=2, cfg=TrainConfig(hidden=((6, "tansig"),), epochs=20, progress=False), k=4
    )
    path = model.save(str(tmp_path / "m"))
    back = ImageModel.load(path)
    np.testing.assert_allclose(back.predict(data.images[:5]), model.predict(data.images[:5]), rtol=1e-10)
    assert back.predict(data.images[:5].reshape(5, 12, 12)).shape == (2, 5, 3)
    from elastimap.errors import UserError

    with pytest.raises(UserError, match="pixels"):
        back.predict(np.ones((2, 7)))


@pytest.mark.parametrize(
    "args,param",
    [
        (["--k", "1"], "--k"),
        (["--algo", "adam"], "--algo"),
        (["--validate", "kfold"], "--validate"),
        (["--data", "/nonexistent"], "--data"),
    ],
)
def test_cli_bad_options_exit_2(args, param):
    import subprocess
    import sys

    r = subprocess.run(
        [sys.executable, "-m", "elastimap.workflows.studies.image_model", *args], capture_output=True, text=True
    )
    assert r.returncode == 2
    assert r.stderr.startswith("error: ") and param in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_log_e_target_scores_on_E_and_round_trips(tmp_path):
    """``log_e``: the network learns ln E, the table is still scored on E (same linear scaling)."""
    from elastimap.training.experiment import TrainConfig

    data = _synthetic_data()
    cfg = TrainConfig(hidden=((6, "tansig"),), epochs=30, progress=False)
    lin = run_image_validation(data, "scg", "hov", 2, cfg, seed=0, k=4)
    log = run_image_validation(data, "scg", "hov", 2, cfg, seed=0, k=4, log_e=True)
    assert log.row["algo"] == "scg-image-lnE" and log.row["log_e"] is True
    # identical d, h targets and scaling: the MSE x 100 of d is computed the same way in both
    p = log.extra["pred"][:, log.extra["test"]]
    assert np.all(p[..., 2] > 0)
    t = data.theta[log.extra["test"]]
    mre_E = 100 * np.mean(np.abs(p[..., 2] - t[:, 2]) / t[:, 2], axis=1)
    np.testing.assert_allclose(mre_E.mean(), log.row["mre_E_mean"], rtol=1e-9)
    Et = data.theta[~log.extra["test"], 2]  # linear [-1, 1] scaling over the training rows
    s = lambda e: 2 * (e - Et.min()) / (Et.max() - Et.min()) - 1  # noqa: E731
    mse = 100 * np.mean((s(p[..., 2]) - s(t[:, 2])) ** 2, axis=1)
    np.testing.assert_allclose(mse.mean(), log.row["mse100_E_mean"], rtol=1e-9)
    assert np.isfinite(lin.row["mse100_E_mean"]) and np.isfinite(log.row["mse100_E_mean"])
    model = fit_image_model(data, "scg", repeats=2, cfg=cfg, k=4, log_e=True)
    back = ImageModel.load(model.save(str(tmp_path / "m")))
    assert back.log_e
    y = back.predict(data.images[:4])
    np.testing.assert_allclose(y, model.predict(data.images[:4]), rtol=1e-10)
    assert np.all(y[..., 2] > 0)


def test_shared_noise_predictions_put_one_noisy_image_through_every_network():
    from elastimap.training.experiment import TrainConfig

    data = _synthetic_data(n=30, phantoms=3)
    cfg = TrainConfig(hidden=((4, "tansig"),), epochs=5, progress=False)
    r = run_image_validation(data, "scg", "loocv", 2, cfg, seed=0, k=3, image_noise=0.02)
    ps, p = r.extra["pred_shared_noise"], r.extra["pred"]
    assert ps.shape == p.shape == (2, 30, 3) and np.isfinite(ps).all()
    assert not np.allclose(ps, p)  # a different (single) noise draw than each repeat's own
    assert run_image_validation(data, "scg", "loocv", 1, cfg, k=3, image_noise=0.0).extra["pred_shared_noise"] is None


@pytest.mark.parametrize("name", sorted(STUDIES))
def test_every_study_is_a_click_main_with_help(name):
    """The studies live in elastimap.workflows.studies, each a click command ``main`` with -h."""
    import importlib

    import click
    from click.testing import CliRunner

    mod = importlib.import_module(f"elastimap.workflows.studies.{name}")
    assert isinstance(mod.main, click.Command)
    r = CliRunner().invoke(mod.main, ["-h"])
    assert r.exit_code == 0 and "Usage" in r.output
    if name == "crbmap":
        assert "--install" in r.output
