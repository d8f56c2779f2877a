"""A trained ensemble of MLPs: the inverse map (O1, O2, O3) -> (d, h, E), and the protocol
(:class:`InverseModel`) every inverse model that inference takes implements.

On disk a model is a directory with

* ``ensemble.safetensors`` -- ``layer<l>.weight`` ``(M, out, in)`` and
  ``layer<l>.bias`` ``(M, out)`` (float64) for the ``M`` member networks;
  safetensors holds plain arrays only, so loading never executes code;
* ``model.json`` -- architecture, the ``mapminmax`` scaling of inputs and
  targets (fitted on the training rows), feature/target names and units,
  feature and target ranges of the training data, training provenance
  (algorithm, epochs, seed, SHA-256 of the training data, code version) and
  ``weights_sha256``, the SHA-256 of ``ensemble.safetensors``, checked on load.

The folder is written atomically (a temporary sibling renamed into place) and
every kind of damage is refused on load with one line naming the file.

Prediction is plain NumPy: ``Ensemble.predict`` works without torch on the
device and gives every member's estimate so callers can report the spread.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import ClassVar, Protocol, runtime_checkable

import numpy as np

from elastimap.errors import UserError

from .data import FEATURES, TARGETS, UNITS
from .net import Arch
from .problem import mapminmax_apply, mapminmax_reverse

FORMAT = "elastimap.training.ensemble"
FORMAT_VERSION = 1
WEIGHTS_FILE = "ensemble.safetensors"
META_FILE = "model.json"


@runtime_checkable
class InverseModel(Protocol):
    """What inference (:mod:`elastimap.camera.infer`) needs of any inverse model: the feature
    ensemble (:class:`Ensemble`) and the image model (:class:`elastimap.identify.image_model.ImageModel`).

    ``input_kind`` names what ``X`` is, and so the identifiability map's measurement set:
    ``"features"`` (calibrated FEM features O1..O3, ``(n, 3)``) or ``"image"`` (FEM difference
    images, mm, ``(n, ny*nx)``)."""

    input_kind: ClassVar[str]

    @property
    def n_members(self) -> int: ...

    @property
    def target_range(self) -> np.ndarray:
        """``(2, 3)`` min, max of (d, h, E) over the training rows."""
        ...

    def predict(self, X) -> np.ndarray:
        """Every member's ``(d mm, h mm, E kPa)``: ``(members, n, 3)``."""
        ...

    def in_range(self, X) -> np.ndarray:
        """``(n,)`` true where the input lies inside the training range."""
        ...

    def outside_training(self, X) -> list[list[str]]:
        """Per row, the names of the inputs outside the training range (flags ``outside_training:<name>``)."""
        ...

    def save(self, directory: str) -> str: ...

    @classmethod
    def load(cls, directory: str) -> InverseModel: ...


def _act_np(z, name):
    if name == "tansig":
        return np.tanh(z)
    if name == "logsig":
        return 1.0 / (1.0 + np.exp(-z))
    return z


