"""The image-based inverse model: shape-PCA of the elasticity image (+ force) -> MLP -> (d, h, E).

Inputs per lesion (:func:`elastimap.identify.measure.image_inputs`): ``ln(peak)`` of the difference image,
the first ``K - 1`` PCA scores of the peak-normalised image (its *shape*) and, with ``force``,
``100 (force - force_ref) / force_ref``.  The network is the paper's MLP (``K -> 25 tansig ->
10 tansig -> 3 purelin``), trained by :mod:`training`'s batched LM / SCG
(:func:`elastimap.training.experiment.make_batch` / :func:`~elastimap.training.experiment.train_batch`), validated by
the same HOV (the 9 phantoms) / LOOCV x repeats, scored with the same metrics (MSE x 100 on the
network's mapminmax [-1, 1] targets, MRE %, RMSE), so a result is one more row of the training
table (``algo`` ``lm-image`` / ``scg-image``).

Differences from the feature MLP, all deliberate:

* the PCA basis is fitted on the noise-free images of the training rows (HOV: the non-test rows;
  LOOCV: all rows -- PCA sees no targets, and a 1-row difference in a 520-image basis is
  negligible; a per-fold basis would cost n SVDs);
* ``image_noise`` adds per-pixel Gaussian noise of ``image_noise x peak`` to every image, drawn
  once per *repeat* and shared by that repeat's LOOCV folds (the held-out row's draw is
  independent of the training rows' draws, as in the feature MLP), then projected on the basis.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch

from elastimap.errors import UserError
from elastimap.training.data import TARGETS, UNITS, prepare
from elastimap.training.experiment import (
    METRICS,
    TrainConfig,
    ValidationResult,
    make_batch,
    predict_scaled,
    rng_for,
    split_rows,
    summarize,
    train_batch,
)
from elastimap.training.model import Ensemble
from elastimap.training.net import Arch
from elastimap.training.problem import NetObjective, mapminmax_apply, mapminmax_fit, mapminmax_reverse

from .measure import Data, ShapePCA, add_image_noise, image_inputs

PCA_FILE = "image_pca.json"


@dataclass
class ImageTrainConfig(TrainConfig):
    """:class:`elastimap.training.experiment.TrainConfig` with ``n_in`` inputs instead of three."""

    n_in: int = 10

    @property
    def arch(self) -> Arch:
        return Arch(self.n_in, tuple(self.hidden), len(TARGETS))


def input_names(k: int, force: bool) -> tuple[str, ...]:
    return ("ln_peak",) + tuple(f"shape{i}" for i in range(1, k)) + (("dF_pct",) if force else ())


def samples_of(data: Data):
    df = pd.DataFrame(
        {
            "sample_id": data.ids,
            "tag": data.tags,
            "O1": data.features[:, 0],
            "O2": data.features[:, 1],
            "O3": data.features[:, 2],
            "d": data.theta[:, 0],
            "h": data.theta[:, 1],
            "E": data.theta[:, 2],
        }
    )
    return prepare(df, source=data.source or "<data>")


def _inputs(data: Data, pca: ShapePCA, force: bool, images=None):
    imgs = data.images if images is None else images
    return image_inputs(imgs, pca, data.dforce if force else None, data.force_ref if force else None)


def _train_targets(T: np.ndarray, log_e: bool) -> np.ndarray:
    """Network targets: (d, h, E) or, with ``log_e``, (d, h, ln E)."""
    Tt = np.array(T, dtype=np.float64, copy=True)
    if log_e:
        Tt[..., 2] = np.log(Tt[..., 2])
    return Tt


def _physical(Y: np.ndarray, log_e: bool) -> np.ndarray:
    Y = np.array(Y, dtype=np.float64, copy=True)
    if log_e:
        Y[..., 2] = np.exp(Y[..., 2])
    return Y


def run_image_validation(
    data: Data,
    algo: str,
    validate: str,
    repeats: int,
    cfg: TrainConfig,
    *,
    seed: int = 0,
    test_split: float | None = None,
    k: int = 10,
    image_noise: float = 0.0,
    force: bool = False,
    log_e: bool = False,
) -> ValidationResult:
    """HOV / LOOCV x repeats of the image MLP; ``extra['pred']`` holds the test predictions
    ``(R, n, 3)`` (NaN where a row was not a test row of that repeat) and ``extra['test']``.

    ``log_e``: the network learns ln E instead of E (relative errors of E become additive).  The
    metrics are computed on E itself either way; MSE x 100 on the linear [-1, 1] mapminmax scaling
    of (d, h, E) over each training fold, as for the feature MLP, so the rows stay comparable."""
    samples = samples_of(data)
    if list(samples.df["sample_id"]) != list(data.ids):
        raise UserError("data", "rows must be sorted by sample_id (use elastimap.identify.measure.load)")
    n = data.n
    T = data.theta.astype(np.float64)
    Tt = _train_targets(T, log_e)
    rng, gen = rng_for(seed, validate)
    test1, note = split_rows(samples, validate, test_split, rng)
    if validate == "hov":
        test = np.broadcast_to(test1, (repeats, n)).copy()
        folds = 1
        pca_rows = ~test1
    else:
        test = np.tile(np.eye(n, dtype=bool), (repeats, 1))
        folds = n
        note = f"{n} folds"
        pca_rows = np.ones(n, bool)
    pca = ShapePCA.fit(data.images[pca_rows], k)
    X0 = _inputs(data, pca, force)
    icfg = ImageTrainConfig(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(TrainConfig)}, n_in=X0.shape[1])
    icfg.feature_noise = 0.0
    fit = ~test
    t0 = time.perf_counter()
    batch = make_batch(X0, Tt, fit, test, icfg, rng, gen)
    obj = batch.obj
    if image_noise > 0:
        Xr = []
        for r in range(repeats):
            nrng = np.random.default_rng([int(seed), 7, r])
            Xr.append(_inputs(data, pca, force, add_image_noise(data.images, image_noise, nrng)))
        Xb = np.repeat(np.stack(Xr), folds, axis=0)  # (B, n, c)
        Xs = torch.as_tensor(mapminmax_apply(Xb, batch.x_lo, batch.x_hi), dtype=obj.X.dtype, device=obj.X.device)
        obj = NetObjective(icfg.arch, Xs, obj.T, obj.w, obj.w_val, obj.w_test)
    res = train_batch(algo, obj, batch.theta0, icfg, desc=f"{algo}-image {validate}")
    wall = time.perf_counter() - t0
    Ys = predict_scaled(res.theta, obj.X, icfg.arch)
    Ts = obj.T.cpu().numpy()
    Yp = _physical(mapminmax_reverse(Ys, batch.t_lo, batch.t_hi), log_e)
    if log_e:  # scores on the linear scaling of (d, h, E) over each training fold
        lo, hi = mapminmax_fit(np.broadcast_to(T, Yp.shape), batch.train)
        Ys, Ts = mapminmax_apply(Yp, lo, hi), mapminmax_apply(np.broadcast_to(T, Yp.shape), lo, hi)
    R = repeats
    shp = (R, folds, n)
    tm = test.reshape(shp)[..., None]
    cnt = tm.sum(axis=(1, 2))
    Tp = np.broadcast_to(T, Yp.shape)
    per = {
        "mse100": 100.0 * (((Ts - Ys) ** 2).reshape(*shp, 3) * tm).sum(axis=(1, 2)) / cnt,
        "mre": 100.0 * ((np.abs(Yp - Tp) / np.abs(Tp)).reshape(*shp, 3) * tm).sum(axis=(1, 2)) / cnt,
        "rmse": np.sqrt((((Yp - Tp) ** 2).reshape(*shp, 3) * tm).sum(axis=(1, 2)) / cnt),
    }
    pred = np.where(tm, Yp.reshape(*shp, 3), 0.0).sum(axis=1)  # (R, n, 3)
    pred[~test.reshape(shp).any(axis=1)] = np.nan
    # the deployed situation: ONE noisy image of each held-out lesion through every repeat's network
    # (above, each repeat saw its own noise draw, so a mean over repeats would also average noise)
    pred_shared = None
    if image_noise > 0:
        Xf = _inputs(data, pca, force, add_image_noise(data.images, image_noise, np.random.default_rng([int(seed), 9])))
        Xf = torch.as_tensor(
            mapminmax_apply(np.broadcast_to(Xf, (test.shape[0],) + Xf.shape), batch.x_lo, batch.x_hi),
            dtype=obj.X.dtype,
            device=obj.X.device,
        )
        Yf = _physical(mapminmax_reverse(predict_scaled(res.theta, Xf, icfg.arch), batch.t_lo, batch.t_hi), log_e)
        pred_shared = np.where(tm, Yf.reshape(*shp, 3), 0.0).sum(axis=1)
        pred_shared[~test.reshape(shp).any(axis=1)] = np.nan
    trm = batch.train.reshape(shp)[..., None]
    train_mse = 100.0 * ((((Ts - Ys) ** 2).reshape(*shp, 3) * trm).sum(axis=2) / trm.sum(axis=2)).mean(axis=1)
    B = test.shape[0]
    row = {
        "algo": f"{algo}-image" + ("-lnE" if log_e else ""),
        "validate": validate,
        "repeats": R,
        "n_samples": n,
        "n_train": int(batch.train[0].sum()),
        "n_test_per_repeat": int(cnt[0, 0]),
        "trainings": B,
        "hidden": ",".join(f"{s}" if a == "tansig" else f"{s}:{a}" for s, a in icfg.hidden),
        "epochs": icfg.epochs,
        "feature_noise": 0.0,
        "image_noise": image_noise,
        "pca_k": k,
        "force": force,
        "log_e": log_e,
        "val_fraction": icfg.val_fraction,
        "test_set": note,
        "wall_s": round(wall, 3),
        "trainings_per_s": round(B / wall, 3),
        "mean_epochs_run": float(res.epochs.double().mean()),
    }
    for m in METRICS:
        for j, t in enumerate(TARGETS):
            for kk, v in summarize(per[m][:, j]).items():
                row[f"{m}_{t}_{kk}"] = v
    for j, t in enumerate(TARGETS):
        row[f"train_mse100_{t}_mean"] = float(train_mse[:, j].mean())
    stops: dict[str, int] = {}
    for s in res.stop:
        stops[s] = stops.get(s, 0) + 1
    row["stops"] = ";".join(f"{a}:{b}" for a, b in sorted(stops.items()))
    curves = {kk: v.numpy() for kk, v in res.history.items() if kk in ("train", "test", "val")}
    return ValidationResult(
        f"{algo}-image" + ("-lnE" if log_e else ""),
        validate,
        R,
        row,
        per,
        curves,
        stops,
        wall,
        extra={
            "pred": pred,
            "pred_shared_noise": pred_shared,
            "test": test1 if validate == "hov" else np.ones(n, bool),
        },
    )


# ----------------------------------------------------------------------------- the saved model
@dataclass
class ImageModel:
    """An :class:`elastimap.training.model.Ensemble` over image inputs plus the PCA basis that makes them."""

    ensemble: Ensemble
    pca: ShapePCA
    force: bool = False
    shape: tuple[int, int] | None = None  # (ny, nx) of the FEM difference images it was trained on
    pixel: float | None = None  # their pixel side, mm
    log_e: bool = False  # the networks output ln E (predict returns E)

    def inputs(self, images, dforce=None, force_ref=None) -> np.ndarray:
        images = np.atleast_2d(np.asarray(images, dtype=np.float64))
        p = self.pca.mean.size
        if images.ndim != 2 or images.shape[1] != p:
            images = images.reshape(images.shape[0], -1) if images.size % p == 0 else images
        if images.shape[-1] != p:
            raise UserError("image", f"expected images of {p} pixels (got shape {np.shape(images)})")
        if not np.isfinite(images).all():
            raise UserError("image", "contains NaN or inf")
        if self.force:
            if dforce is None or force_ref is None:
                raise UserError("force", "this model needs the plate-force difference and the reference force")
        return image_inputs(images, self.pca, dforce if self.force else None, force_ref if self.force else None)

    def predict(self, images, dforce=None, force_ref=None) -> np.ndarray:
        """``(members, n, 3)`` d mm, h mm, E kPa for ``(n, ny*nx)`` (or ``(n, ny, nx)``) difference images."""
        return _physical(self.ensemble.predict(self.inputs(images, dforce, force_ref)), self.log_e)

    def in_range(self, images, dforce=None, force_ref=None) -> np.ndarray:
        return self.ensemble.in_range(self.inputs(images, dforce, force_ref))

    def save(self, directory: str) -> str:
        self.ensemble.save(directory)
        with open(os.path.join(directory, PCA_FILE), "w") as f:
            json.dump(
                {
                    "format": "elastimap.identify.image_pca",
                    "version": 1,
                    "force": self.force,
                    "inputs": "ln(peak), PCA scores of image/peak" + (", 100 dF/F_ref" if self.force else ""),
                    "image_shape": list(self.shape) if self.shape else None,
                    "pixel_mm": self.pixel,
                    "log_e": self.log_e,
                    **self.pca.to_json(),
                },
                f,
            )
        return directory

    @classmethod
    def load(cls, directory: str) -> ImageModel:
        p = os.path.join(directory, PCA_FILE)
        if not os.path.isfile(p):
            raise UserError("model", f"{directory} is not an image model (missing {PCA_FILE})")
        with open(p) as f:
            meta = json.load(f)
        shape = tuple(int(x) for x in meta["image_shape"]) if meta.get("image_shape") else None
        pixel = float(meta["pixel_mm"]) if meta.get("pixel_mm") else None
        return cls(
            Ensemble.load(directory),
            ShapePCA.from_json(meta),
            bool(meta.get("force", False)),
            shape,
            pixel,
            bool(meta.get("log_e", False)),
        )


def fit_image_model(
    data: Data,
    algo: str = "scg",
    repeats: int = 10,
    cfg: TrainConfig | None = None,
    *,
    seed: int = 0,
    k: int = 10,
    force: bool = False,
    image_noise: float = 0.0,
    log_e: bool = False,
) -> ImageModel:
    """Train the saved ensemble on every row of ``data`` (``repeats`` initialisations)."""
    from elastimap.provenance import code_version
    from elastimap.training.data import data_hash

    cfg = cfg or TrainConfig(progress=False)
    pca = ShapePCA.fit(data.images, k)
    X0 = _inputs(data, pca, force)
    icfg = ImageTrainConfig(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(TrainConfig)}, n_in=X0.shape[1])
    icfg.feature_noise = 0.0
    T = data.theta.astype(np.float64)
    rng, gen = rng_for(seed, "final")
    batch = make_batch(X0, _train_targets(T, log_e), np.ones((repeats, data.n), bool), None, icfg, rng, gen)
    obj = batch.obj
    if image_noise > 0:
        Xb = np.stack(
            [
                _inputs(
                    data, pca, force, add_image_noise(data.images, image_noise, np.random.default_rng([seed, 8, r]))
                )
                for r in range(repeats)
            ]
        )
        obj = NetObjective(
            icfg.arch,
            torch.as_tensor(mapminmax_apply(Xb, batch.x_lo, batch.x_hi), dtype=obj.X.dtype, device=obj.X.device),
            obj.T,
            obj.w,
            obj.w_val,
            obj.w_test,
        )
    res = train_batch(algo, obj, batch.theta0, icfg, desc=f"{algo}-image final")
    names = input_names(k, force)
    units = dict(UNITS, **{nm: "" for nm in names})
    meta = {
        "algo": f"{algo}-image" + ("-lnE" if log_e else ""),
        "log_e": log_e,
        "epochs": icfg.epochs,
        "repeats": repeats,
        "seed": seed,
        "pca_k": k,
        "force": force,
        "image_noise": image_noise,
        "n_train": data.n,
        "data_source": data.source,
        "data_sha256": data_hash(samples_of(data).df),
        "stop_reasons": res.stop,
        "epochs_run": res.epochs.tolist(),
        "code_version": code_version(),
        "device": str(icfg.resolved_device()),
    }
    ens = Ensemble(
        arch=icfg.arch,
        theta=res.theta.detach().cpu().numpy().astype(np.float64),
        x_min=batch.x_lo[0],
        x_max=batch.x_hi[0],
        y_min=batch.t_lo[0],
        y_max=batch.t_hi[0],
        feature_names=names,
        target_names=TARGETS,
        units=units,
        feature_range=np.stack([X0.min(0), X0.max(0)]),
        target_range=np.stack([T.min(0), T.max(0)]),
        meta=meta,
    )
    return ImageModel(ens, pca, force, tuple(data.shape), float(data.pixel), log_e)
