"""Where an estimate of (d, h, E) can be trusted: the identifiability map used by inference.

The map holds, on the grid of :func:`elastimap.identify.bounds.grid` (d, depth fraction u, E), the Cramér–Rao
relative standard deviation ``r_q = sqrt(C_qq) / q`` (``C = F⁻¹``, ``F`` the Fisher information of
the measurement set under the camera noise of :mod:`elastimap.workflows.studies.crbmap`) of each output
``q ∈ {d, h, E}``.  ``r_q`` is a *lower* bound on the relative error of any unbiased estimator at
that point, so

* ``r_q > threshold`` (default 10 %): ``q`` is **not identifiable** there; an estimate landing there
  is flagged ``non_identifiable:q``;
* every estimate gets an interval at least as wide as the bound's approximate 95 % interval,
  log-normal so it stays positive, ``[q e^(-2 r_q), q e^(2 r_q)]``, widened to the ensemble's
  10–90 % range and clipped to the training range of ``q``.  Where ``q`` is not identifiable the
  interval is wide (for E at ``r_E = 0.5`` it spans a factor e² ≈ 7.4) and is reported in place of
  a number.

``r`` is interpolated linearly in ``(d, u, ln E)`` of ``ln r`` (the bound spans decades); estimates
outside the map's box are flagged ``outside_identifiability_map`` and evaluated at the nearest
point of the box.  Depth fraction ``u = (h - h_lo(d)) / (h_hi(d) - h_lo(d))`` with
:func:`elastimap.solver.params.depth_range` (pure Python; no DOLFINx).

The sets ``features``, ``image``, ``image+force`` and ``two-depths`` assume 1 % noise (of each
feature, of the image's peak per pixel).  ``camera`` is the bound from the nominal SYNTHETIC
camera's frames: per-pixel shot and read noise through the optics (``camera_sigma``, mm per image
pixel, for ``camera_frames`` lesion and background frames), the same for every lesion, so large
shallow inclusions are measured far better than 1 % of their peak and small deep ones far worse
(``python -m elastimap.workflows.studies.cameramap``).  Inference from frames scales it by the
frames' own noise (:meth:`IdentifiabilityMap.camera_scale`).

Maps come from ``python -m elastimap.workflows.studies.crbmap`` (file ``crb_grid.npz``); the package ships the one
measured on the default 512-sample sweep and scaled with real finite differences on the morphed forward
map (:data:`DEFAULT_MAP`, ``identify/maps/default.npz``), used when none is given and written by that
study's ``--install``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from elastimap.dataset.schema import TARGETS, THICKNESS
from elastimap.errors import UserError
from elastimap.solver.params import depth_range

DEFAULT_MAP = os.path.join(os.path.dirname(__file__), "maps", "default.npz")
#: measurement sets; "camera": the nominal SYNTHETIC camera's frames (per-pixel shot and read noise
#: through the optics, python -m elastimap.workflows.studies.cameramap), the others 1 % noise
SETS = ("features", "image", "image+force", "two-depths", "camera")
#: what inference from camera frames uses: per output the larger of the ``camera`` bound (the
#: frames' noise) and the ``image`` bound (1 % of the peak, about the forward model's own error at
#: the mesh levels it runs on: 0.1-1.3 % of the peak, docs/identifiability.md, 'What camera frames identify') -- an estimate
#: from frames is no better than either allows
FRAMES = "frames"


@dataclass
class Assessment:
    """Per estimate: bound ``r`` (n, 3), interval ``lo``/``hi`` (n, 3) and flags (list per row)."""

    r: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    flags: list[list[str]] = field(default_factory=list)
    identifiable: np.ndarray | None = None  # (n, 3) bool


@dataclass
class IdentifiabilityMap:
    d: np.ndarray  # (nd,) mm
    u: np.ndarray  # (nu,) depth fraction of the allowed centre-depth range
    E: np.ndarray  # (nE,) kPa
    relstd: dict  # set -> (nd, nu, nE, 3) Cramér–Rao relative std of d, h, E
    thickness: float = THICKNESS  # mm, tissue slab of the sweep the map was made on
    source: str = ""
    camera_sigma: np.ndarray | None = None  # (ny, nx) mm: the "camera" set's per-pixel noise
    camera_frames: int = 0  # frames (lesion and background each) the "camera" set assumes

    # ------------------------------------------------------------------ io
    @classmethod
    def load(cls, path: str | os.PathLike | None = None) -> IdentifiabilityMap:
        p = str(path) if path else DEFAULT_MAP
        if not os.path.isfile(p):
            raise UserError(
                "identifiability", f"{p}: no such map file (make one with python -m elastimap.workflows.studies.crbmap)"
            )
        try:
            z = np.load(p, allow_pickle=False)
            d, u, E = (np.asarray(z[k], float) for k in ("d", "u", "E"))
            shape = (d.size, u.size, E.size, 3)
            rel = {s: np.asarray(z[s], float).reshape(shape) for s in SETS if s in z.files}
            thickness = float(z["thickness"]) if "thickness" in z.files else THICKNESS
            source = str(z["source"]) if "source" in z.files else p
            cam_sigma = np.asarray(z["camera_sigma"], float) if "camera_sigma" in z.files else None
            cam_frames = int(z["camera_frames"]) if "camera_frames" in z.files else 0
        except (KeyError, ValueError, OSError) as exc:
            raise UserError("identifiability", f"{p}: not an identifiability map ({exc})") from None
        if not rel:
            raise UserError("identifiability", f"{p}: holds none of the measurement sets {', '.join(SETS)}")
        if "camera" in rel and cam_sigma is None:
            raise UserError("identifiability", f"{p}: its camera set has no camera_sigma (the noise it assumes)")
        return cls(d, u, E, rel, thickness, source, cam_sigma, cam_frames)

    def save(self, path: str | os.PathLike) -> None:
        extra = {}
        if self.camera_sigma is not None:
            extra = {"camera_sigma": self.camera_sigma, "camera_frames": self.camera_frames}
        np.savez(
            path,
            d=self.d,
            u=self.u,
            E=self.E,
            thickness=self.thickness,
            source=self.source,
            **extra,
            **{s: v.reshape(-1, 3) for s, v in self.relstd.items()},
        )

    def camera_scale(self, sigma: np.ndarray, image: np.ndarray | None = None) -> float:
        """How much the "camera" set's bound grows for frames with per-pixel noise ``sigma`` (mm,
        the map's image shape): the bound scales with the noise (F ∝ σ⁻²), so the factor is the
        median over the pixels of σ / ``camera_sigma`` -- over the pixels where ``image`` is above
        10 % of its peak when given (there the information is).  1 for the nominal camera at
        ``camera_frames`` frames; √(``camera_frames`` / n) for n frames of it."""
        if self.camera_sigma is None:
            raise UserError("identifiability", "the map has no camera set")
        s = np.asarray(sigma, float).ravel()
        ref = self.camera_sigma.ravel()
        if s.size != ref.size:
            raise UserError(
                "sigma", f"{s.size} pixels; the map's camera set is on {ref.size} ({self.camera_sigma.shape})"
            )
        keep = np.isfinite(s) & (s > 0)
        if image is not None:
            img = np.abs(np.asarray(image, float).ravel())
            if img.size == s.size and img.max() > 0:
                keep &= img >= 0.1 * img.max()
        if not keep.any():
            raise UserError("sigma", "no finite positive pixel noise")
        return float(np.median(s[keep] / ref[keep]))

    # ------------------------------------------------------------------ evaluation
    def coords(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) grid coordinates (d, u, ln E) clipped to the box, and (n,) bool: was inside."""
        theta = np.atleast_2d(np.asarray(theta, float))
        lo, hi = np.array([depth_range(max(dv, 1e-6), self.thickness) for dv in theta[:, 0]]).T
        u = (theta[:, 1] - lo) / np.where(hi > lo, hi - lo, 1.0)
        x = np.column_stack([theta[:, 0], u, np.log(np.clip(theta[:, 2], 1e-12, None))])
        box_lo = np.array([self.d[0], self.u[0], np.log(self.E[0])])
        box_hi = np.array([self.d[-1], self.u[-1], np.log(self.E[-1])])
        tol = 1e-9 + 1e-6 * (box_hi - box_lo)
        inside = np.all((x >= box_lo - tol) & (x <= box_hi + tol), axis=1) & np.all(np.isfinite(theta), axis=1)
        return np.clip(np.nan_to_num(x, nan=0.0), box_lo, box_hi), inside

    def bound(self, theta: np.ndarray, mset: str, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Cramér–Rao relative std (n, 3) at ``theta`` for measurement set ``mset`` (times ``scale``,
        e.g. :meth:`camera_scale`), and ``inside``.  ``mset = "frames"``: the larger of the
        ``camera`` set times ``scale`` and the ``image`` set (see :data:`FRAMES`)."""
        if not (np.isfinite(scale) and scale > 0):
            raise UserError("scale", f"must be finite and > 0 (got {scale})")
        if mset == FRAMES:
            rc, inside = self.bound(theta, "camera", scale)
            return np.maximum(rc, self.bound(theta, "image")[0]), inside
        if mset not in self.relstd:
            raise UserError("identifiability", f"the map has no set {mset!r} (has {', '.join(self.relstd)})")
        x, inside = self.coords(theta)
        R = np.log(np.clip(self.relstd[mset], 1e-12, None))
        axes = (self.d, self.u, np.log(self.E))
        r = np.column_stack([np.exp(RegularGridInterpolator(axes, R[..., j])(x)) for j in range(3)])
        return r * scale, inside

    def assess(
        self,
        mean: np.ndarray,
        mset: str,
        threshold: float = 0.10,
        p10: np.ndarray | None = None,
        p90: np.ndarray | None = None,
        target_range: np.ndarray | None = None,
        scale: float = 1.0,
    ) -> Assessment:
        """Flags and intervals for estimates ``mean`` (n, 3) (see the module docstring); ``scale``
        multiplies the bound (:meth:`bound`)."""
        if not 0 < threshold < 10:
            raise UserError("threshold", f"must be in (0, 10) (got {threshold:g})")
        mean = np.atleast_2d(np.asarray(mean, float))
        r, inside = self.bound(mean, mset, scale)
        pos = np.clip(mean, 1e-12, None)
        lo, hi = pos * np.exp(-2.0 * r), pos * np.exp(2.0 * r)
        if p10 is not None:
            lo = np.minimum(lo, np.asarray(p10, float))
        if p90 is not None:
            hi = np.maximum(hi, np.asarray(p90, float))
        if target_range is not None:
            tr = np.asarray(target_range, float)
            lo, hi = np.clip(lo, tr[0], tr[1]), np.clip(hi, tr[0], tr[1])
        ok = r <= threshold
        flags = []
        for i in range(mean.shape[0]):
            f = [f"non_identifiable:{q}" for j, q in enumerate(TARGETS) if not ok[i, j]]
            if not inside[i]:
                f.append("outside_identifiability_map")
            flags.append(f)
        return Assessment(r, lo, hi, flags, ok)
