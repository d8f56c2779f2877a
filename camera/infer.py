"""Inference: camera features or frames -> calibrated FEM features -> (d, h, E).

Python API (imports no solver and no DOLFINx)::

    from camera.infer import load_ensemble, estimate, estimate_images
    from camera.calibration import Calibration
    cal = Calibration.load("cal.json")
    ens = load_ensemble("models/run1")              # training.model.Ensemble
    est = estimate([[O1, O2, O3]], cal, ens)        # camera features (see camera.features)
    est[0].d, est[0].d_sd, est[0].flags

Uncertainty: the ensemble's members (the networks of the training repeats)
each predict (d, h, E); the estimate is their mean and the uncertainty their
standard deviation (``*_sd``), plus the 10-90 % member range.  Inputs are
never silently extrapolated: every estimate carries ``flags``:

* ``outside_calibration:Ok`` - camera feature k outside the range spanned by
  the nine calibration phantoms (the linear map is extrapolated);
* ``outside_training:Ok`` - the calibrated FEM feature k outside the
  network's training range (``ensemble.feature_range``);
* ``no_signal`` - O1 at or below zero: no inclusion visible.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from elastimap.errors import UserError

from .calibration import FEATURES, Calibration

TARGETS = ("d", "h", "E")
TARGET_UNITS = {"d": "mm", "h": "mm", "E": "kPa"}


@dataclass
class Estimate:
    id: str
    cam: np.ndarray          # camera features (3,)
    fem: np.ndarray          # calibrated FEM features (3,)
    mean: np.ndarray         # (d, h, E) ensemble mean
    sd: np.ndarray           # ensemble standard deviation
    p10: np.ndarray
    p90: np.ndarray
    n_members: int
    flags: list[str] = field(default_factory=list)

    d = property(lambda s: float(s.mean[0]))
    h = property(lambda s: float(s.mean[1]))
    E = property(lambda s: float(s.mean[2]))
    d_sd = property(lambda s: float(s.sd[0]))
    h_sd = property(lambda s: float(s.sd[1]))
    E_sd = property(lambda s: float(s.sd[2]))

    @property
    def ok(self) -> bool:
        return not self.flags

    def to_dict(self) -> dict:
        out: dict = {"id": self.id}
        for j, k in enumerate(TARGETS):
            out[k] = float(self.mean[j])
            out[f"{k}_sd"] = float(self.sd[j])
            out[f"{k}_p10"] = float(self.p10[j])
            out[f"{k}_p90"] = float(self.p90[j])
        for j, k in enumerate(FEATURES):
            out[f"cam_{k}"] = float(self.cam[j])
        for j, k in enumerate(FEATURES):
            out[f"fem_{k}"] = float(self.fem[j])
        out["n_members"] = self.n_members
        out["flags"] = ";".join(self.flags)
        out["ok"] = self.ok
        return out


def load_ensemble(directory: str | os.PathLike):
    """Load a trained ensemble (``training.model.Ensemble.load``) with a clear error if impossible."""
    d = str(directory)
    if not os.path.isdir(d):
        raise UserError("model", f"{d}: no such model directory")
    try:
        from training.model import Ensemble
    except ImportError as exc:
        raise UserError("model", f"the training package is not available ({exc})") from None
    return Ensemble.load(d)


def _feature_range(ensemble) -> np.ndarray | None:
    fr = getattr(ensemble, "feature_range", None)
    if fr is None:
        return None
    fr = np.asarray(fr, dtype=float)
    return fr if fr.shape == (2, 3) else None


def estimate(cam_features, calibration: Calibration, ensemble, ids: list[str] | None = None) -> list[Estimate]:
    """(n, 3) camera features -> list of :class:`Estimate`."""
    cam = np.atleast_2d(np.asarray(cam_features, dtype=float))
    if cam.ndim != 2 or cam.shape[1] != 3:
        raise UserError("features", f"need three camera features O1 O2 O3 per lesion (got shape {cam.shape})")
    if not np.all(np.isfinite(cam)):
        raise UserError("features", "camera features must be finite numbers")
    n = cam.shape[0]
    ids = [str(i + 1) for i in range(n)] if ids is None else [str(i) for i in ids]
    if len(ids) != n:
        raise UserError("ids", f"{len(ids)} ids for {n} lesions")
    fem = calibration.apply(cam)
    Y = np.asarray(ensemble.predict(fem), dtype=float)
    if Y.ndim == 2:
        Y = Y[None]
    if Y.shape[1:] != (n, 3):
        raise RuntimeError(f"ensemble.predict returned shape {Y.shape}, expected (members, {n}, 3)")
    mean = Y.mean(axis=0)
    sd = Y.std(axis=0, ddof=1) if Y.shape[0] > 1 else np.full((n, 3), math.nan)
    p10, p90 = np.percentile(Y, 10, axis=0), np.percentile(Y, 90, axis=0)
    out_cal = calibration.outside(cam)
    fr = _feature_range(ensemble)
    out_train = ((fem < fr[0]) | (fem > fr[1])) if fr is not None else np.zeros_like(out_cal)
    ests = []
    for i in range(n):
        flags = [f"outside_calibration:{k}" for j, k in enumerate(FEATURES) if out_cal[i, j]]
        flags += [f"outside_training:{k}" for j, k in enumerate(FEATURES) if out_train[i, j]]
        if cam[i, 0] <= 0:
            flags.insert(0, "no_signal")
        ests.append(Estimate(ids[i], cam[i], fem[i], mean[i], sd[i], p10[i], p90[i], Y.shape[0], flags))
    return ests


def sensor_of(calibration: Calibration):
    """The camera geometry (and synthetic model) the calibration was made with."""
    from .optics import SensorModel

    return SensorModel.from_dict(calibration.sensor) if calibration.sensor else SensorModel()


def settings_of(calibration: Calibration):
    from .features import FeatureSettings

    return FeatureSettings.from_dict(calibration.feature_settings or {})


def features_of_images(images: list[str], background: list[str], calibration: Calibration):
    """Camera features of one lesion's frames, computed exactly as for the calibration."""
    from .features import features_from_files

    return features_from_files(images, background, sensor_of(calibration), settings_of(calibration))


