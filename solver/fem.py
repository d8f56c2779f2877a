r"""Finite-element model of the probe pressing the tissue (DOLFINx 0.11): the orchestrator.

Bodies Ω = Ω_tissue ∪ Ω_inclusion ∪ Ω_skin (one tissue body) and Ω_probe (three
PDMS layers) are isotropic and bonded internally.  For the displacement u (mm)
with test function v, linear elasticity reads

$$
a(u, v) = \int_\Omega \sigma(u) : \varepsilon(v) \, {\rm d}x = 0 \quad \forall v,
$$

with u = 0 on the chest wall z = 0 (or, for a compliant wall, the term of :func:`chest_wall_form`
added to a), u = (0, 0, −δ) on the probe top, u·n = 0 on
the symmetry planes of the quarter model, a traction-free tissue surface outside
the probe, and the interface law on the footprint Γ.  Each part of the maths has
its own module, with its equations next to its UFL:

==========================================  ==================================================
:mod:`~elastimap.solver.space`              mesh, P_k space, node sets (geometry only)
:mod:`~elastimap.solver.materials`          λ, μ, ε, σ, ψ_lin, ψ_NH; cell-wise E, ν, β
:mod:`~elastimap.solver.interface`          node pairs on Γ, M_Γ, gap, pressure, patch force,
                                            friction S, the contact active set
:mod:`~elastimap.solver.reduction`          u = P ū + u_D, PᵀAP ū = −PᵀA u_D, MUMPS LU
:mod:`~elastimap.solver.newton`             Newton on the reduced system (finite strain)
:mod:`~elastimap.solver.sampler`            w = u_z + δ on the pixel grid of the probe bottom
==========================================  ==================================================

:class:`Model` builds them once per sample and runs the reference solve and the
inclusion solve on them (same mesh, same forms, same sparsity): the reference press is
factorised, and the inclusion press, which differs from it by the inclusion's cells only, is
updated by those cells and solved as the difference of the two presses by CG on the reference
press's factors (docs/forward-model.md, "Shared presses").
"""

from __future__ import annotations

import time

from . import _boot  # noqa: F401  (must precede dolfinx)

# isort: split

import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI
from petsc4py import PETSc

from .errors import SolverError
from .geometry import RawMesh
from .interface import Friction, Interface, active_set
from .materials import CellMaterials, psi_blended
from .newton import Newton
from .params import SolveParams
from .reduction import CG_RTOL, LU, SINGLE_MIN_UNKNOWNS, Recycled, Reduction, Solution
from .sampler import ImageSampler
from .space import Space, petsc_matrix

__all__ = ["Model", "Solution", "SolverError"]

