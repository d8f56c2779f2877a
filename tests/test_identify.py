"""Identifiability helpers and the image-based inverse (issue 7), on SYNTHETIC arrays only."""

from __future__ import annotations

import numpy as np
import pytest

from identify.imagenet import ImageModel, fit_image_model, run_image_validation
from identify.measure import Data, ShapePCA, add_image_noise, image_inputs


def _synthetic_data(n: int = 48, seed: int = 0, phantoms: int = 6) -> Data:
    """SYNTHETIC lesions: a Gaussian bump whose width follows d, depth-damped amplitude, E saturating."""
    rng = np.random.default_rng(seed)
    d = rng.uniform(3, 12, n)
    h = rng.uniform(4, 12, n)
    E = np.exp(rng.uniform(np.log(10), np.log(200), n))
    y, x = np.mgrid[0:12, 0:12] * 0.5
    r2 = x.ravel() ** 2 + y.ravel() ** 2
    amp = 1e-3 * d ** 2 / h * (E / (E + 20))
    width = 0.5 * d + 0.3 * h
    images = amp[:, None] * np.exp(-r2[None] / (2 * width[:, None] ** 2))
    feats = np.column_stack([amp, images.sum(1), (images > 0.5 * amp[:, None]).sum(1) + 1.0])
    tags = np.array(["phantom:p%d" % i if i < phantoms else "design" for i in range(n)])
    ids = np.array([f"s{i:04d}" for i in range(n)])
    return Data(theta=np.column_stack([d, h, E]), features=feats, images=images, dforce=amp * 100,
                force_ref=np.full(n, 1400.0), tags=tags, ids=ids, shape=(12, 12), pixel=0.5, source="SYNTHETIC")


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
    from training.experiment import TrainConfig

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
    from training.experiment import TrainConfig

    data = _synthetic_data()
    model = fit_image_model(data, "scg", repeats=2, cfg=TrainConfig(hidden=((6, "tansig"),), epochs=20,
                                                                    progress=False), k=4)
    path = model.save(str(tmp_path / "m"))
    back = ImageModel.load(path)
    np.testing.assert_allclose(back.predict(data.images[:5]), model.predict(data.images[:5]), rtol=1e-10)
    assert back.predict(data.images[:5].reshape(5, 12, 12)).shape == (2, 5, 3)
    from elastimap.errors import UserError
    with pytest.raises(UserError, match="pixels"):
        back.predict(np.ones((2, 7)))


@pytest.mark.parametrize("args,param", [(["--k", "1"], "--k"), (["--algo", "adam"], "--algo"),
                                        (["--validate", "kfold"], "--validate"),
                                        (["--data", "/nonexistent"], "--data")])
def test_cli_bad_options_exit_2(args, param):
    import subprocess
    import sys
    r = subprocess.run([sys.executable, "-m", "identify.imagenet", *args], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.startswith("error: ") and param in r.stderr and len(r.stderr.strip().splitlines()) == 1
