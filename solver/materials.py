r"""Materials: Lamé constants, strain, stress and stored energy, and the cell-wise moduli.

Every body is isotropic.  With Young's modulus E in kPa and lengths in mm, stresses
and stored energies are in kPa and nodal forces in kPa·mm² = mN.  The tissue, skin,
inclusion and the three PDMS layers differ only in (E, ν), held cell-wise by
:class:`CellMaterials`; the finite-strain effect switch adds a cell-wise blend
factor β (0 = linear elastic).
"""

from __future__ import annotations

from . import _boot  # noqa: F401  (must precede dolfinx)

# isort: split

import numpy as np
import ufl
from dolfinx import fem

from .geometry import CORE, INCLUSION, PROBE_LAYER0, SKIN, TISSUE
from .params import SolveParams


def lame(E, nu):
    r"""Lamé constants (μ, λ) in the units of E, for numbers or UFL expressions:

    $$
    \mu = \frac{E}{2(1 + \nu)}, \qquad \lambda = \frac{E \nu}{(1 + \nu)(1 - 2\nu)} .
    $$
    """
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


def epsilon(u):
    r"""Small-strain tensor (dimensionless)

    $$ \varepsilon(u) = \tfrac12 \left( \nabla u + \nabla u^{T} \right) . $$
    """
    return ufl.sym(ufl.grad(u))


def sigma(u, E, nu):
    r"""Linear isotropic stress (kPa for E in kPa)

    $$ \sigma(u) = 2 \mu \, \varepsilon(u) + \lambda \, {\rm tr}\,\varepsilon(u) \, I ; $$

    the bilinear form of linear elasticity is
    $a(u, v) = \int_\Omega \sigma(u) : \varepsilon(v) \, {\rm d}x$ (mN·mm).
    """
    mu, lmbda = lame(E, nu)
    return 2 * mu * epsilon(u) + lmbda * ufl.tr(epsilon(u)) * ufl.Identity(len(u))


def psi_linear(u, E, nu):
    r"""Linear-elastic stored energy density (kPa)

    $$ \psi_{\rm lin} = \mu \, \varepsilon : \varepsilon + \tfrac12 \lambda \, ({\rm tr}\,\varepsilon)^2 . $$
    """
    mu, lmbda = lame(E, nu)
    eps = epsilon(u)
    return mu * ufl.inner(eps, eps) + 0.5 * lmbda * ufl.tr(eps) ** 2


def psi_neo_hookean(u, E, nu):
    r"""Compressible neo-Hookean stored energy density (kPa)

    $$
    \psi_{\rm NH} = \tfrac12 \mu \, (I_C - 3) - \mu \ln J + \tfrac12 \lambda \, (\ln J)^2,
    \qquad F = I + \nabla u, \quad C = F^{T} F, \quad I_C = {\rm tr}\, C, \quad J = \det F,
    $$

    with the Lamé constants of :func:`sigma`, so that its linearisation at u = 0 is the
    linear model.
    """
    mu, lmbda = lame(E, nu)
    F = ufl.Identity(len(u)) + ufl.grad(u)
    Ic = ufl.tr(F.T * F)
    lnJ = ufl.ln(ufl.det(F))
    return 0.5 * mu * (Ic - 3) - mu * lnJ + 0.5 * lmbda * lnJ**2


def psi_blended(u, E, nu, beta):
    r"""Stored energy density of the ``Tissue.nonlinearity`` switch (kPa)

    $$ \psi = (1 - \beta) \, \psi_{\rm lin} + \beta \, \psi_{\rm NH}, \qquad \beta \in [0, 1] ; $$

    β = 0 is linear elasticity, β = 1 the plain neo-Hookean solid.
    """
    return (1 - beta) * psi_linear(u, E, nu) + beta * psi_neo_hookean(u, E, nu)


