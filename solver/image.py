"""The elasticity image and its three features (paper section 3.2).

An elasticity image here is a 2-D array of probe-bottom deflection in mm on a
regular pixel grid (pixel side ``pixel`` mm).  The features follow the paper:

* O1 = max_ij w_ij                       (mm)   maximum deformation
* O2 = sum_ij w_ij                       (mm)   total deformation
* O3 = area{ w > threshold }             (mm^2) deformed area

O3 is measured on a bilinear ``supersample``-times upsampling of the image so
that it changes continuously with the field instead of in whole pixels.
This module is pure numpy: the camera side uses the same definitions.
"""

from __future__ import annotations

import numpy as np


def upsample_bilinear(img: np.ndarray, factor: int) -> np.ndarray:
    """Bilinear upsampling of a cell-centred image by an integer factor.

    Sub-pixel centres are placed at the centres of the ``factor x factor``
    sub-cells of each pixel; values outside the outer pixel centres are held
    constant (edge clamp).
    """
    img = np.asarray(img, dtype=float)
    if factor == 1:
        return img
    ny, nx = img.shape

    def coords(n):
        c = (np.arange(n * factor) + 0.5) / factor - 0.5  # sub-cell centre in pixel-index units
        return np.clip(c, 0, n - 1)

    def along_rows(a: np.ndarray, n: int) -> np.ndarray:
        # bilinear interpolation is separable: each sub-cell centre mixes the two pixel centres
        # around it with the weights (1 − t, t), rows first, then columns
        c = coords(n)
        if n == 1:
            return np.repeat(a[:1], c.size, axis=0)
        i0 = np.minimum(np.floor(c).astype(int), n - 2)
        t = (c - i0)[:, None]
        return (1 - t) * a[i0] + t * a[np.minimum(i0 + 1, n - 1)]

    return along_rows(along_rows(img, ny).T, nx).T


def features(
    img: np.ndarray, pixel: float, threshold: float = 1e-3, supersample: int = 8
) -> tuple[float, float, float]:
    """Return (O1 mm, O2 mm, O3 mm^2) of an elasticity image with square pixels of ``pixel`` mm."""
    img = np.asarray(img, dtype=float)
    if img.ndim != 2 or img.size == 0:
        raise ValueError(f"an elasticity image must be a non-empty 2-D array (got shape {img.shape})")
    if not np.all(np.isfinite(img)):
        raise ValueError("the elasticity image contains NaN or inf")
    o1 = float(img.max())
    o2 = float(img.sum())
    fine = upsample_bilinear(img, supersample)
    o3 = float(np.count_nonzero(fine > threshold)) * (pixel / supersample) ** 2
    return o1, o2, o3


def pixel_centres(size: float, pixel: float) -> np.ndarray:
    """Pixel-centre coordinates (mm) across a footprint of side ``size`` centred on 0."""
    n = int(round(size / pixel))
    return -size / 2 + pixel * (np.arange(n) + 0.5)


def mirror_quarter(q: np.ndarray) -> np.ndarray:
    """Full image from the quadrant x > 0, y > 0 (rows = y ascending, cols = x ascending)."""
    top = np.concatenate([q[:, ::-1], q], axis=1)
    return np.concatenate([top[::-1, :], top], axis=0)
