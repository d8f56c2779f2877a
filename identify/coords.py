"""The physics fit's coordinates: ``x = (d, u, e)`` for ``θ = (d mm, h mm, E kPa)``.

``u = (h − lo(d)) / (hi(d) − lo(d))`` is the depth inside its admissible range (:func:`h_range`,
:func:`elastimap.solver.params.depth_range`), so the design box is a box in x; ``e`` is a coordinate
of E, ``ln E`` (:func:`to_x`, :func:`to_theta`) or Eshelby's contrast ``ln c(E)`` (:class:`FitCoords`).

Plain numbers in and out; no DOLFINx.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from elastimap.dataset.schema import DESIGN_BOX, THICKNESS
from elastimap.errors import UserError
from elastimap.solver.params import depth_range

#: the fit's coordinate of E (:class:`FitCoords`)
COORDS = ("contrast", "log")


def h_range(d: float, thickness: float = THICKNESS) -> tuple[float, float]:
    """The admissible centre depths ``(lo, hi)`` (mm) of an inclusion of diameter ``d`` (mm)."""
    return depth_range(float(d), thickness)


def to_x(theta, thickness: float = THICKNESS) -> np.ndarray:
    """``(d, u, ln E)`` of ``θ = (d mm, h mm, E kPa)``."""
    d, h, E = (float(v) for v in theta)
    lo, hi = h_range(d, thickness)
    return np.array([d, (h - lo) / (hi - lo), math.log(E)])


def to_theta(x, thickness: float = THICKNESS) -> np.ndarray:
    """``θ = (d mm, h mm, E kPa)`` of ``x = (d, u, ln E)``."""
    d, u, lnE = (float(v) for v in x)
    lo, hi = h_range(d, thickness)
    return np.array([d, lo + u * (hi - lo), math.exp(lnE)])


def dtheta_dx(x, thickness: float = THICKNESS) -> np.ndarray:
    """Jacobian of (d, h, ln E) with respect to x = (d, u, ln E)."""
    d, u = float(x[0]), float(x[1])
    lo0, hi0 = h_range(d, thickness)
    eps = 1e-6
    lo1, hi1 = h_range(d + eps, thickness)
    dh_dd = ((lo1 + u * (hi1 - lo1)) - (lo0 + u * (hi0 - lo0))) / eps
    return np.array([[1.0, 0.0, 0.0], [dh_dd, hi0 - lo0, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class FitCoords:
    """The fit's parameters ``x = (d, u, e)``: d (mm); ``u`` = (h − lo(d)) / (hi(d) − lo(d)), the
    depth inside its admissible range (:func:`h_range`); and ``e``, a coordinate of E (kPa):

    * ``"log"``: ``e = ln E``;
    * ``"contrast"``: ``e = ln c(E)``, ``c(E) = (E − a) / (E + b)`` with ``a = E_t``, ``b = 1.5 E_t``
      (``E_t`` the tissue's modulus; ``a`` at most half the box's lowest E).  Up to a constant
      ``c`` is Eshelby's strain concentration of a small sphere in an incompressible matrix,
      ``5(μ_i − μ)/(3μ + 2μ_i)`` with ``E = 3μ``: the image's amplitude goes roughly as ``d³ c(E)``,
      so the long d–E valley of equal images, ``3 ln d + ln c = const``, is close to a straight line
      in (d, e), whereas in (d, ln E) it bends (c saturates for a stiff inclusion).  A straight
      valley is what a Gauss–Newton step follows; the 95 % interval of E is taken in ``e`` and
      mapped back, so a stiff inclusion's upper end reaches the box where the image cannot tell.

    ``box(d_range, E_range)`` is the feasible set in x; ``dtheta(x)`` = ∂(d, h, ln E)/∂x."""

    thickness: float = THICKNESS
    coord: str = "contrast"
    E_tissue: float = 5.0  # kPa (solver.params.Tissue)
    E_lo: float = DESIGN_BOX["E"][0]

    def __post_init__(self):
        if self.coord not in COORDS:
            raise UserError("coords", f"must be one of {', '.join(COORDS)} (got {self.coord!r})")
        if not (math.isfinite(self.E_tissue) and self.E_tissue > 0):
            raise UserError("E_tissue", f"must be a finite modulus > 0 kPa (got {self.E_tissue})")

    @property
    def _ab(self) -> tuple[float, float]:
        return min(self.E_tissue, 0.5 * self.E_lo), 1.5 * self.E_tissue

    def x(self, theta) -> np.ndarray:
        x = to_x(theta, self.thickness)
        if self.coord == "contrast":
            a, b = self._ab
            E = float(theta[2])
            x[2] = math.log((E - a) / (E + b))
        return x

    def theta(self, x) -> np.ndarray:
        return self.thetas(np.asarray(x, dtype=float)[None, :])[0]

    def thetas(self, xs: np.ndarray) -> np.ndarray:
        """(n, 3) (d mm, h mm, E kPa) of (n, 3) fit coordinates ``xs``."""
        d, u, e = xs[:, 0], xs[:, 1], xs[:, 2]
        lo, hi = depth_range(d, self.thickness)
        if self.coord == "log":
            E = np.exp(e)
        else:
            a, b = self._ab
            c = np.exp(e)
            E = (a + b * c) / (1.0 - c)
        return np.column_stack([d, lo + u * (hi - lo), E])

    def dtheta(self, x) -> np.ndarray:
        g = dtheta_dx(x, self.thickness)
        if self.coord == "contrast":  # d ln E / d ln c
            a, b = self._ab
            E = self.theta(x)[2]
            g[2, 2] = (E + b) * (E - a) / (E * (a + b))
        return g

    def box(self, d_range, E_range) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self.x([d_range[0], 0.0, E_range[0]]), self.x([d_range[0], 0.0, E_range[1]])
        return np.array([d_range[0], 0.0, lo[2]]), np.array([d_range[1], 1.0, hi[2]])
