"""Measurement sets and their noise models.

A *measurement* is what the camera side can deliver for one lesion.  The sets compared are

* ``features`` -- the paper's O1, O2, O3 (:mod:`elastimap.solver.image`), noise ``1 %`` of each value
  (the training stage's ``--feature-noise 0.01``);
* ``image`` -- the whole 50 x 50 difference elasticity image (0.5 mm pixels, mm of deflection);
* ``image+force`` -- the image and the plate-force difference ``force - force_ref`` (mN).

Image noise models (per pixel, independent Gaussian):

* ``relative`` (default, "1 % image noise"): ``sigma = level * max(image)`` of that image, the
  same for every pixel of one image (``level`` = 0.01);
* a fixed map ``sigma(x, y)`` in mm (``sigma_map``), e.g. the deflection-equivalent noise of the
  SYNTHETIC TIR camera, :func:`elastimap.camera.optics.deflection_noise_map` (the camera's noise
  model lives with the camera; this library takes the map as plain data and imports no camera code).

Force noise: ``sigma_dF = force_noise * force_ref * sqrt(2)`` (the press and the reference press
each read with a relative error ``force_noise`` of the load, default 0.001 = 0.1 % of ~1.4 N).

Image representation for regressors and the image MLP (:func:`image_inputs`): ``log(peak)``
and the first ``K - 1`` PCA scores of the peak-normalised image ``image / peak`` (the *shape*).
The raw-image PCA is dominated by amplitude, which is what O1/O2 already give; the modulus is in
the shape (measured: see docs/identifiability.md).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from elastimap.dataset.io import read_image_meta, read_samples
from elastimap.dataset.phantoms import is_phantom
from elastimap.errors import UserError

PEAK_FLOOR = 1e-7  # mm; peaks below this are clipped before the log (no visible inclusion)


@dataclass
class Data:
    """Design rows of a sweep, as arrays."""

    theta: np.ndarray  # (n, 3) d mm, h mm, E kPa
    features: np.ndarray  # (n, 3) O1, O2, O3
    images: np.ndarray  # (n, ny*nx) float64, mm
    dforce: np.ndarray  # (n,) force - force_ref, mN
    force_ref: np.ndarray  # (n,)
    tags: np.ndarray  # (n,) str
    ids: np.ndarray  # (n,) str
    shape: tuple[int, int]
    pixel: float
    source: str = ""

    @property
    def n(self) -> int:
        return self.theta.shape[0]

    def subset(self, mask) -> Data:
        m = np.asarray(mask)
        return Data(
            self.theta[m],
            self.features[m],
            self.images[m],
            self.dforce[m],
            self.force_ref[m],
            self.tags[m],
            self.ids[m],
            self.shape,
            self.pixel,
            self.source,
        )


def load(data_path: str, design_only: bool = False) -> Data:
    """Read a sweep (Parquet directory) with its images; rows sorted by ``sample_id``."""
    path = data_path
    if not os.path.exists(path):
        raise UserError("data_path", f"no such file or directory: {path}")
    df = read_samples(path)
    if "image" not in df.columns or df["image"].isna().any():
        raise UserError("data_path", f"{path} has no stored elasticity images (the image column is missing or empty)")
    shape, pixel = read_image_meta(path)
    df = df.sort_values("sample_id", kind="stable").reset_index(drop=True)
    if design_only:
        df = df[~is_phantom(df["tag"])].reset_index(drop=True)
    if len(df) < 10:
        raise UserError("data_path", f"{path}: only {len(df)} usable rows; need at least 10")
    images = np.stack(df["image"].to_numpy()).astype(np.float64)
    if images.shape[1] != shape[0] * shape[1]:
        raise UserError("data_path", f"{path}: images have {images.shape[1]} pixels, metadata says {shape}")
    return Data(
        theta=df[["d", "h", "E"]].to_numpy(float),
        features=df[["O1", "O2", "O3"]].to_numpy(float),
        images=images,
        dforce=(df["force"] - df["force_ref"]).to_numpy(float),
        force_ref=df["force_ref"].to_numpy(float),
        tags=df["tag"].astype(str).to_numpy(),
        ids=df["sample_id"].astype(str).to_numpy(),
        shape=tuple(shape),
        pixel=float(pixel),
        source=path,
    )


# ----------------------------------------------------------------------------- noise
def add_image_noise(
    images: np.ndarray, level: float, rng: np.random.Generator, sigma_map: np.ndarray | None = None
) -> np.ndarray:
    """Noisy copies: ``relative`` (``level`` x each image's peak) or a fixed ``sigma_map`` (mm)."""
    images = np.asarray(images, dtype=np.float64)
    if sigma_map is not None:
        return images + np.asarray(sigma_map).ravel() * rng.standard_normal(images.shape)
    if level <= 0:
        return images
    pk = np.abs(images).max(axis=-1, keepdims=True)
    return images + level * pk * rng.standard_normal(images.shape)


# ----------------------------------------------------------------------------- representations
@dataclass
class ShapePCA:
    """``log(peak)`` and PCA scores of ``image / peak`` (orthonormal components, not whitened)."""

    mean: np.ndarray  # (p,)
    components: np.ndarray  # (K-1, p)
    explained: np.ndarray  # (K-1,) explained variance ratio of the shapes

    @classmethod
    def fit(cls, images: np.ndarray, k: int = 10) -> ShapePCA:
        if k < 2:
            raise UserError("k", f"need at least 2 inputs (log peak + 1 component), got {k}")
        S = _shapes(images)
        mean = S.mean(axis=0)
        U, sv, Vt = np.linalg.svd(S - mean, full_matrices=False)
        var = sv**2
        return cls(mean, Vt[: k - 1].copy(), (var / var.sum())[: k - 1])

    @property
    def k(self) -> int:
        return 1 + self.components.shape[0]

    def transform(self, images: np.ndarray) -> np.ndarray:
        images = np.atleast_2d(np.asarray(images, dtype=np.float64))
        pk = np.clip(np.abs(images).max(axis=1), PEAK_FLOOR, None)
        S = images / pk[:, None]
        return np.column_stack([np.log(pk), (S - self.mean) @ self.components.T])

    def to_json(self) -> dict:
        return {
            "mean": self.mean.tolist(),
            "components": self.components.tolist(),
            "explained": self.explained.tolist(),
        }

    @classmethod
    def from_json(cls, d: dict) -> ShapePCA:
        return cls(np.asarray(d["mean"], float), np.asarray(d["components"], float), np.asarray(d["explained"], float))


def _shapes(images: np.ndarray) -> np.ndarray:
    images = np.asarray(images, dtype=np.float64)
    pk = np.clip(np.abs(images).max(axis=1), PEAK_FLOOR, None)
    return images / pk[:, None]


def feature_inputs(features: np.ndarray) -> np.ndarray:
    """log O1, log O2, log O3 (relative noise becomes additive)."""
    F = np.asarray(features, dtype=float)
    return np.log(np.clip(F, 1e-12, None))


def image_inputs(
    images: np.ndarray, pca: ShapePCA, dforce: np.ndarray | None = None, force_ref: np.ndarray | None = None
) -> np.ndarray:
    """Regressor / MLP inputs of an image set: log peak, shape scores (and dF / force_ref x 100)."""
    Z = pca.transform(images)
    if dforce is not None:
        Z = np.column_stack([Z, 100.0 * np.asarray(dforce, float) / np.asarray(force_ref, float)])
    return Z