def estimate_images(images: list[str], background: list[str], calibration: Calibration, ensemble,
                    id: str = "1") -> Estimate:
    cf = features_of_images(images, background, calibration)
    return estimate(cf.values[None], calibration, ensemble, [id])[0]


def read_lesions_csv(path: str | os.PathLike, calibration: Calibration) -> tuple[list[str], np.ndarray]:
    """Batch input: a CSV with ``id`` and either ``O1,O2,O3`` (camera features) or
    ``images`` and ``background`` (';'-separated files or globs, relative to the CSV)."""
    import pandas as pd

    from .frames import expand

    p = str(path)
    if not os.path.exists(p):
        raise UserError("csv", f"{p}: no such file")
    try:
        df = pd.read_csv(p, comment="#", skipinitialspace=True)
    except Exception as exc:
        raise UserError("csv", f"{p}: not a readable CSV ({exc})") from None
    if len(df) == 0:
        raise UserError("csv", f"{p}: no lesions")
    ids = [str(x) for x in df["id"]] if "id" in df.columns else [str(i + 1) for i in range(len(df))]
    if all(k in df.columns for k in FEATURES):
        vals = df[list(FEATURES)].apply(pd.to_numeric, errors="coerce").to_numpy(float)
        bad = ~np.all(np.isfinite(vals), axis=1)
        if bad.any():
            raise UserError("csv", f"{p}: non-numeric features for lesion(s) {[ids[i] for i in np.flatnonzero(bad)]}")
        return ids, vals
    if "images" in df.columns and "background" in df.columns:
        base = os.path.dirname(os.path.abspath(p))
        rows = []
        for _, r in df.iterrows():
            rows.append(features_of_images(expand(str(r["images"]), base), expand(str(r["background"]), base),
                                           calibration).values)
        return ids, np.array(rows)
    raise UserError("csv", f"{p}: needs columns O1,O2,O3 or images,background (plus optional id)")
