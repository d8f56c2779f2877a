"""A trained ensemble of MLPs: the inverse map (O1, O2, O3) -> (d, h, E).

On disk a model is a directory with

* ``ensemble.safetensors`` -- ``layer<l>.weight`` ``(M, out, in)`` and
  ``layer<l>.bias`` ``(M, out)`` (float64) for the ``M`` member networks;
  safetensors holds plain arrays only, so loading never executes code;
* ``model.json`` -- architecture, the ``mapminmax`` scaling of inputs and
  targets (fitted on the training rows), feature/target names and units,
  feature and target ranges of the training data, and training provenance
  (algorithm, epochs, seed, SHA-256 of the training data, code version).

Prediction is plain NumPy: ``Ensemble.predict`` works without torch on the
device and gives every member's estimate so callers can report the spread.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field

import numpy as np

from elastimap.errors import UserError

from .data import FEATURES, TARGETS, UNITS
from .net import Arch
from .problem import mapminmax_apply, mapminmax_reverse

FORMAT = "elastimap.training.ensemble"
FORMAT_VERSION = 1
WEIGHTS_FILE = "ensemble.safetensors"
META_FILE = "model.json"


def _act_np(z, name):
    if name == "tansig":
        return np.tanh(z)
    if name == "logsig":
        return 1.0 / (1.0 + np.exp(-z))
    return z


@dataclass
class Ensemble:
    """``M`` networks sharing one architecture and one input/target scaling."""

    arch: Arch
    theta: np.ndarray                    # (M, P) flat parameters, layout of elastimap.training.net
    x_min: np.ndarray                    # (n_in,) mapminmax input scaling
    x_max: np.ndarray
    y_min: np.ndarray                    # (n_out,) mapminmax target scaling
    y_max: np.ndarray
    feature_names: tuple[str, ...] = FEATURES
    target_names: tuple[str, ...] = TARGETS
    units: dict = field(default_factory=lambda: dict(UNITS))
    feature_range: np.ndarray | None = None   # (2, n_in) min, max over training data
    target_range: np.ndarray | None = None    # (2, n_out)
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.theta = np.atleast_2d(np.asarray(self.theta, dtype=np.float64))
        for k in ("x_min", "x_max", "y_min", "y_max"):
            setattr(self, k, np.asarray(getattr(self, k), dtype=np.float64))
        if self.feature_range is None:
            self.feature_range = np.stack([self.x_min, self.x_max])
        if self.target_range is None:
            self.target_range = np.stack([self.y_min, self.y_max])
        self.feature_range = np.asarray(self.feature_range, dtype=np.float64)
        self.target_range = np.asarray(self.target_range, dtype=np.float64)
        self.feature_names = tuple(self.feature_names)
        self.target_names = tuple(self.target_names)
        if self.theta.shape[1] != self.arch.n_params:
            raise ValueError(f"theta has {self.theta.shape[1]} parameters, architecture needs {self.arch.n_params}")

    @property
    def n_members(self) -> int:
        return self.theta.shape[0]

    def layers(self):
        """Per layer ``(W (M, out, in), b (M, out), activation)``."""
        out, M = [], self.n_members
        for (fi, fo, name), sl in zip(self.arch.layers, self.arch.slices):
            Wb = self.theta[:, sl].reshape(M, fo, fi + 1)
            out.append((Wb[:, :, :fi], Wb[:, :, fi], name))
        return out

    def predict(self, X) -> np.ndarray:
        """Every member's ``(d, h, E)`` for features ``X`` ``(n, 3)`` in physical units.

        Returns ``(n_members, n, 3)`` in mm, mm, kPa.  Inputs outside
        :attr:`feature_range` are extrapolation; see :meth:`in_range`.
        """
        X = np.asarray(X, dtype=np.float64)
        if X.ndim == 1:
            X = X[None, :]
        if X.ndim != 2 or X.shape[1] != self.arch.n_in:
            raise UserError("features", f"expected an array of shape (n, {self.arch.n_in}) with columns "
                                        f"{', '.join(self.feature_names)} (got shape {X.shape})")
        if not np.isfinite(X).all():
            raise UserError("features", "contain NaN or inf")
        a = np.broadcast_to(mapminmax_apply(X, self.x_min, self.x_max), (self.n_members, *X.shape))
        for W, b, name in self.layers():
            a = _act_np(np.einsum("mni,moi->mno", a, W) + b[:, None, :], name)
        return mapminmax_reverse(a, self.y_min, self.y_max)

    def predict_stats(self, X):
        """``(mean, std)`` over members, each ``(n, 3)``."""
        Y = self.predict(X)
        return Y.mean(axis=0), Y.std(axis=0, ddof=1) if self.n_members > 1 else np.zeros(Y.shape[1:])

    def in_range(self, X) -> np.ndarray:
        """``(n,)`` true where every feature lies inside the training range."""
        X = np.atleast_2d(np.asarray(X, dtype=np.float64))
        return ((X >= self.feature_range[0]) & (X <= self.feature_range[1])).all(axis=1)

    # ------------------------------------------------------------------ I/O
    def to_json(self) -> dict:
        return {
            "format": FORMAT, "format_version": FORMAT_VERSION,
            "architecture": self.arch.to_json(),
            "n_members": self.n_members,
            "weights_file": WEIGHTS_FILE,
            "parameter_layout": "layer<l>.weight (members, out, in) and layer<l>.bias (members, out), l = 0 .. input to output",
            "feature_names": list(self.feature_names), "target_names": list(self.target_names),
            "units": {k: self.units.get(k, "") for k in (*self.feature_names, *self.target_names)},
            "scaling": {"method": "mapminmax", "ymin": -1.0, "ymax": 1.0,
                        "note": "y = (ymax-ymin)(x-xmin)/(xmax-xmin)+ymin per column, fitted on the training rows",
                        "x_min": self.x_min.tolist(), "x_max": self.x_max.tolist(),
                        "t_min": self.y_min.tolist(), "t_max": self.y_max.tolist()},
            "feature_range": self.feature_range.tolist(),
            "target_range": self.target_range.tolist(),
            "training": self.meta,
        }

    def save(self, directory: str) -> str:
        from safetensors.numpy import save_file

        os.makedirs(directory, exist_ok=True)
        tensors = {}
        for l, (W, b, _) in enumerate(self.layers()):
            tensors[f"layer{l}.weight"] = np.ascontiguousarray(W)
            tensors[f"layer{l}.bias"] = np.ascontiguousarray(b)
        save_file(tensors, os.path.join(directory, WEIGHTS_FILE), metadata={"format": FORMAT})
        with open(os.path.join(directory, META_FILE), "w") as f:
            json.dump(self.to_json(), f, indent=2)
            f.write("\n")
        return directory

    @classmethod
    def load(cls, directory: str) -> "Ensemble":
        from safetensors.numpy import load_file

        meta_p = os.path.join(directory, META_FILE)
        w_p = os.path.join(directory, WEIGHTS_FILE)
        for p in (meta_p, w_p):
            if not os.path.isfile(p):
                raise UserError("model", f"{directory} is not a trained model directory (missing {os.path.basename(p)})")
        with open(meta_p) as f:
            try:
                meta = json.load(f)
            except json.JSONDecodeError as exc:
                raise UserError("model", f"{meta_p} is not valid JSON ({exc})") from None
        if meta.get("format") != FORMAT or int(meta.get("format_version", -1)) > FORMAT_VERSION:
            raise UserError("model", f"{meta_p}: unsupported model format {meta.get('format')!r} "
                                     f"version {meta.get('format_version')!r}")
        arch = Arch.from_json(meta["architecture"])
        t = load_file(w_p)
        parts = []
        for l in range(len(arch.layers)):
            W, b = t[f"layer{l}.weight"], t[f"layer{l}.bias"]
            parts.append(np.concatenate([W, b[:, :, None]], axis=2).reshape(W.shape[0], -1))
        theta = np.concatenate(parts, axis=1).astype(np.float64)
        sc = meta["scaling"]
        return cls(arch=arch, theta=theta, x_min=sc["x_min"], x_max=sc["x_max"], y_min=sc["t_min"],
                   y_max=sc["t_max"], feature_names=tuple(meta["feature_names"]),
                   target_names=tuple(meta["target_names"]), units=dict(meta.get("units", {})),
                   feature_range=np.asarray(meta["feature_range"]), target_range=np.asarray(meta["target_range"]),
                   meta=dict(meta.get("training", {})))
