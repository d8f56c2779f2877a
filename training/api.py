"""Stable Python API of the training stage.

>>> from elastimap.training.api import fit_ensemble
>>> from elastimap.training.model import Ensemble
>>> ens = fit_ensemble(df, algo="scg", repeats=10)      # df: sample table (pandas)
>>> ens.save("runs/model")
>>> Ensemble.load("runs/model").predict(X)              # (members, n, 3): d mm, h mm, E kPa

Importing this module does not import the solver (no dolfinx).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch

from elastimap.errors import UserError

from .data import FEATURES, TARGETS, UNITS, Samples, data_hash, prepare
from .experiment import ALGOS, TrainConfig, make_batch, rng_for, train_batch
from .model import Ensemble
from .net import parse_hidden

__all__ = ["fit_ensemble", "Ensemble"]


def fit_ensemble(
    df: pd.DataFrame | Samples,
    algo: str = "scg",
    repeats: int = 10,
    epochs: int = 100,
    hidden=(25, 10),
    seed: int = 0,
    *,
    activation: str = "tansig",
    feature_noise: float = 0.0,
    val_fraction: float = 0.0,
    device: str | None = None,
    progress: bool = False,
    dtype: torch.dtype = torch.float64,
) -> Ensemble:
    """Train ``repeats`` networks (independent initialisations) on every usable row of ``df``.

    ``df`` is a sample table (columns ``O1, O2, O3, d, h, E``; ``status``,
    ``tag``, ``sample_id`` optional -- failed rows are dropped) or a
    :class:`elastimap.training.data.Samples`.  ``hidden``: ``(25, 10)``, ``"25,10"`` or
    ``"25,10,7:purelin"``.  Returns the :class:`Ensemble` (not yet saved).
    """
    if algo not in ALGOS:
        raise UserError("algo", f"unknown algorithm {algo!r}; use one of {', '.join(ALGOS)}")
    if int(repeats) < 1:
        raise UserError("repeats", f"must be >= 1 (got {repeats})")
    if int(epochs) < 1:
        raise UserError("epochs", f"must be >= 1 (got {epochs})")
    samples = df if isinstance(df, Samples) else prepare(df)
    cfg = TrainConfig(
        hidden=parse_hidden(hidden, activation),
        epochs=int(epochs),
        feature_noise=float(feature_noise),
        val_fraction=float(val_fraction),
        device=device,
        dtype=dtype,
        progress=progress,
    )
    d = samples.df
    X = d[list(FEATURES)].to_numpy(np.float64)
    T = d[list(TARGETS)].to_numpy(np.float64)
    R, n = int(repeats), len(d)
    rng, gen = rng_for(seed, "final")
    fit = np.ones((R, n), bool)
    batch = make_batch(X, T, fit, None, cfg, rng, gen)
    res = train_batch(algo, batch.obj, batch.theta0, cfg, desc=f"{algo} final")
    from elastimap.dataset.io import sensor_record
    from elastimap.provenance import stamp

    meta = {
        "algo": algo,
        "epochs": cfg.epochs,
        "repeats": R,
        "seed": int(seed),
        "feature_noise": cfg.feature_noise,
        "val_fraction": cfg.val_fraction,
        "n_train": n,
        "n_failed_excluded": samples.n_failed,
        "data_source": samples.source,
        "data_sha256": data_hash(d),
        "tags": sorted(set(d["tag"])),
        "stop_reasons": res.stop,
        "epochs_run": res.epochs.tolist(),
        "final_train_mse": [float(v) for v in _last(res.history["train"])],
        "dtype": str(cfg.dtype).replace("torch.", ""),
        "device": str(cfg.resolved_device()),
        **stamp(),
        **sensor_record(samples.source),
        "initialisation": "Nguyen-Widrow (MATLAB initnw) hidden layers, uniform [-1,1] purelin layers",
    }
    return Ensemble.from_training(cfg.arch, res, batch, X, T, FEATURES, UNITS, meta)


def _last(h: torch.Tensor) -> np.ndarray:
    """Last non-NaN value per row of a ``(B, epochs+1)`` history."""
    a = h.numpy()
    ok = ~np.isnan(a)
    idx = np.where(ok.any(1), a.shape[1] - 1 - np.argmax(ok[:, ::-1], axis=1), 0)
    return a[np.arange(a.shape[0]), idx]