@dataclass
class Ensemble:
    """``M`` networks sharing one architecture and one input/target scaling: the feature
    :class:`InverseModel` (O1, O2, O3 -> d, h, E)."""

    input_kind: ClassVar[str] = "features"

    arch: Arch
    theta: np.ndarray  # (M, P) flat parameters, layout of elastimap.training.net
    x_min: np.ndarray  # (n_in,) mapminmax input scaling
    x_max: np.ndarray
    y_min: np.ndarray  # (n_out,) mapminmax target scaling
    y_max: np.ndarray
    feature_names: tuple[str, ...] = FEATURES
    target_names: tuple[str, ...] = TARGETS
    units: dict = field(default_factory=lambda: dict(UNITS))
    feature_range: np.ndarray | None = None  # (2, n_in) min, max over training data
    target_range: np.ndarray | None = None  # (2, n_out)
    meta: dict = field(default_factory=dict)

    @classmethod
    def from_training(cls, arch, res, batch, X, T, feature_names, units, meta) -> Ensemble:
        """The ensemble a training run made: ``res`` (its parameters), ``batch`` (the mapminmax
        scalings of its first member, shared by all), ``X``/``T`` the training inputs and targets
        (their ranges are the model's range flags)."""
        return cls(
            arch=arch,
            theta=res.theta.detach().cpu().numpy().astype(np.float64),
            x_min=batch.x_lo[0],
            x_max=batch.x_hi[0],
            y_min=batch.t_lo[0],
            y_max=batch.t_hi[0],
            feature_names=tuple(feature_names),
            target_names=TARGETS,
            units=dict(units),
            feature_range=np.stack([X.min(0), X.max(0)]),
            target_range=np.stack([T.min(0), T.max(0)]),
            meta=meta,
        )

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
            raise UserError(
                "features",
                f"expected an array of shape (n, {self.arch.n_in}) with columns "
                f"{', '.join(self.feature_names)} (got shape {X.shape})",
            )
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

    def outside_training(self, X) -> list[list[str]]:
        """Per row, the features outside the training range (:attr:`feature_range`)."""
        X = np.atleast_2d(np.asarray(X, dtype=np.float64))
        out = (X < self.feature_range[0]) | (X > self.feature_range[1])
        return [[k for j, k in enumerate(self.feature_names) if row[j]] for row in out]

    # ------------------------------------------------------------------ I/O
    def to_json(self) -> dict:
        return {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "architecture": self.arch.to_json(),
            "n_members": self.n_members,
            "weights_file": WEIGHTS_FILE,
            "parameter_layout": "layer<l>.weight (members, out, in) and layer<l>.bias (members, out), l = 0 .. input to output",
            "feature_names": list(self.feature_names),
            "target_names": list(self.target_names),
            "units": {k: self.units.get(k, "") for k in (*self.feature_names, *self.target_names)},
            "scaling": {
                "method": "mapminmax",
                "ymin": -1.0,
                "ymax": 1.0,
                "note": "y = (ymax-ymin)(x-xmin)/(xmax-xmin)+ymin per column, fitted on the training rows",
                "x_min": self.x_min.tolist(),
                "x_max": self.x_max.tolist(),
                "t_min": self.y_min.tolist(),
                "t_max": self.y_max.tolist(),
            },
            "feature_range": self.feature_range.tolist(),
            "target_range": self.target_range.tolist(),
            "training": self.meta,
        }

    def save(self, directory: str) -> str:
        """Write the model folder atomically: a temporary sibling folder is filled (weights, then
        ``model.json`` with the SHA-256 of the weights file) and renamed onto ``directory``, which
        it replaces whole; a crash leaves either the old folder or the new one, never a mix."""
        import tempfile

        from safetensors.numpy import save_file

        from elastimap.outputs import publish_dir, umask

        final = os.path.abspath(directory)
        os.makedirs(os.path.dirname(final), exist_ok=True)
        tmp = tempfile.mkdtemp(prefix=f".{os.path.basename(final)}.", suffix=".partial", dir=os.path.dirname(final))
        os.chmod(tmp, 0o777 & ~umask())  # mkdtemp's 0700 would outlive the rename
        try:
            tensors = {}
            for l, (W, b, _) in enumerate(self.layers()):
                tensors[f"layer{l}.weight"] = np.ascontiguousarray(W)
                tensors[f"layer{l}.bias"] = np.ascontiguousarray(b)
            w_p = os.path.join(tmp, WEIGHTS_FILE)
            save_file(tensors, w_p, metadata={"format": FORMAT})
            doc = self.to_json()
            doc["weights_sha256"] = _sha256(w_p)
            with open(os.path.join(tmp, META_FILE), "w") as f:
                json.dump(doc, f, indent=2)
                f.write("\n")
            from pathlib import Path

            for name in os.listdir(tmp):  # safetensors writes its file 0600
                os.chmod(os.path.join(tmp, name), 0o666 & ~umask())
            publish_dir(Path(tmp), Path(final), "model")
        except BaseException:
            import shutil

            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return directory

    @classmethod
    def load(cls, directory: str) -> Ensemble:
        """Read a model folder; any damage is ONE :class:`UserError` naming the file.

        Checked: ``model.json`` is JSON with the format, architecture, scaling, names and
        ranges (:func:`_read_meta`); the weights file matches the SHA-256 recorded in
        ``model.json`` (folders written before the hash was recorded skip this check); it is a
        readable safetensors file holding exactly the tensors the architecture needs, with their
        shapes, all finite (:func:`_read_weights`).
        """
        meta_p = os.path.join(directory, META_FILE)
        w_p = os.path.join(directory, WEIGHTS_FILE)
        if not os.path.isdir(directory):
            raise UserError("model", f"{directory}: no such model directory")
        for p in (meta_p, w_p):
            if not os.path.isfile(p):
                raise UserError(
                    "model", f"{directory} is not a trained model directory (missing {os.path.basename(p)})"
                )
        m = _read_meta(meta_p)
        theta = _read_weights(w_p, m["arch"], m["meta"].get("weights_sha256"))
        scal = m["scaling"]
        return cls(
            arch=m["arch"],
            theta=theta,
            x_min=scal["x_min"],
            x_max=scal["x_max"],
            y_min=scal["t_min"],
            y_max=scal["t_max"],
            feature_names=m["feature_names"],
            target_names=m["target_names"],
            units=dict(m["meta"].get("units", {})),
            feature_range=m["feature_range"],
            target_range=m["target_range"],
            meta=dict(m["meta"].get("training", {})),
        )


