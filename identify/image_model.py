"""The image-based inverse model: shape-PCA of the elasticity image (+ force) -> MLP -> (d, h, E).

Inputs per lesion (:func:`elastimap.identify.measure.image_inputs`): ``ln(peak)`` of the difference image,
the first ``K - 1`` PCA scores of the peak-normalised image (its *shape*) and, with ``force``,
``100 (force - force_ref) / force_ref``.  The network is the paper's MLP (``K -> 25 tansig ->
10 tansig -> 3 purelin``), trained by :mod:`training`'s batched LM / SCG and
validated by the same HOV (the 9 phantoms) / LOOCV x repeats of
:func:`elastimap.training.experiment.validate_inputs` (on these inputs instead of the three
features), scored with the same metrics (MSE x 100 on the
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
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pandas as pd

from elastimap.errors import UserError
from elastimap.training.data import UNITS, data_hash, prepare
from elastimap.training.experiment import TrainConfig, ValidationResult, plan_folds, train_final, validate_inputs
from elastimap.training.model import Ensemble

from .measure import Data, ShapePCA, add_image_noise, image_inputs

PCA_FILE = "image_pca.json"


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


def _noisy_inputs(data: Data, pca: ShapePCA, force: bool, image_noise: float, *key: int) -> np.ndarray:
    """The inputs of one draw of per-pixel noise (``image_noise`` x each image's peak), seeded by ``key``."""
    return _inputs(data, pca, force, add_image_noise(data.images, image_noise, np.random.default_rng(list(key))))


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


def _label(algo: str, log_e: bool) -> str:
    return f"{algo}-image" + ("-lnE" if log_e else "")


def _image_cfg(cfg: TrainConfig) -> TrainConfig:
    """The image networks draw no feature noise: their noise is ``image_noise`` on the pixels."""
    return dataclasses.replace(cfg, feature_noise=0.0)


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
    """HOV / LOOCV x repeats of the image MLP (:func:`elastimap.training.experiment.validate_inputs`
    on the image inputs); ``extra['pred']`` holds the test predictions ``(R, n, 3)`` (NaN where a
    row was not a test row of that repeat), ``extra['test']`` the held-out rows and, with
    ``image_noise``, ``extra['pred_shared_noise']`` the deployed situation: ONE noisy image of each
    held-out lesion through every repeat's network (in training each repeat saw its own noise
    draw, so a mean over repeats would also average noise).

    ``log_e``: the network learns ln E instead of E (relative errors of E become additive).  The
    metrics are computed on E itself either way (see ``validate_inputs``)."""
    samples = samples_of(data)
    if list(samples.df["sample_id"]) != list(data.ids):
        raise UserError("data", "rows must be sorted by sample_id (use elastimap.identify.measure.load)")
    folds = plan_folds(samples, validate, repeats, seed, test_split)
    # PCA sees no targets: HOV fits it on the non-test rows, LOOCV on all rows (module docstring)
    pca = ShapePCA.fit(data.images[~folds.held_out if validate == "hov" else np.ones(data.n, bool)], k)
    X0 = _inputs(data, pca, force)
    X_rep = X_eval = None
    if image_noise > 0:
        X_rep = np.stack([_noisy_inputs(data, pca, force, image_noise, int(seed), 7, r) for r in range(repeats)])
        X_eval = _noisy_inputs(data, pca, force, image_noise, int(seed), 9)
    vr = validate_inputs(
        X0,
        data.theta.astype(np.float64),
        folds,
        algo,
        _image_cfg(cfg),
        names=input_names(k, force),
        label=_label(algo, log_e),
        row_extra={"image_noise": image_noise, "pca_k": k, "force": force, "log_e": log_e},
        X_repeats=X_rep,
        train_targets=(lambda T: _train_targets(T, log_e)) if log_e else None,
        to_physical=(lambda Y: _physical(Y, log_e)) if log_e else None,
        X_eval=X_eval,
    )
    vr.extra["pred_shared_noise"] = vr.extra.pop("pred_eval", None)
    return vr


# ----------------------------------------------------------------------------- the saved model
@dataclass
class ImageModel:
    """An :class:`elastimap.training.model.Ensemble` over image inputs plus the PCA basis that makes
    them: an :class:`elastimap.training.model.InverseModel` whose input is the FEM difference image."""

    input_kind: ClassVar[str] = "image"

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
        """``(n,)`` true where every image input (ln peak, shape scores) lies in the training range."""
        return self.ensemble.in_range(self.inputs(images, dforce, force_ref))

    def outside_training(self, images) -> list[list[str]]:
        """Per image, ``["image"]`` when its inputs leave the training range, else ``[]``."""
        return [[] if ok else ["image"] for ok in np.asarray(self.in_range(images), bool)]

    @property
    def n_members(self) -> int:
        return self.ensemble.n_members

    @property
    def target_range(self) -> np.ndarray:
        return self.ensemble.target_range

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
    from elastimap.provenance import stamp

    cfg = _image_cfg(cfg or TrainConfig(progress=False))
    pca = ShapePCA.fit(data.images, k)
    X0 = _inputs(data, pca, force)
    T = data.theta.astype(np.float64)
    X_rep = None
    if image_noise > 0:
        X_rep = np.stack([_noisy_inputs(data, pca, force, image_noise, seed, 8, r) for r in range(repeats)])
    res, batch = train_final(
        X0, _train_targets(T, log_e), algo, repeats, cfg, seed, names=input_names(k, force), X_repeats=X_rep
    )
    icfg = dataclasses.replace(cfg, n_in=X0.shape[1])
    names = input_names(k, force)
    units = dict(UNITS, **{nm: "" for nm in names})
    meta = {
        "algo": _label(algo, log_e),
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
        **stamp(),
        "device": str(icfg.resolved_device()),
    }
    ens = Ensemble.from_training(icfg.arch, res, batch, X0, T, names, units, meta)
    return ImageModel(ens, pca, force, tuple(data.shape), float(data.pixel), log_e)