def core_weight(p: SolveParams) -> float:
    r"""w, the core's share of an inclusion-modulus change (``Inclusion.core``; 0 without a core).

    A press sets every inclusion cell from one inclusion modulus E_inc (E_inc = E_t: the
    reference press, the tissue without the inclusion; E_inc = E: the inclusion press).  The
    core follows it affinely,

    $$ E_{\rm core}(E_{\rm inc}) = E_t + w\,(E_{\rm inc} - E_t), \qquad
       w = \frac{\kappa E - E_t}{E - E_t}, $$

    so that E_core = E_t in the reference press, κE (κ = ``core_ratio``) in the inclusion press,
    and the stiffness stays affine in E_inc (A(E) = A(E') + (E − E') A₁, A₁ with weight w on
    the core: ``fem.Model``'s shared presses hold for a core/shell inclusion too).
    """
    inc, Et = p.inclusion, p.tissue.E
    return (inc.core_ratio * inc.E - Et) / (inc.E - Et) if inc.core > 0 else 0.0


class CellMaterials:
    """Piecewise-constant (DG0) fields E (kPa), ν and, with the finite-strain switch, β.

    Cells take their values from their marker: tissue (E_t, ν_t), skin (skin_E, ν_t),
    inclusion (E, ν_inc), a core/shell inclusion's core (:func:`core_weight`), probe layer i
    (E_i, ν_probe).  β is ``Tissue.nonlinearity``
    on the tissue bodies and 0 on the probe (the PDMS is 10–60 times stiffer than the
    tissue, so its strains stay small); ``beta`` is None when the switch is off.
    """

    def __init__(self, msh, markers: np.ndarray, p: SolveParams):
        self.p = p
        self.markers = markers
        Q = fem.functionspace(msh, ("DG", 0))
        self.E = fem.Function(Q, name="E")
        self.nu = fem.Function(Q, name="nu")
        self.set_inclusion_modulus(p.inclusion.E)
        self.beta = None
        if p.tissue.nonlinearity > 0:
            self.beta = fem.Function(Q, name="beta")
            b = np.where(markers >= PROBE_LAYER0, 0.0, float(p.tissue.nonlinearity))
            self.beta.x.array[: len(b)] = b

    def set_params(self, p: SolveParams) -> None:
        """Take the moduli, ν and β of ``p`` (same mesh): the forms see the new values at their
        next assembly, so nothing is rebuilt (:func:`elastimap.solver.batch.solve_batch`)."""
        self.p = p
        self.set_inclusion_modulus(p.inclusion.E)
        if self.beta is not None:
            b = np.where(self.markers >= PROBE_LAYER0, 0.0, float(p.tissue.nonlinearity))
            self.beta.x.array[: len(b)] = b

    def set_inclusion_modulus(self, E_inclusion: float) -> None:
        """Fill E and ν from the markers, with the inclusion's modulus set to ``E_inclusion`` (kPa)."""
        p, m = self.p, self.markers
        E = np.empty(len(m))
        nu = np.empty(len(m))
        E[m == TISSUE], nu[m == TISSUE] = p.tissue.E, p.tissue.nu
        E[m == SKIN], nu[m == SKIN] = p.tissue.skin_E, p.tissue.nu
        E[m == INCLUSION], nu[m == INCLUSION] = E_inclusion, p.inclusion.nu
        w = core_weight(p)
        E[m == CORE], nu[m == CORE] = p.tissue.E + w * (E_inclusion - p.tissue.E), p.inclusion.nu
        for i, (_th, El) in enumerate(p.probe.layers):
            sel = m == PROBE_LAYER0 + i
            E[sel], nu[sel] = El, p.probe.nu
        self.E.x.array[: len(E)] = E
        self.nu.x.array[: len(nu)] = nu

    def stiffness_form(self, V):
        """The bilinear form a(u, v) = ∫ σ(u) : ε(v) dx on ``V`` (see :func:`sigma`)."""
        u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
        return ufl.inner(sigma(u, self.E, self.nu), epsilon(v)) * ufl.dx
