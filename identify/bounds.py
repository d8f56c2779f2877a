"""Local bounds on (d, h, E): Jacobian, Fisher information and Cramér–Rao bounds.

Jacobian of each measurement with respect to ``theta' = (d mm, h mm, ln E)`` by **central finite
differences of a smooth surrogate** fitted to the sweep (:class:`Surrogate`: one Gaussian-process
regression per output on standardised ``(d, h, ln E)``, Matérn 5/2 ARD kernel).  The surrogate
predicts ``ln O1, ln O2, ln O3``, ``ln peak`` and the shape scores of the image
(:class:`elastimap.identify.measure.ShapePCA`) and the plate-force difference; images are reconstructed as
``peak * (mean + scores @ components)``.  The studies check it against the Jacobian from real
forward solves (:func:`elastimap.workflows.solves.fd_jacobian_solves`).

Fisher information with independent Gaussian noise ``sigma_i``: ``F = Jᵀ diag(1/sigma²) J``;
Cramér–Rao bound ``C = F⁻¹``; relative standard deviations ``sqrt(C_dd)/d``, ``sqrt(C_hh)/h`` and
``sqrt(C_lnE lnE)`` (= relative std of E to first order).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel
from tqdm import tqdm

from elastimap.dataset.schema import DESIGN_BOX, THICKNESS
from elastimap.solver.params import depth_range

from .measure import Data, ShapePCA, feature_inputs

STEP = np.array([0.05, 0.05, 0.01])  # surrogate FD steps in d (mm), h (mm), ln E


def to_param(theta: np.ndarray) -> np.ndarray:
    t = np.atleast_2d(np.asarray(theta, dtype=float))
    return np.column_stack([t[:, 0], t[:, 1], np.log(t[:, 2])])


def from_param(p: np.ndarray) -> np.ndarray:
    p = np.atleast_2d(np.asarray(p, dtype=float))
    return np.column_stack([p[:, 0], p[:, 1], np.exp(p[:, 2])])


@dataclass
class Surrogate:
    """Smooth forward surrogate theta -> (ln O, ln peak + shape scores, dF)."""

    pca: ShapePCA
    mu: np.ndarray
    sd: np.ndarray
    gps: list
    n_feat: int = 3

    @classmethod
    def fit(cls, data: Data, k: int = 16, progress: bool = False) -> Surrogate:
        P = to_param(data.theta)
        mu, sd = P.mean(0), P.std(0)
        X = (P - mu) / sd
        pca = ShapePCA.fit(data.images, k)
        Y = np.column_stack([feature_inputs(data.features), pca.transform(data.images), data.dforce])
        gps = []
        it = range(Y.shape[1])
        if progress:
            it = tqdm(it, desc="surrogate GPs", leave=False)
        for j in it:
            kern = ConstantKernel(1.0, (1e-3, 1e3)) * Matern([1.0, 1.0, 1.0], (1e-2, 1e2), nu=2.5) + WhiteKernel(
                1e-5, (1e-10, 1e-1)
            )
            gp = GaussianProcessRegressor(kern, normalize_y=True, n_restarts_optimizer=0, random_state=j)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                gp.fit(X, Y[:, j])
            gps.append(gp)
        return cls(pca, mu, sd, gps)

    def predict(self, theta: np.ndarray) -> np.ndarray:
        """Raw surrogate outputs ``(n, 3 + K + 1)`` at ``(n, 3)`` (d, h, E)."""
        X = (to_param(theta) - self.mu) / self.sd
        return self._predict_x(X)

    def _predict_x(self, X):
        return np.column_stack([gp.predict(X) for gp in self.gps])

    def split(self, out: np.ndarray):
        """-> ln features (n, 3), images (n, p), dF (n,)."""
        lnF = out[:, :3]
        k = self.pca.k
        lnpk, sc = out[:, 3], out[:, 4 : 3 + k]
        img = np.exp(lnpk)[:, None] * (self.pca.mean + sc @ self.pca.components)
        return lnF, img, out[:, 3 + k]

    def jacobians(self, theta: np.ndarray):
        """Central-difference Jacobians w.r.t. (d, h, ln E) at ``(n, 3)`` points.

        Returns dict: ``lnF`` (n, 3, 3), ``image`` (n, p, 3), ``dF`` (n, 3), and the values
        ``image0`` (n, p), ``lnF0``, ``dF0`` at the points.
        """
        P = to_param(theta)
        n = P.shape[0]
        pts = [P]
        for j in range(3):
            for s in (+1, -1):
                q = P.copy()
                q[:, j] += s * STEP[j]
                pts.append(q)
        out = self._predict_x((np.concatenate(pts) - self.mu) / self.sd)
        lnF, img, dF = self.split(out)
        sl = lambda i: slice(i * n, (i + 1) * n)  # noqa: E731
        J = {"lnF": np.zeros((n, 3, 3)), "image": np.zeros((n, img.shape[1], 3)), "dF": np.zeros((n, 3))}
        for j in range(3):
            a, b = sl(1 + 2 * j), sl(2 + 2 * j)
            J["lnF"][:, :, j] = (lnF[a] - lnF[b]) / (2 * STEP[j])
            J["image"][:, :, j] = (img[a] - img[b]) / (2 * STEP[j])
            J["dF"][:, j] = (dF[a] - dF[b]) / (2 * STEP[j])
        J["image0"], J["lnF0"], J["dF0"] = img[sl(0)], lnF[sl(0)], dF[sl(0)]
        return J


@dataclass
class NoiseSpec:
    feature: float = 0.01  # relative noise of O1, O2, O3
    image: float = 0.01  # relative (x peak) per-pixel noise, used when sigma_map is None
    sigma_map: np.ndarray | None = None  # camera noise map (mm) instead of the relative level
    force: float = 0.001  # relative noise of each plate-force reading
    force_ref: float = 1375.0  # mN, the reference plate force (for the force noise)


def fisher(J: dict, noise: NoiseSpec) -> dict:
    """Fisher matrices (n, 3, 3) for every measurement set."""
    Ji = J["image"]
    if noise.sigma_map is not None:
        w = 1.0 / np.asarray(noise.sigma_map, float).ravel() ** 2
        Fi = np.einsum("npi,p,npj->nij", Ji, w, Ji)
    else:
        sig = noise.image * np.abs(J["image0"]).max(axis=1)
        Fi = np.einsum("npi,npj->nij", Ji, Ji) / sig[:, None, None] ** 2
    sF = noise.force * noise.force_ref * np.sqrt(2.0)
    Ff = np.einsum("ni,nj->nij", J["dF"], J["dF"]) / sF**2
    return {
        "features": np.einsum("nki,nkj->nij", J["lnF"], J["lnF"]) / noise.feature**2,
        "image": Fi,
        "image+force": Fi + Ff,
        # linear forward model: the image at delta2 is (delta2/delta1) x the image at delta1; with
        # noise relative to each image's peak its Fisher matrix equals the first one -> 2 F
        "two-depths": 2.0 * Fi,
    }


def crb_relstd(F: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """(n, 3) relative standard deviations of d, h, E from Fisher matrices (n, 3, 3)."""
    theta = np.atleast_2d(theta)
    C = np.linalg.pinv(F, hermitian=True)
    sd = np.sqrt(np.clip(np.einsum("nii->ni", C), 0, None))
    return np.column_stack([sd[:, 0] / theta[:, 0], sd[:, 1] / theta[:, 1], sd[:, 2]])


def fd_relstd(J: dict, theta: np.ndarray, noise: NoiseSpec) -> dict:
    """CRB relative std ``{set: (n, 3)}`` from stacked FD Jacobians (keys image, image0, lnF, dF).

    Points whose Fisher matrix is not finite (e.g. O3 = 0, so ln O3 and its difference are
    undefined) get NaN for that set instead of poisoning the batch."""
    F = fisher(J, noise)
    out = {}
    for s, Fs in F.items():
        bad = ~np.isfinite(Fs).all(axis=(1, 2))
        r = crb_relstd(np.where(bad[:, None, None], np.eye(3), Fs), theta)
        r[bad] = np.nan
        out[s] = r
    return out


def stack(Js: list[dict]) -> dict:
    out = {}
    for k in ("image", "lnF", "dF", "image0", "lnF0"):
        out[k] = np.stack([np.asarray(J[k]) for J in Js])
    return out


def grid(nd: int = 14, nu: int = 5, nE: int = 15, d=DESIGN_BOX["d"], E=DESIGN_BOX["E"], thickness: float = THICKNESS):
    """(d, h, E) grid over the design space; h = lo + u (hi - lo) of the allowed range for d.

    Returns ``theta`` (nd*nu*nE, 3) and the axes (d, u, E) with ``theta`` in C order over them."""
    ds = np.linspace(*d, nd)
    us = np.linspace(0.1, 0.9, nu)
    Es = np.geomspace(*E, nE)
    T = []
    for dv in ds:
        lo, hi = depth_range(dv, thickness)
        for u in us:
            for Ev in Es:
                T.append((dv, lo + u * (hi - lo), Ev))
    return np.array(T), (ds, us, Es)
