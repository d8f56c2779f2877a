"""A TOY analytic stand-in for the FEM, for fast tests of the camera chain only.

It is *not* physics: a bump ``amp * exp(-(r / width)^p)`` whose height, width
and profile exponent depend on (d, h, E) so that the three features identify
the three parameters, on top of a flat-punch-like probe compression with edge
peaks.  It returns an object with the attributes of
:class:`elastimap.solver.params.SolveResult` that the camera side uses (``image``,
``image_raw``, ``pixel``, ``O1``, ``O2``, ``O3``).  Never use it for results.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from elastimap.solver.image import features, pixel_centres


def toy_solve(d: float, h: float, E: float, delta: float = 3.0, size: float = 25.0, pixel: float = 0.5,
              threshold: float = 1e-3, tissue_E: float = 5.0):
    x = pixel_centres(size, pixel)
    X, Y = np.meshgrid(x, x)
    a = size / 2
    edge = np.exp(-(a - np.abs(X)) / 1.0) + np.exp(-(a - np.abs(Y)) / 1.0)
    base = 0.08 * (delta / 3.0) * (1.0 + 0.8 * edge) * (1 - 0.2 * (X ** 2 + Y ** 2) / (2 * a * a))
    amp = 0.03 * (delta / 3.0) * (d / 8.0) ** 2.2 * (8.0 / h) ** 1.6 * (max(E - tissue_E, 0.0) / 45.0) ** 0.6
    width = 0.35 * d * (1.0 - 0.2 * np.log(E / 50.0)) + 0.25 * h
    p = 1.0 + 0.12 * h                       # profile sharpness: a third, depth-driven shape parameter
    diff = amp * np.exp(-(np.sqrt(X ** 2 + Y ** 2) / width) ** p)
    o1, o2, o3 = features(diff, pixel, threshold, supersample=4)
    return SimpleNamespace(image=diff, image_raw=base + diff, pixel=pixel, O1=o1, O2=o2, O3=o3,
                           force=float("nan"), toy=True)
