"""A TOY analytic stand-in for the FEM, for fast tests of the camera chain only.

It is *not* physics: a Gaussian bump whose height and width grow with d and E
and shrink with depth, on top of a flat-punch-like probe compression with edge
peaks.  It returns an object with the attributes of
:class:`solver.params.SolveResult` that the camera side uses (``image``,
``image_raw``, ``pixel``, ``O1``, ``O2``, ``O3``).  Never use it for results.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from solver.image import features, pixel_centres


def toy_solve(d: float, h: float, E: float, delta: float = 3.0, size: float = 25.0, pixel: float = 0.5,
              threshold: float = 1e-3, tissue_E: float = 5.0):
    x = pixel_centres(size, pixel)
    X, Y = np.meshgrid(x, x)
    a = size / 2
    edge = np.exp(-(a - np.abs(X)) / 1.0) + np.exp(-(a - np.abs(Y)) / 1.0)
    base = 0.08 * (delta / 3.0) * (1.0 + 0.8 * edge) * (1 - 0.2 * (X ** 2 + Y ** 2) / (2 * a * a))
    amp = 0.03 * (delta / 3.0) * (d / 8.0) ** 2.2 * (8.0 / h) ** 1.6 * (E - tissue_E) / (E + 25.0)
    width = 0.3 * d + 0.35 * h
    diff = amp * np.exp(-(X ** 2 + Y ** 2) / (2 * width ** 2))
    o1, o2, o3 = features(diff, pixel, threshold)
    return SimpleNamespace(image=diff, image_raw=base + diff, pixel=pixel, O1=o1, O2=o2, O3=o3,
                           force=float("nan"), toy=True)