def _read_meta(meta_p: str) -> dict:
    """``model.json`` checked: format and version, architecture, finite scalings with max > min,
    finite ranges with min <= max (the range flags need them), names matching the architecture.
    Returns ``meta`` (the raw document), ``arch``, ``scaling``, the ranges and the names."""

    def bad(why: str) -> UserError:
        return UserError("model", f"{meta_p}: {why}")

    try:
        with open(meta_p, encoding="utf-8") as f:
            meta = json.load(f)
    except (ValueError, UnicodeDecodeError) as exc:
        raise bad(f"not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise bad("not a JSON object")
    try:
        version = int(meta.get("format_version", -1))
    except (TypeError, ValueError):
        version = -1
    if meta.get("format") != FORMAT or not 1 <= version <= FORMAT_VERSION:
        raise bad(f"unsupported model format {meta.get('format')!r} version {meta.get('format_version')!r}")
    for key in ("architecture", "scaling", "feature_names", "target_names", "feature_range", "target_range"):
        if key not in meta:
            raise bad(f"missing '{key}'")
    try:
        arch = Arch.from_json(meta["architecture"])
        if arch.n_in < 1 or arch.n_out < 1 or any(n < 1 for n, _ in arch.hidden):
            raise ValueError("layer sizes must be >= 1")
    except (KeyError, TypeError, ValueError) as exc:
        raise bad(f"unreadable 'architecture' ({type(exc).__name__}: {exc})") from None
    sc = meta["scaling"]
    try:
        scal = {k: np.asarray(sc[k], dtype=np.float64) for k in ("x_min", "x_max", "t_min", "t_max")}
        fr = np.asarray(meta["feature_range"], dtype=np.float64)
        tr = np.asarray(meta["target_range"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise bad(f"unreadable 'scaling' or ranges ({type(exc).__name__}: {exc})") from None
    for k, v in scal.items():
        n = arch.n_in if k.startswith("x") else arch.n_out
        if v.shape != (n,) or not np.isfinite(v).all():
            raise bad(f"scaling {k} must be {n} finite numbers")
    if not ((scal["x_max"] > scal["x_min"]).all() and (scal["t_max"] > scal["t_min"]).all()):
        raise bad("scaling maxima must exceed the minima")
    if fr.shape != (2, arch.n_in) or tr.shape != (2, arch.n_out):
        raise bad("feature_range / target_range do not match the architecture")
    for name, r in (("feature_range", fr), ("target_range", tr)):
        if not np.isfinite(r).all() or (r[0] > r[1]).any():
            raise bad(f"{name} must hold finite minima no larger than their maxima (the range flags need it)")
    names_f, names_t = tuple(meta["feature_names"]), tuple(meta["target_names"])
    if len(names_f) != arch.n_in or len(names_t) != arch.n_out:
        raise bad("feature/target names do not match the architecture")
    return {
        "meta": meta,
        "arch": arch,
        "scaling": scal,
        "feature_range": fr,
        "target_range": tr,
        "feature_names": names_f,
        "target_names": names_t,
    }


def _read_weights(w_p: str, arch: Arch, want_sha: str | None) -> np.ndarray:
    """The flat parameters ``(M, P)`` from the safetensors file ``w_p``, checked against the
    SHA-256 ``want_sha`` (None: not recorded) and against ``arch`` (tensor names and shapes,
    one member count, all finite)."""
    from safetensors.numpy import load_file

    def bad(why: str) -> UserError:
        return UserError("model", f"{w_p}: {why}")

    if want_sha is not None and _sha256(w_p) != want_sha:
        raise bad("does not match the SHA-256 recorded in model.json (damaged or edited)")
    try:
        t = load_file(w_p)
    except Exception as exc:  # safetensors raises several types for damaged files
        raise bad(f"not a readable safetensors file ({type(exc).__name__})") from None
    want = {f"layer{l}.{k}" for l in range(len(arch.layers)) for k in ("weight", "bias")}
    if set(t) != want:
        missing, extra = sorted(want - set(t)), sorted(set(t) - want)
        raise bad(
            "tensors do not match the architecture in model.json"
            + (f"; missing {', '.join(missing)}" if missing else "")
            + (f"; unexpected {', '.join(extra)}" if extra else "")
        )
    parts, M = [], None
    for l, (fi, fo, _) in enumerate(arch.layers):
        W, b = t[f"layer{l}.weight"], t[f"layer{l}.bias"]
        M = W.shape[0] if M is None else M
        if W.shape != (M, fo, fi) or b.shape != (M, fo) or M < 1:
            raise bad(
                f"layer{l} has shapes {W.shape} and {b.shape}; model.json's architecture "
                f"needs ({M}, {fo}, {fi}) and ({M}, {fo})"
            )
        parts.append(np.concatenate([W, b[:, :, None]], axis=2).reshape(M, -1))
    theta = np.concatenate(parts, axis=1).astype(np.float64)
    if not np.isfinite(theta).all():
        raise bad("holds NaN or inf weights")
    return theta


def _sha256(path: str) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
