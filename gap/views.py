"""Views of one phantom's measurement that the diagnosis compares with the model.

* ``features`` -- the three camera features (O1 FS, O2 FS mm², O3 mm²); their standard error
  adds the scatter over lesion frames (against the mean background) and over background frames
  (the mean lesion frame against each), se² = sd_F²/nF + sd_B²/nB;
* ``profile`` -- the radial profile of the camera difference image D (FS): the mean of D over
  the annuli r_k <= r < r_(k+1) (mm from the probe axis, :data:`EDGES`), a reduction of the
  whole image that keeps its shape (height, width, tail) and averages the pixel noise down;
* ``force`` -- the plate force (mN), when the user measured it.

Noise of the profile.  From frames F_1..F_nF (lesion) and B_1..B_nB (background) the per-pixel
standard error of the denoised difference image is

    se_D(x)² = var_k[G(F_k − B̄)](x) / nF + var_k[G(F̄ − B_k)](x) / nB

(G the same Gaussian smoothing, sigma s pixels, as the features).  Smoothing correlates
neighbouring pixels, so the standard error of an annulus mean over A pixels is
mean(se_D) / sqrt(n_eff) with n_eff = max(1, A / (4π s²)) independent pixels (the mean of a
Gaussian-smoothed white field over A ≫ s² pixels has the variance of the unsmoothed field over A).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
from scipy import ndimage

from elastimap.camera.deflection import radius_grid
from elastimap.camera.features import camera_features

from .simulate import camera_features_of

EDGES = (0.0, 1.0, 2.0, 3.0, 4.5, 6.0, 8.0, 10.0, 12.5)  # mm from the probe axis
VIEWS = ("features", "profile", "force")


def _bins(shape, pixel_mm: float, edges=EDGES) -> list[np.ndarray]:
    R = radius_grid(shape, pixel_mm)
    return [(R >= a) & (R < b) for a, b in zip(edges[:-1], edges[1:])]


def radial_profile(D: np.ndarray, pixel_mm: float, edges=EDGES) -> np.ndarray:
    """(K,) mean of the difference image over each annulus (FS)."""
    D = np.asarray(D, float)
    return np.array([D[b].mean() if b.any() else 0.0 for b in _bins(D.shape, pixel_mm, edges)])


def profile_matrix(shape, pixel_mm: float, edges=EDGES) -> np.ndarray:
    """(K, p) the annulus means of :func:`radial_profile` as a matrix on the flattened image
    (``profile = B @ D.ravel()``)."""
    out = []
    for b in _bins(shape, pixel_mm, edges):
        row = b.ravel().astype(float)
        out.append(row / row.sum() if row.any() else row)
    return np.array(out)


def profile_se(se_map: np.ndarray, pixel_mm: float, smooth_px: float, edges=EDGES) -> np.ndarray:
    """(K,) standard error of :func:`radial_profile` from a per-pixel standard-error map."""
    se_map = np.asarray(se_map, float)
    corr = 4 * math.pi * max(smooth_px, 0.5) ** 2
    out = []
    for b in _bins(se_map.shape, pixel_mm, edges):
        A = int(b.sum())
        out.append(float(se_map[b].mean() / math.sqrt(max(1.0, A / corr))) if A else 0.0)
    return np.array(out)


def difference_se(
    frames: np.ndarray, background: np.ndarray, full_scale: float, window, smooth_px: float
) -> np.ndarray:
    """Per-pixel standard error (FS) of the denoised difference image over the footprint window,
    from the frame scatter (module docstring)."""
    r0, c0, n = window
    F = np.asarray(frames, float)[:, r0 : r0 + n, c0 : c0 + n] / full_scale
    B = np.asarray(background, float)[:, r0 : r0 + n, c0 : c0 + n] / full_scale

    def g(a):
        return ndimage.gaussian_filter(a, smooth_px, mode="reflect") if smooth_px > 0 else a

    var = np.zeros((n, n))
    if F.shape[0] > 1:
        Bm = B.mean(axis=0)
        var += np.var([g(f - Bm) for f in F], axis=0, ddof=1) / F.shape[0]
    if B.shape[0] > 1:
        Fm = F.mean(axis=0)
        var += np.var([g(Fm - b) for b in B], axis=0, ddof=1) / B.shape[0]
    return np.sqrt(var)


def from_frames(frames: np.ndarray, background: np.ndarray, sensor, settings, full_scale: float | None = None) -> dict:
    """Features, their standard errors, the denoised difference image and its per-pixel standard
    error from lesion and background frames (arrays in DN; ``full_scale`` defaults to the sensor's)."""
    fs = float(full_scale or sensor.full_scale)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cf = camera_features(frames, background, fs, sensor.window, sensor.pixel_mm, settings)
    nf = max(cf.n_frames, 1)
    var = (np.asarray(cf.frame_sd) / math.sqrt(nf)) ** 2
    B = np.asarray(background, float)
    if B.ndim == 3 and B.shape[0] > 1:
        # the lesion-frame scatter misses the noise of the mean background: add the scatter of
        # the features of the mean lesion frame against each background frame
        Fm = np.asarray(frames, float).mean(axis=0)[None]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            per = np.array(
                [camera_features(Fm, b[None], fs, sensor.window, sensor.pixel_mm, settings).values for b in B]
            )
        var = var + per.var(axis=0, ddof=1) / B.shape[0]
    return {
        "values": cf.values,
        "se": np.sqrt(var),
        "difference": cf.difference,
        "difference_se": difference_se(frames, background, fs, sensor.window, settings.smooth_px),
    }


# The views of a diagnosis: simulated (from solve records; the measured ones: measured.measured_views)
# and the decision's view list.
def sim_views(recs, sensor, settings) -> tuple[dict, np.ndarray]:
    """Views {"features" (n,3), "profile" (n,K), "force" (n,1)} and difference images of records."""
    F, P, D, Fo = [], [], [], []
    for r in recs:
        v, d = camera_features_of(r, sensor, settings)
        F.append(v)
        D.append(d)
        P.append(radial_profile(d, sensor.pixel_mm) if np.all(np.isfinite(d)) else np.full(len(EDGES) - 1, np.nan))
        Fo.append([r.force])
    return {"features": np.asarray(F), "profile": np.asarray(P), "force": np.asarray(Fo, float)}, np.asarray(D)


def decision_views(mv: dict) -> list[str]:
    """The views the verdict uses: the image profile when every phantom has an image, else the
    features; plus the force when measured (the features are always reported as a view)."""
    names = ["profile"] if "profile" in mv else ["features"]
    if "force" in mv:
        names.append("force")
    return names


def cat(d: dict, names) -> np.ndarray:
    """The views ``names`` of ``d`` side by side (last axis)."""
    return np.concatenate([d[k] for k in names], axis=-1)


def slices(V: dict, names) -> dict:
    """{view: the slice of its columns in :func:`cat` of ``names``}."""
    out, a = {}, 0
    for k in names:
        q = V[k].shape[-1]
        out[k] = slice(a, a + q)
        a += q
    return out