#: a linear solve whose inclusion modulus differs by more than this factor from the one its
#: factors were made with factorises afresh (:class:`~elastimap.solver.reduction.Recycled`)
RECYCLE_MAX_RATIO = 2.0
#: an inclusion press that would factorise afresh on a large mesh (BORROW_MIN_UNKNOWNS unknowns or
#: more: the `default` and `fine` levels) is first tried by CG on the reference press's factors
#: on the same mesh when the moduli differ by at most this factor (κ ≤ the ratio; measured on
#: the `fine` quarter model at d/h 12/10: 13-41 iterations for E/E_tissue 2-20, a sample's two
#: presses 8.9-10.1 s -> 5.8-7.6 s; docs/forward-model.md "Speed"), in at most BORROW_MAX_IT
#: iterations
BORROW_MAX_RATIO = 20.0
BORROW_MAX_IT = 50
BORROW_MIN_UNKNOWNS = 25_000
#: the inclusion press right after the reference press was factorised on the same mesh, active set
#: and plate travel (every sample's second press): CG on the reference press's factors for the difference
#: of the two presses, K(E) v = f − K(E) ū_ref (``Recycled.borrow(start=)``), on any mesh size,
#: for moduli within PRESS_MAX_RATIO of the tissue's, to PRESS_RTOL relative to that residual, in
#: at most PRESS_MAX_IT iterations (about what a factorisation costs on the `default` mesh; else
#: the inclusion's own factorisation).  Measured on `default` (docs/forward-model.md, "Shared
#: presses"): E 10-200 kPa in 9-18 iterations, O1 and O2 within 5e-7 of the factorised press's.
#: Looser was measured and not kept: 1e-5 (7-14 iterations, features within 5e-6) moved the
#: camera fit from frames (tests/camera/test_camera_frames_fem.py) from d 8.6 [7.3, 10.0] to
#: 9.9 [9.7, 10.1] mm, the truth 8 outside, since the fit differentiates the forward map and a
#: CG tolerance is noise in it; 1e-4 moved O3 (counted in 1/64 pixels) by 1.5e-4 on one of 8 samples
PRESS_MAX_RATIO = 100.0
PRESS_MAX_IT = 32
PRESS_RTOL = 1e-6
#: the same difference press on **single-precision** reference factors (``Model.single_factors``:
#: a remeshed sample's `default` level; :data:`~elastimap.solver.reduction.SINGLE_MIN_UNKNOWNS`):
#: CG on float32 factors stagnates near 1e-7 of the difference field, and at PRESS_RTOL the features
#: moved by up to 4.4e-5 from the separate presses' (64 `default` samples; stiff inclusions, E 145-200
#: kPa); at 1e-8 by up to 1.3e-6, in 26-34 instead of 17-18 iterations (docs/forward-model.md,
#: 'Shared presses')
PRESS_RTOL_SINGLE = 1e-8
#: ... in at most this many iterations: 30-34 at E/E_t = 40, the design's stiffest (d/h/E 12/8/199,
#: 2.5/4/200, 8/12/200: 30-31; 13/9/180, 15/9.5/200, 14.5/10/200: 32-34, which PRESS_MAX_IT would
#: have sent to a factorisation of their own); a float32 factorisation and its own solve cost about
#: 40 iterations of 12-15 ms
PRESS_MAX_IT_SINGLE = 48
#: the environment variable that sets how every new :class:`Model` shares its presses
#: (``shared``, the default, or ``separate``: the path before, each press factorised for itself):
#: a whole command (``infer --refine``, ``gap diagnose``) can be timed on the path before without a
#: change on its side (docs/sweep.md, 'Benchmark')
PRESSES_ENV = "ELASTIMAP_PRESSES"


def default_presses() -> str:
    """``shared`` or ``separate``: what ``$ELASTIMAP_PRESSES`` says (``shared`` when unset);
    raises :class:`~elastimap.errors.UserError` naming the variable for any other value."""
    import os

    value = os.environ.get(PRESSES_ENV, "").strip() or "shared"
    if value not in ("shared", "separate"):
        from elastimap.errors import UserError

        raise UserError(PRESSES_ENV, f"must be shared or separate (got {value!r})")
    return value


class Model:
    """One mesh with its materials, interface, reduction, image sampler and (optionally) Newton.

    ``solve(E_inclusion, delta)`` runs the configured interface law;
    ``plate_force`` and ``probe_bottom_w`` measure a solution.
    """

    def __init__(self, raw: RawMesh, p: SolveParams):
        t0 = time.perf_counter()
        self.p = p
        self.space = space = Space(raw, p)
        self.mesh, self.V = space.mesh, space.V
        self.ndofs, self.ncells = space.ndofs, space.ncells
        self.materials = CellMaterials(space.mesh, space.markers, p)
        a = self.materials.stiffness_form(space.V)
        wall = chest_wall_form(space, p.tissue.wall_compliance)
        self.a = fem.form(a if wall is None else a + wall)
        self.interface = Interface(space)
        bonded = p.disc.interface == "bonded"
        self.reduction = Reduction(space, self.interface, (0, 1, 2) if bonded else (2,), rigid_wall=wall is None)
        self.reduction.tilt = float(p.loading.tilt)
        kt = 0.0 if bonded else float(p.disc.friction_kt)
        self.friction = Friction(self.interface, kt, space.ndofs) if kt > 0 else None
        self.sampler = ImageSampler(space, p)
        self._A_values, self.A = petsc_matrix(self.a)
        # Pᵀ(K + S)P, the elastic stiffness with the rigid modes constrained, is solved by CG on
        # the factors of the last variant of the same solve kind (the inclusion's and the
        # reference's stiffness differ by the inclusion's modulus), with friction (whose K is
        # rebuilt every solve) by its own factors; each solver is made when first needed
        self.lu: LU | None = None
        self.recycled: dict[str, Recycled] = {}
        self.refactor_after: int | None = None  # Recycled's: a resolve after more CG iterations refactorises
        self.cg_rtol: float = CG_RTOL  # Recycled's CG tolerance (set before the first solve)
        self.last_linear: LU | Recycled | None = None  # what the last linear solve used (``resolve``)
        self.newton = self._finite_strain() if self.materials.beta is not None else None
        self._warm = None  # (prescribed-values key, u) of the last Newton solution
        # what the matrices hold, so that a press that differs from the last one by the inclusion's
        # modulus only updates them by the inclusion's cells (``_assemble``, ``_reduce``)
        self._version = 0  # bumped when the moduli, ν or the mesh's coordinates change
        self._A_at = None  # (version, inclusion modulus) of the values in A
        self._K_at = None  # (version, active-set key, inclusion modulus) of the reduced K
        self._unit = None  # (version, A_1, {active-set key: Pᵀ A_1 P}) for the unit-modulus inclusion
        # (version, key, δ, tilt, ū, whether the reference solver holds its own factors) of the last
        # reference press (linear, no friction)
        self._reference = None
        self.share_presses = default_presses() == "shared"
        # whether the shared presses may factorise in single precision (SINGLE_MIN_UNKNOWNS and up):
        # set by ``api.solve`` for a remeshed sample (a sweep, a single ``solve``); morphed maps (a
        # fit differentiates them) and batched variants keep double factors
        self.single_factors = False
        self.timings = {"setup": time.perf_counter() - t0}

    def set_params(self, p: SolveParams) -> None:
        """Switch to the moduli, ν and plate travel of ``p``, which must share this model's mesh
        and switches (everything but moduli, ν and loading; :mod:`elastimap.solver.batch`)."""
        self.p = p
        self.materials.set_params(p)
        self.reduction.tilt = float(p.loading.tilt)
        self.moved()

    def set_inclusion_modulus(self, p: SolveParams) -> None:
        """Switch to ``p``, which differs from this model's parameters by the inclusion's modulus
        alone: the matrices, the factors and the last reference press stay valid (each press sets
        the inclusion's cells itself, ``solve_linear``; :func:`elastimap.solver.batch.solve_group`)."""
        if self.p.with_inclusion(E=p.inclusion.E) != p or p.inclusion.core > 0:
            raise ValueError(
                "set_inclusion_modulus: the parameters differ by more than the inclusion's modulus (or have a core)"
            )
        self.p = self.materials.p = p

    @property
    def share_presses(self) -> bool:
        """False: every press assembles and reduces its whole matrix (by PETSc's default PᵀAP) and
        factorises for itself in double precision, the inclusion press first: the path before the shared presses
        (``solve(presses="separate")``, the baseline of ``sweep bench --compare``)."""
        return self._share

    @share_presses.setter
    def share_presses(self, on: bool) -> None:
        self._share = bool(on)
        self.reduction.ptap_via = "rap" if on else None

    def moved(self) -> None:
        """Say that the moduli, ν or the mesh's coordinates changed (:mod:`elastimap.solver.morph`
        moves the mesh): the next press assembles the whole matrix again."""
        self._version += 1
        if self._unit is not None:
            for M in (self._unit[1], *self._unit[2].values()):
                if M is not None:
                    M.destroy()
        if self._reference is not None:
            self._reference[4].destroy()
        self._A_at = self._K_at = self._unit = self._reference = None

    def _finite_strain(self) -> Newton:
        """Residual R(u; v) = D_u Ψ[v] and Jacobian of Ψ = ∫ ψ dx (:func:`psi_blended`)."""
        m, V = self.materials, self.space.V
        u_fun = fem.Function(V, name="u")
        psi = psi_blended(u_fun, m.E, m.nu, m.beta)
        # quadrature of degree 2(k-1): exact for the linear part (∇u of P_k is P_{k-1}), like a(u, v)
        dxq = ufl.dx(metadata={"quadrature_degree": max(2 * (self.p.disc.degree - 1), 1)})
        energy = psi * dxq
        wall = chest_wall_form(self.space, self.p.tissue.wall_compliance, u_fun)
        if wall is not None:  # the spring's energy ½ k_w |u|² on the chest wall (linear in u)
            energy = energy + wall
        R = ufl.derivative(energy, u_fun, ufl.TestFunction(V))
        J = ufl.derivative(R, u_fun, ufl.TrialFunction(V))
        return Newton(fem.form(R), fem.form(J), u_fun)

    def _tick(self, key: str, t0: float) -> float:
        t = time.perf_counter()
        self.timings[key] = self.timings.get(key, 0.0) + t - t0
        return t

    def _all_closed(self) -> np.ndarray:
        return np.ones(self.interface.npairs, dtype=bool)

    # ------------------------------------------------------------------ solves
    def solve_linear(self, E_inclusion: float, delta: float, active: np.ndarray | None = None) -> Solution:
        """One linear solve with the pairs in ``active`` closed (all pairs when None)."""
        t = time.perf_counter()
        active = self._all_closed() if active is None else active
        key = active.tobytes()
        self.materials.set_inclusion_modulus(E_inclusion)
        A_before = self._assemble(E_inclusion)
        t = self._tick("assemble", t)

        Pm, uD, new_pattern = self.reduction.operator(delta, active)
        friction = self.friction.matrices(active, self.reduction.P_csr) if self.friction is not None else None
        K, f = self._reduce(E_inclusion, A_before, key, Pm, uD, new_pattern, friction)
        t = self._tick("ptap", t)

        if friction is None:
            kind = "reference" if E_inclusion == self.p.tissue.E else "inclusion"
            if kind not in self.recycled:
                # single-precision factors on the shared path of a model that allows them only:
                # ``separate`` stays the path before, morphed and batched models keep double factors
                single_min = SINGLE_MIN_UNKNOWNS if self.share_presses and self.single_factors else None
                self.recycled[kind] = Recycled(
                    kind, rtol=self.cg_rtol, refactor_after=self.refactor_after, single_min=single_min
                )
            rec = self.last_linear = self.recycled[kind]
            # an inclusion modulus far from the factorised one (rec.tag): cond(K₀⁻¹K) up to the
            # ratio, more CG iterations than a factorisation costs (a sweep's E, not a variant's)
            E0 = E_inclusion if rec.tag is None else rec.tag
            far = max(E_inclusion / E0, E0 / E_inclusion) > RECYCLE_MAX_RATIO
            ubar = None
            if (far or rec.K0 is None) and kind == "inclusion":
                ubar = self._borrow(rec, K, f, key, E_inclusion, delta)
            if ubar is None:
                ubar = rec.solve(K, f, key, fresh=far, tag=E_inclusion)
            if kind == "reference" and self.newton is None:
                if self._reference is not None:
                    self._reference[4].destroy()
                # the factors are this very matrix's when the solve did not run CG on older ones
                own = rec.last[0] == 0
                self._reference = (self._version, key, float(delta), self.reduction.tilt, ubar.copy(), own)
        else:
            self.lu = self.lu or LU("linear", "spd")
            self.last_linear = self.lu
            ubar = self.lu.solve(K, f, new_pattern)
        t = self._tick("factor_solve", t)

        u = self.reduction.expand(Pm, ubar, uD)
        r = _mult(self.A, u)
        f.destroy()
        ubar.destroy()
        if not np.all(np.isfinite(u)):
            raise SolverError("the solve produced non-finite displacements")
        self._tick("post", t)
        return Solution(u=u, reaction=r, iterations=1)

    def _borrow(self, rec: Recycled, K, f, key: bytes, E_inclusion: float, delta: float):
        """The inclusion press by CG on the reference press's factors (``Recycled.borrow``) where
        that is cheaper than factorising, else None: right after the reference press factorised
        this mesh position, moduli, pattern and loading, for the difference of the two presses
        (PRESS_*; on older factors, e.g. a batch's next variant, its tolerance would not bound the
        features' error alike); otherwise on a large mesh, moduli within BORROW_MAX_RATIO."""
        donor = self.recycled.get("reference")
        if donor is None or donor.tag is None:
            return None
        ratio = max(E_inclusion / donor.tag, donor.tag / E_inclusion)
        ref = self._reference if self.share_presses else None
        if (
            ref is not None
            and ref[:4] == (self._version, key, float(delta), self.reduction.tilt)
            and ref[5]
            and ratio <= PRESS_MAX_RATIO
        ):
            rtol = max(PRESS_RTOL_SINGLE if donor.single else PRESS_RTOL, self.cg_rtol)
            max_it = PRESS_MAX_IT_SINGLE if donor.single else PRESS_MAX_IT
            return rec.borrow(donor, K, f, key, max_it, tag=E_inclusion, start=ref[4], rtol=rtol)
        if K.getSize()[0] < BORROW_MIN_UNKNOWNS or ratio > BORROW_MAX_RATIO:
            return None
        return rec.borrow(donor, K, f, key, BORROW_MAX_IT, tag=E_inclusion)

    # ------------------------------------------------------------------ matrices
    def _unit_inclusion(self, key: bytes | None = None, Pm=None):
        r"""A₁, the stiffness of the inclusion's cells at unit modulus (its ν),
        $a_1(u, v) = \int_{\Omega_{inc}} \sigma(u; E{=}1, \nu_{inc}) : \varepsilon(v)\,{\rm d}x$,
        so that A(E) = A(E') + (E − E') A₁ exactly (σ is linear in E at fixed ν); with ``key``, its
        reduced Pᵀ A₁ P for that active set.  Made once per mesh position and moduli; None when the
        mesh has no inclusion cells."""
        if self._unit is None or self._unit[0] != self._version:
            A1 = self._assemble_unit_inclusion()
            self._unit = (self._version, A1, {})
        _v, A1, reduced = self._unit
        if A1 is None or key is None:
            return A1
        if key not in reduced:
            reduced.clear()  # one active set at a time
            reduced[key] = self.reduction.restrict(A1, Pm)  # PᵀA₁P
        return reduced[key]

    def _assemble_unit_inclusion(self):
        from .geometry import CORE, INCLUSION
        from .materials import core_weight, epsilon, sigma

        markers = self.space.markers
        cells = np.flatnonzero(np.isin(markers, (INCLUSION, CORE))).astype(np.int32)
        if cells.size == 0:
            return None
        if getattr(self, "_a1", None) is None:
            from dolfinx import mesh as dmesh

            tags = dmesh.meshtags(self.mesh, 3, cells, markers[cells].astype(np.int32))
            dx = ufl.Measure("dx", domain=self.mesh, subdomain_data=tags)
            u, v = ufl.TrialFunction(self.V), ufl.TestFunction(self.V)
            a1 = ufl.inner(sigma(u, 1.0, self.materials.nu), epsilon(v)) * dx(INCLUSION)
            if np.any(markers == CORE):  # a core/shell inclusion: the core takes w of each change
                self._a1_core = fem.Constant(self.mesh, 0.0)
                a1 = a1 + self._a1_core * ufl.inner(sigma(u, 1.0, self.materials.nu), epsilon(v)) * dx(CORE)
            self._a1 = fem.form(a1)
        if getattr(self, "_a1_core", None) is not None:
            self._a1_core.value = core_weight(self.p)  # w follows the parameters (set_params)
        # A₁'s values live in the CSR matrix ``_a1_values`` (kept with the form; ``petsc_matrix``)
        self._a1_values, A1 = petsc_matrix(self._a1)
        fem.assemble_matrix(self._a1_values, self._a1)
        A1.assemble()
        return A1

    def _assemble(self, E_inclusion: float) -> float | None:
        """A := A(E_inclusion): by the inclusion's cells, A += (E − E_A) A₁, when A holds this mesh's
        matrix at another inclusion modulus E_A; else assembled afresh.  Returns E_A (None: afresh)."""
        at = self._A_at
        if self.share_presses and at is not None and at[0] == self._version and self._unit_inclusion() is not None:
            if E_inclusion != at[1]:
                self.A.axpy(E_inclusion - at[1], self._unit_inclusion(), PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
            self._A_at = (self._version, E_inclusion)
            return at[1]
        self._A_values.set_value(0.0)
        fem.assemble_matrix(self._A_values, self.a)  # into A's values (``space.petsc_matrix``)
        self.A.assemble()
        self._A_at = (self._version, E_inclusion)
        return None

    def _reduce(self, E_inclusion: float, A_before, key: bytes, Pm, uD, new_pattern: bool, friction):
        """The reduced (K, f) of A(E_inclusion): K updated by the inclusion's cells when it holds
        Pᵀ A P of this mesh at another modulus on the same active set (``Reduction.increment``),
        else K = PᵀAP afresh (``Reduction.reduce``)."""
        at = self._K_at
        if (
            friction is None
            and not new_pattern
            and A_before is not None
            and at is not None
            and at[:2] == (self._version, key)
        ):
            K, f = self.reduction.increment(self.A, Pm, uD, self._unit_inclusion(key, Pm), E_inclusion - at[2])
        else:
            K, f, _new = self.reduction.reduce(self.A, Pm, uD, new_pattern, friction)
        self._K_at = (self._version, key, E_inclusion) if friction is None else None
        return K, f

    def solve_nonlinear(
        self,
        E_inclusion: float,
        delta: float,
        active: np.ndarray | None = None,
        rtol: float = 1e-9,
        max_iter: int = 30,
        load_steps: int = 4,
    ) -> Solution:
        """Finite-strain tissue: Newton (:mod:`elastimap.solver.newton`) from the linear solution,
        in ``load_steps`` increments of the plate travel when there is no warm start."""
        active = self._all_closed() if active is None else active
        lin = self.solve_linear(E_inclusion, delta, active)
        t = time.perf_counter()
        Pm, _uD, _ = self.reduction.operator(delta, active)
        Psp = self.reduction.P_csr
        friction = self.friction.matrices(active, Psp) if self.friction is not None else None
        # warm start from the last converged solution with the same prescribed values (the
        # reference solve after the inclusion solve: a few Newton steps instead of ~20)
        key = (float(delta), float(self.reduction.tilt), active.tobytes())
        start = self._warm[1] if self._warm is not None and self._warm[0] == key else None
        cold = start is None and load_steps > 1
        if cold:
            # a cold start: the linear solution is a poor predictor for the nearly incompressible
            # tissue (λ ln J ~ λ|∇u|² at the plate's edge), Newton from it needs damped steps
            # (24 iterations at β = 1, coarse mesh; the β ≈ 1 data of the seed-5 blind run
            # failed).  Load stepping δ_k = k δ / K, each step predicted by the quadratic
            # extrapolation of the nonlinear correction u − u_lin ∝ δ², takes full steps.
            # Without tilt u_D ∝ δ, so the linear solution at δ_k is (δ_k/δ) u_lin (u and A u
            # scale alike): no solve; a tilted plate's u_D = −(δ + tilt x) is not, and is solved.
            corr, pre = None, 0
            for k in range(1, load_steps):
                dk = delta * k / load_steps
                if self.reduction.tilt:
                    lin_k = self.solve_linear(E_inclusion, dk, active)
                else:
                    s = k / load_steps
                    lin_k = Solution(u=s * lin.u, reaction=s * lin.reaction, iterations=lin.iterations)
                Pk, _uk, _ = self.reduction.operator(dk, active)
                Pks = self.reduction.P_csr
                fk = self.friction.matrices(active, Pks) if self.friction is not None else None
                st = None if corr is None else lin_k.u + (k / (k - 1)) ** 2 * corr
                s_k = self.newton.solve(lin_k, Pk, Pks, key[2], fk, rtol=1e-4, max_iter=max_iter, start=st)
                corr, pre = s_k.u - lin_k.u, pre + s_k.iterations
            start = lin.u + (load_steps / (load_steps - 1)) ** 2 * corr
            Pm, _uD, _ = self.reduction.operator(delta, active)
            Psp = self.reduction.P_csr
        sol = self.newton.solve(lin, Pm, Psp, key[2], friction, rtol=rtol, max_iter=max_iter, start=start)
        sol.iterations += pre if cold else 0
        self._warm = (key, sol.u)
        self._tick("newton", t)
        return sol

    def _solve_once(self, E_inclusion: float, delta: float, active: np.ndarray | None = None) -> Solution:
        if self.newton is not None:
            return self.solve_nonlinear(E_inclusion, delta, active)
        return self.solve_linear(E_inclusion, delta, active)

    def solve(self, E_inclusion: float, delta: float, max_iter: int = 30) -> tuple[Solution, dict]:
        """Solve with the configured interface law; returns the solution and interface diagnostics."""
        itf = self.interface
        if self.p.disc.interface == "contact":
            sol, active, its = active_set(
                lambda act: self._solve_once(E_inclusion, delta, act),
                lambda s: itf.patch_force(s.reaction),
                lambda s: itf.gap(s.u),
                self._all_closed(),
                gap_tol=1e-9 * delta,
                max_iter=max_iter,
            )
        else:
            active = self._all_closed()
            sol = self._solve_once(E_inclusion, delta, active)
            its = sol.iterations
        sol.iterations = its
        return sol, itf.diagnostics(sol.u, sol.reaction, active)

    # ------------------------------------------------------------------ measures
    def plate_force(self, sol: Solution) -> float:
        """Total force (mN) the plate applies on the probe, compressive positive, full probe."""
        f = -float(np.sum(sol.reaction[3 * self.space.top + 2]))
        return 4 * f if self.p.disc.symmetry == "quarter" else f

    def probe_bottom_w(self, sol: Solution, delta: float) -> np.ndarray:
        """Deflection of the probe bottom relative to the plate, u_z + δ (+ tilt · x for a tilted
        plate: the compression of the probe under the plate point above the pixel; mm), on the pixel grid."""
        t = time.perf_counter()
        w = self.sampler.deflection(sol.u, delta)
        if self.reduction.tilt:
            w = w + self.reduction.tilt * self.sampler.points[:, 0].reshape(w.shape)
        self._tick("image", t)
        return w

    def destroy(self) -> None:
        self.moved()  # drops the unit-modulus matrices and the reference solution
        for part in (self.lu, *self.recycled.values(), self.reduction, self.friction, self.newton, self.interface):
            if part is not None:
                part.destroy()
        if self.A is not None:
            self.A.destroy()
            self.A = self._A_values = None


#: the facet tag of the chest wall z = 0 in :func:`chest_wall_form`'s measure
WALL_TAG = 1


def chest_wall_form(space, compliance: float, u_energy=None):
    r"""The compliant chest wall's term of the weak form; None for a rigid wall (``compliance`` 0).

    A chest wall of compliance c_w (mm/kPa; ``Tissue.wall_compliance``) is an isotropic Winkler
    foundation under the slab's bottom face Γ_w (z = 0): the traction there is t = −k_w u with
    k_w = 1 / c_w (kPa/mm), which adds to a(u, v)

    $$
    a_w(u, v) = \int_{\Gamma_w} k_w \, u \cdot v \, {\rm d}s
    $$

    (kPa/mm · mm · mm · mm² = mN mm, like ∫ σ(u) : ε(v) dx), in place of the Dirichlet condition
    u = 0 there (:class:`elastimap.solver.reduction.Reduction`, ``rigid_wall``).  With ``u_energy``
    (a Function, the finite-strain path) it returns the spring's stored energy ½ ∫_Γw k_w |u|² ds
    instead, whose derivatives are the same term.  The slab's outer faces stay traction-free; the
    probe body has no face on z = 0.
    """
    if compliance == 0:
        return None
    from dolfinx import mesh as dmesh

    msh = space.mesh
    facets = dmesh.locate_entities_boundary(msh, 2, lambda x: np.abs(x[2]) < space.tol)
    tags = dmesh.meshtags(msh, 2, facets.astype(np.int32), np.full(facets.size, WALL_TAG, dtype=np.int32))
    ds = ufl.Measure("ds", domain=msh, subdomain_data=tags)(WALL_TAG)
    k_w = fem.Constant(msh, PETSc.ScalarType(1.0 / compliance))  # kPa/mm
    if u_energy is not None:
        return 0.5 * k_w * ufl.inner(u_energy, u_energy) * ds
    u, v = ufl.TrialFunction(space.V), ufl.TestFunction(space.V)
    return k_w * ufl.inner(u, v) * ds


def _mult(A: PETSc.Mat, x: np.ndarray) -> np.ndarray:
    """A x for a numpy vector (the nodal reaction r = A u, mN)."""
    vx = PETSc.Vec().createWithArray(x, comm=MPI.COMM_SELF)
    y = A.createVecLeft()
    A.mult(vx, y)
    out = y.getArray().copy()
    vx.destroy()
    y.destroy()
    return out
