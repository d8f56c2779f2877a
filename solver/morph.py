r"""Mesh morphing: a reference mesh moved smoothly to the inclusion's diameter d and depth h.

Remeshing every (d, h) with gmsh makes the forward map jitter at the scale of the mesh
(central differences in d or h depend on the step).  Here a reference mesh, built by gmsh
once at (d₀, h₀), is moved to (d, h) by a mesh motion that is exactly affine in (d, h):

$$
x(d, h) = x_0 + (h_0 - h) \, U_h + \left(\frac{d}{d_0} - 1\right) U_s \qquad {\rm (mm)},
$$

where U_h and U_s are two unit motions of the tissue body computed once per reference
mesh, each the discrete solution (P1, one component at a time) of a mesh-Laplace problem

$$
\nabla \cdot \big( k \, \nabla U_c \big) = 0 \ \text{in the tissue}, \qquad
k = \frac{\bar V}{V_K} \ \text{(cell volume } V_K\text{: small cells move stiffly)},
$$

with the inclusion's nodes prescribed — U_h = (0, 0, 1) (the centre rises by 1 mm),
U_s = x − c₀ (radial scaling about the reference centre c₀) — and U = 0 on every probe
node, on the tissue surface z = T (so the footprint and its node pairs do not move), on
the chest wall z = 0, on the slab's outer faces and on the skin layer; on the symmetry
planes of the quarter model only the normal component is zero.  Consequences:

* x(d₀, h₀) = x₀ exactly: the morphed mesh at the reference is the gmsh mesh;
* every inclusion node maps to c(h) + (d/d₀)(x₀ − c₀) with c(h) = c₀ + (h₀ − h) e_z, so the
  nodes of the sphere (ellipsoid) lie on the new sphere of diameter d centred at depth h,
  and the elements per diameter (the mesh "sized by d") are kept;
* within one reference the map (d, h) ↦ mesh, hence the whole discrete forward map, is
  smooth (affine geometry, polynomial assembly, one fixed topology).

The probe, the interface, the node sets, the image sampler and the sparsity pattern do
not move or change, so one DOLFINx :class:`~elastimap.solver.fem.Model` per reference serves
every (d, h) it covers: its ``mesh.geometry.x`` is overwritten in place and the stiffness
matrix re-assembled — no gmsh, no form compilation, same symbolic LU factorisation.

Which reference serves which (d, h)
-----------------------------------
Bins in d are geometric, width √2, centred on d₀ = 8 · √2^k mm (…, 2, 2.83, 4, 5.66, 8,
11.3, 16, …; edges at 8 · √2^(k ± ½): 1.68, 2.38, 3.36, 4.76, 6.73, 9.51, 13.5, 19 mm),
so d/d₀ ∈ [2^(−1/4), 2^(1/4)].  Bins in depth use the log ratio of the two gaps the
motion compresses, s = ln(g / b) with the top cover g = h − a d / 2 and the floor
clearance b = T − h − a d / 2 (a the aspect ratio), width ln 2, anchored so that the paper's
default sample (d = 8, h = 7 mm, T = 20 mm) is a reference; each gap then changes by at most
a factor of about √2 from its reference value.  The reference of a bin is (d₀, h₀) with h₀
from the bin's centre s₀ (clamped into the allowed depth range of d₀).  Within a bin the
map is smooth; at a bin edge the sample switches to another mesh and the result jumps by
the discretisation error (measured in docs/forward-model.md).  A caller that needs one
smooth map over a wider region (a fit) pins a reference (``reference=``); the motion is
refused only when a cell would invert or lose too much shape quality.

Public API (the contract)
-------------------------
``MorphedForward(params)`` — ``params`` is a :class:`~elastimap.solver.params.SolveParams`
template; everything except the inclusion's d, h, E (tissue, probe, loading, image,
``disc.mesh``/degree/interface/symmetry, inclusion ν, aspect, offsets) is fixed for the
object's life.

* ``fwd.solve(d, h, E, reference=None) -> SolveResult`` — one sample (inclusion solve and
  reference solve E_inc = E_tissue, difference image, O1..O3, force), exactly what
  :func:`elastimap.solver.solve` returns with ``disc.geometry = "morph"``
  (``result.params.disc.geometry == "morph"``).  ``reference`` (a :class:`Reference`)
  pins the reference mesh; None picks :meth:`MorphedForward.reference_for`. The reference
  solve does not depend on E and is reused when only E changes (one linear solve then).
  ``linearise_at=(d_s, h_s)`` takes the reference solve to first order in (d, h) about that
  point of the same reference mesh instead (one linear solve per sample; exact at the point).
* ``fwd.solve_tangent(d, h, E, reference=None, linearise_at=None) -> (SolveResult, J)`` — the
  same sample and ``J`` ``(3, ny, nx)``, the exact derivative of its difference image in d, h
  (mm) and E (kPa) on the reference mesh used (one back-solve per parameter with the solves'
  factorisations; linear problems under a prescribed plate travel, ``fwd.has_tangent``).
* ``fwd.reference_for(d, h) -> Reference`` — the bin's reference (frozen dataclass
  ``d0``, ``h0``; hashable).
* ``fwd.quality(d, h, reference=None) -> MorphQuality`` — min volume ratio and min
  shape-quality ratio of the morphed tissue cells against the reference mesh.
* ``fwd.close()`` (or ``with MorphedForward(p) as fwd:``) frees the PETSc objects.

Up to ``max_references`` reference Models are kept alive (least recently used first out).
Bad (d, h) raise :class:`elastimap.errors.UserError` like ``solve``; a refused motion with a
pinned reference falls back to the bin's own reference, and a refused bin reference to a
gmsh mesh at (d, h) itself (``timings["morph_fallback"]`` = 1 or 2).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from elastimap.errors import UserError

from .geometry import INCLUSION, PROBE_LAYER0, SKIN, RawMesh
from .params import THICKNESS, SolveParams, SolveResult, depth_range

#: d-bin width (ratio of edges) and the diameter (mm) at which the d-grid is anchored
D_RATIO = math.sqrt(2.0)
D_ANCHOR = 8.0
#: depth-bin width in s = ln(g / b) and its anchor: the default sample d = 8, h = 7 mm, T = 20 mm
S_WIDTH = math.log(2.0)
S_ANCHOR = math.log(3.0 / 9.0)
#: a motion is refused when a tissue cell's volume drops below this fraction of its reference
#: volume, or its shape quality below this fraction of the reference mesh's worst
MIN_VOLUME_RATIO = 0.2
MIN_QUALITY_RATIO = 0.3
#: a tangent's back-solves on a morphed model refactorise first when the solve before them needed
#: more than this many CG iterations on another sample's factors
#: (:class:`~elastimap.solver.reduction.Recycled`): three back-solves of n iterations each cost more
#: than one factorisation once n > 6 on the coarse mesh (17 ms an iteration, 0.35 s a
#: factorisation); plain solves (no tangent) keep CG
REFACTOR_AFTER = 6


@dataclass(frozen=True)
class Reference:
    """The (d₀, h₀) (mm) at which a reference mesh is built by gmsh."""

    d0: float
    h0: float


@dataclass(frozen=True)
class MorphQuality:
    """Worst tissue cell of a morphed mesh: volume ratio V/V₀ (≤ 0: inverted) and shape
    quality (mean ratio, 1 = regular tetrahedron) relative to the reference mesh's worst cell."""

    min_volume_ratio: float
    min_quality_ratio: float

    @property
    def ok(self) -> bool:
        return self.min_volume_ratio >= MIN_VOLUME_RATIO and self.min_quality_ratio >= MIN_QUALITY_RATIO


def _gaps(d: float, h: float, thickness: float, aspect: float) -> tuple[float, float]:
    half = aspect * d / 2
    return h - half, thickness - h - half


def reference_for(d: float, h: float, thickness: float = THICKNESS, aspect: float = 1.0) -> Reference:
    """The reference (d₀, h₀) of the bin holding (d, h) (see the module docstring)."""
    k = round(math.log(d / D_ANCHOR) / math.log(D_RATIO))
    d0 = D_ANCHOR * D_RATIO**k
    g, b = _gaps(d, h, thickness, aspect)
    lo0, hi0 = depth_range(d0, thickness, aspect)
    if g <= 0 or b <= 0 or lo0 > hi0:
        return Reference(float(d), float(h))  # outside what the bins cover: a mesh of its own
    j = round((math.log(g / b) - S_ANCHOR) / S_WIDTH)
    s0 = S_ANCHOR + j * S_WIDTH
    half0 = aspect * d0 / 2
    room = thickness - 2 * half0
    h0 = half0 + room * math.exp(s0) / (1 + math.exp(s0))
    h0 = min(max(h0, lo0), hi0)
    return Reference(round(d0, 9), round(h0, 9))


# ---------------------------------------------------------------------------- the mesh motion
def _tet_geometry(x: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed volumes (mm³) and mean-ratio shape quality 12 (3|V|)^(2/3) / Σ ℓ² of tetrahedra."""
    p = x[cells]
    e1, e2, e3 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    vol = np.einsum("ij,ij->i", e1, np.cross(e2, e3)) / 6.0
    edges = [p[:, i] - p[:, j] for i, j in ((1, 0), (2, 0), (3, 0), (2, 1), (3, 1), (3, 2))]
    l2 = sum(np.einsum("ij,ij->i", e, e) for e in edges)
    q = 12.0 * np.cbrt(3.0 * np.abs(vol)) ** 2 / l2
    return vol, np.where(vol > 0, q, -q)


def _laplacian(x: np.ndarray, cells: np.ndarray) -> sp.csr_matrix:
    r"""P1 stiffness of ∫ k ∇φ_i · ∇φ_j dx on the given cells, k = mean(V) / V_K."""
    p = x[cells]
    J = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)  # columns = edges
    det = np.linalg.det(J)
    vol = np.abs(det) / 6.0
    Jinv = np.linalg.inv(J)  # rows: gradients of barycentric coordinates 1..3
    g = np.concatenate([-Jinv.sum(axis=1, keepdims=True), Jinv], axis=1)  # (M, 4, 3)
    k = vol.mean() / vol
    Ke = np.einsum("mik,mjk->mij", g, g) * (k * vol)[:, None, None]
    rows = np.repeat(cells, 4, axis=1).ravel()
    cols = np.tile(cells, (1, 4)).ravel()
    n = len(x)
    return sp.csr_matrix((Ke.ravel(), (rows, cols)), shape=(n, n))


class MeshMotion:
    """The two unit motions U_h, U_s (mm per mm of depth, mm per unit d/d₀) of one reference mesh."""

    def __init__(self, raw: RawMesh, p0: SolveParams):
        t0 = time.perf_counter()
        self.x0 = raw.x
        self.ref = Reference(p0.inclusion.d, p0.inclusion.h)
        x, cells, m = raw.x, raw.cells, raw.markers
        T, L = p0.tissue.thickness, p0.tissue.size
        quarter = p0.disc.symmetry == "quarter"
        inc = p0.inclusion
        c0 = np.array([inc.offset_x, inc.offset_y, T - inc.h])
        n = len(x)
        tissue_cells = cells[m < PROBE_LAYER0]
        self.tissue_cells = tissue_cells
        tol = 1e-6 * max(T, L)
        in_tissue = np.zeros(n, dtype=bool)
        in_tissue[tissue_cells.ravel()] = True
        inc_nodes = np.unique(cells[m == INCLUSION])
        lo = 0.0 if quarter else -L / 2
        X, Y, Z = x[:, 0], x[:, 1], x[:, 2]
        fixed = ~in_tissue  # the probe (and any stray node) does not move
        fixed |= (np.abs(Z) < tol) | (np.abs(Z - T) < tol)
        fixed |= (np.abs(X - L / 2) < tol) | (np.abs(Y - L / 2) < tol)
        if not quarter:
            fixed |= (np.abs(X - lo) < tol) | (np.abs(Y - lo) < tol)
        if np.any(m == SKIN):
            fixed[np.unique(cells[m == SKIN])] = True
        sym = [np.abs(X) < tol, np.abs(Y) < tol, np.zeros(n, dtype=bool)] if quarter else [np.zeros(n, bool)] * 3
        K = _laplacian(x, tissue_cells).tocsr()

        self.U_h = np.zeros_like(x)
        self.U_s = np.zeros_like(x)
        data_h = np.zeros_like(x)
        data_h[inc_nodes, 2] = 1.0
        data_s = np.zeros_like(x)
        data_s[inc_nodes] = x[inc_nodes] - c0
        for comp in range(3):
            dirichlet = fixed | sym[comp]
            dirichlet[inc_nodes] = True
            free = np.flatnonzero(~dirichlet)
            bnd = np.flatnonzero(dirichlet)
            rhs_cols = [data_s[:, comp]] + ([data_h[:, comp]] if comp == 2 else [])
            Kff = K[free][:, free].tocsc()
            Kfb = K[free][:, bnd]
            lu = splu(Kff)
            for j, data in enumerate(rhs_cols):
                u = data.copy()
                u[free] = lu.solve(-(Kfb @ data[bnd]))
                (self.U_s if j == 0 else self.U_h)[:, comp] = u
        self.vol0, self.q0 = _tet_geometry(x, tissue_cells)
        self.q0_min = float(self.q0.min())
        self.seconds = time.perf_counter() - t0

    def coordinates(self, d: float, h: float) -> np.ndarray:
        """x(d, h) = x₀ + (h₀ − h) U_h + (d/d₀ − 1) U_s (mm), all nodes of the raw mesh."""
        return self.x0 + (self.ref.h0 - h) * self.U_h + (d / self.ref.d0 - 1.0) * self.U_s

    def quality(self, x: np.ndarray) -> MorphQuality:
        vol, q = _tet_geometry(x, self.tissue_cells)
        return MorphQuality(float(np.min(vol / self.vol0)), float(np.min(q)) / self.q0_min)


# ---------------------------------------------------------------------------- the forward map
_RECORDING = []


def _recording_model_class():
    """:class:`~elastimap.solver.fem.Model` that keeps its last solution (``last_solution``: the
    displacement the tangent of a solve differentiates)."""
    if not _RECORDING:
        from .fem import Model

        class RecordingModel(Model):
            last_solution = None

            def solve(self, E_inclusion, delta, max_iter=30):
                sol, diag = super().solve(E_inclusion, delta, max_iter)
                self.last_solution = (float(E_inclusion), float(delta), sol)
                return sol, diag

        _RECORDING.append(RecordingModel)
    return _RECORDING[0]


class _Entry:
    """One reference: its raw mesh, motion and DOLFINx Model, and where the Model's mesh is now."""

    def __init__(self, template: SolveParams, ref: Reference, cg_rtol: float | None = None):
        from .geometry import build_mesh

        p0 = template.with_inclusion(d=ref.d0, h=ref.h0).validate()
        self.raw = build_mesh(p0)
        self.motion = MeshMotion(self.raw, p0)
        self.model = _recording_model_class()(self.raw, p0)
        # a fit moves the mesh away from the factorised one a little per sample (REFACTOR_AFTER)
        self.model.refactor_after = REFACTOR_AFTER
        if cg_rtol is not None:
            self.model.cg_rtol = float(cg_rtol)
        self.igi = np.asarray(self.model.mesh.geometry.input_global_indices, dtype=np.int64)
        self.at = (ref.d0, ref.h0)
        self.reference_solve = None  # (d, h, tuple) of the last reference solve
        self.reference_tangent = None  # (d, h, {"d": dw/dd, "h": dw/dh}) of that reference press
        self.expansions: OrderedDict = OrderedDict()  # (d_s, h_s) -> (reference tuple, its tangent)
        self._action = None  # (u_fun, compiled form a(u_fun, v)) for the tangent
        self.build_seconds = self.raw.seconds + self.motion.seconds + self.model.timings["setup"]

    def move_to(self, x: np.ndarray, d: float, h: float) -> None:
        if self.at == (d, h):
            return
        self.model.mesh.geometry.x[:, :] = x[self.igi]
        self.model.moved()
        self.model.space.X = self.model.V.tabulate_dof_coordinates()
        self.at = (d, h)
        self.reference_solve = None
        self.reference_tangent = None

    def tangent(self, u: np.ndarray, E_inc: float, delta: float, d: float, h: float, which) -> dict:
        r"""Derivatives of the probe-bottom image of the solution ``u`` (mm, all nodal values) that the
        model just computed at inclusion modulus ``E_inc`` on this mesh (``model.last_linear`` solves with its K).

        The reduced system K(θ) ū = −Pᵀ A(θ) u_D (:mod:`elastimap.solver.reduction`) is linear in u,
        and P, u_D and the pixel sampler do not depend on θ = (d, h, E) (the probe does not move).
        Differentiating,

        $$
        K \, \frac{\partial \bar u}{\partial \theta} = -P^{T} \frac{\partial A}{\partial \theta} u,
        \qquad \frac{\partial u}{\partial \theta} = P \frac{\partial \bar u}{\partial \theta},
        $$

        one back-solve with the same factorisation per θ.  The vector (∂A/∂θ) u is the derivative of
        the assembled residual a(u, ·) with u held fixed: for E (kPa) exactly
        (a(u, ·) is linear in the inclusion's modulus), ((a_{E+η} − a_E)(u, ·)) / η; for d and h (mm) by a
        central difference of the assembly over the mesh motion x(d, h) (:class:`MeshMotion`,
        ∂x/∂d = U_s / d₀, ∂x/∂h = −U_h) with a step of 1e-4 mm (assembly is a smooth rational function
        of the node coordinates).  ``which``: the θ names wanted.  Returns {name: ∂w/∂θ} on the
        model's pixel grid (the quadrant for the quarter model; mm per mm, mm per kPa)."""
        from dolfinx import fem
        from petsc4py import PETSc

        model = self.model
        if self._action is None:
            import ufl

            u_fun = fem.Function(model.V)
            form = fem.form(ufl.action(model.materials.stiffness_form(model.V), u_fun))
            self._action = (u_fun, form)
        u_fun, form = self._action
        u_fun.x.array[: len(u)] = u

        def residual() -> np.ndarray:
            return np.array(fem.assemble_vector(form).array[: len(u)])

        g = model.mesh.geometry.x
        x_here = g.copy()
        ref = self.motion.ref
        moves = {"d": self.motion.U_s[self.igi] / ref.d0, "h": -self.motion.U_h[self.igi]}
        Au = {}
        eps = 1e-4
        for name in which:
            if name == "E":
                eta = 1e-3 * E_inc
                r0 = residual()
                model.materials.set_inclusion_modulus(E_inc + eta)
                Au[name] = (residual() - r0) / eta
                model.materials.set_inclusion_modulus(E_inc)
            else:
                g[:, :] = x_here + eps * moves[name]
                rp = residual()
                g[:, :] = x_here - eps * moves[name]
                rm = residual()
                g[:, :] = x_here
                Au[name] = (rp - rm) / (2 * eps)
        model.reduction.operator(delta, np.ones(model.interface.npairs, dtype=bool))
        Psp = model.reduction.P_csr
        out = {}
        for name, v in Au.items():
            b = PETSc.Vec().createWithArray(-(Psp.T @ v))
            x = model.last_linear.resolve(b)  # K of the solve just made
            du = Psp @ x.getArray()
            b.destroy()
            x.destroy()
            dw = model.sampler.deflection(du, 0.0)
            out[name] = dw
        return out

    def destroy(self) -> None:
        self.model.destroy()


class MorphedForward:
    """The forward map on morphed reference meshes; see the module docstring for the contract.

    ``max_references``: reference meshes kept (least recently used dropped); ``cg_rtol``: the
    relative tolerance of the CG solves on recycled factors
    (:class:`~elastimap.solver.reduction.Recycled`; None: its default ``CG_RTOL``)."""

    def __init__(self, params: SolveParams, max_references: int = 2, cg_rtol: float | None = None):
        if cg_rtol is not None and not (math.isfinite(cg_rtol) and 0 < cg_rtol < 1):
            raise UserError("cg_rtol", f"must be in (0, 1) (got {cg_rtol})")
        self.cg_rtol = cg_rtol
        params = params.validate()
        self.template = params.replace(disc=dataclasses.replace(params.disc, geometry="morph"))
        self.max_references = max(1, int(max_references))
        self._entries: OrderedDict[Reference, _Entry] = OrderedDict()

    # -------------------------------------------------------------- references
    def reference_for(self, d: float, h: float) -> Reference:
        t = self.template
        return reference_for(d, h, t.tissue.thickness, t.inclusion.aspect)

    def _entry(self, ref: Reference) -> tuple[_Entry, float]:
        if ref in self._entries:
            self._entries.move_to_end(ref)
            return self._entries[ref], 0.0
        while len(self._entries) >= self.max_references:
            _k, old = self._entries.popitem(last=False)
            old.destroy()
        e = _Entry(self.template, ref, self.cg_rtol)
        self._entries[ref] = e
        return e, e.build_seconds

    def quality(self, d: float, h: float, reference: Reference | None = None) -> MorphQuality:
        ref = reference or self.reference_for(d, h)
        e, _ = self._entry(ref)
        return e.motion.quality(e.motion.coordinates(d, h))

    # -------------------------------------------------------------- solve
    def _place(self, d: float, h: float, E: float, reference: Reference | None):
        """Validated params, the entry (reference mesh) serving (d, h) and the morphed coordinates."""
        p = self.template.with_inclusion(d=float(d), h=float(h), E=float(E)).validate()
        d, h = p.inclusion.d, p.inclusion.h
        fallback = 0
        ref = reference or self.reference_for(d, h)
        try:
            e, built = self._entry(ref)
        except UserError:  # the bin's reference does not fit these settings (e.g. an offset inclusion)
            fallback, ref = 2, Reference(d, h)
            e, built = self._entry(ref)
        x = e.motion.coordinates(d, h)
        q = e.motion.quality(x)
        if not q.ok and reference is not None and reference != self.reference_for(d, h):
            fallback, ref = 1, self.reference_for(d, h)
            e, b2 = self._entry(ref)
            built += b2
            x = e.motion.coordinates(d, h)
            q = e.motion.quality(x)
        if not q.ok:
            warnings.warn(
                f"morphing reference (d0={ref.d0:g}, h0={ref.h0:g}) to (d={d:g}, h={h:g}) is refused "
                f"(volume ratio {q.min_volume_ratio:.3g}, quality ratio {q.min_quality_ratio:.3g}); "
                "meshing this sample itself",
                RuntimeWarning,
                stacklevel=3,
            )
            fallback, ref = 2, Reference(d, h)
            e, b2 = self._entry(ref)
            built += b2
            x = e.motion.coordinates(d, h)
        t1 = time.perf_counter()
        e.move_to(x, d, h)
        extra = {
            "setup": 0.0,
            "morph": time.perf_counter() - t1,
            "mesh_setup": built,
            "morph_fallback": float(fallback),
        }
        return p, e, extra

    def _reference_press(self, e: _Entry, p: SolveParams, with_tangent: bool):
        """The reference press (E_inc = E_tissue) on the entry's mesh where it is now: the tuple
        :func:`~elastimap.solver.sample.run_sample` takes and, with ``with_tangent``, its image's
        derivatives in d and h (:meth:`_Entry.tangent`); kept while the mesh stays."""
        from .errors import SolverError
        from .sample import sample_tag, solve_at

        here = e.at
        have = e.reference_solve and e.reference_solve[:2] == here
        if have and (not with_tangent or (e.reference_tangent and e.reference_tangent[:2] == here)):
            return e.reference_solve[2], (e.reference_tangent[2] if with_tangent else None)
        model = e.model
        try:
            sol_r, diag_r, delta_r, force_r = solve_at(model, p.tissue.E, p)
        except SolverError as exc:
            raise SolverError(f"solve failed for {sample_tag(p)} (reference press): {exc}") from exc
        ref = (sol_r, diag_r, delta_r, force_r, model.probe_bottom_w(sol_r, delta_r))
        e.reference_solve = (*here, ref)
        tan = None
        if with_tangent:  # now, while the factorisation is the reference press's
            tan = e.tangent(sol_r.u, p.tissue.E, delta_r, *here, ("d", "h"))
            e.reference_tangent = (*here, tan)
        return ref, tan

    def _linearised_reference(self, e: _Entry, p: SolveParams, d: float, h: float, centre: tuple[float, float]):
        r"""The reference press at (d, h) to first order about ``centre`` = (d_s, h_s) on the same
        reference mesh,

        $$ w_{\rm ref}(d, h) \approx w_{\rm ref}(d_s, h_s) + (d - d_s)\, \partial_d w_{\rm ref} + (h - h_s)\, \partial_h w_{\rm ref}, $$

        (mm) with the derivatives of :meth:`_Entry.tangent` at the centre; the force and
        diagnostics are the centre's.  Returns (the tuple for ``run_sample``, ∂w_ref/∂(d, h))."""
        key = (float(centre[0]), float(centre[1]))
        if key not in e.expansions:
            x_here, at = e.motion.coordinates(d, h), e.at
            e.move_to(e.motion.coordinates(*key), *key)
            e.expansions[key] = self._reference_press(e, p, with_tangent=True)
            while len(e.expansions) > 4:
                e.expansions.popitem(last=False)
            e.move_to(x_here, *at)
        e.expansions.move_to_end(key)
        ref, tan = e.expansions[key]
        w = ref[4] + (d - key[0]) * tan["d"] + (h - key[1]) * tan["h"]
        return (*ref[:4], w), tan

    def solve(
        self,
        d: float,
        h: float,
        E: float,
        reference: Reference | None = None,
        linearise_at: tuple[float, float] | None = None,
    ) -> SolveResult:
        """One sample at (d mm, h mm, E kPa) on a morphed reference mesh.

        ``linearise_at`` = (d_s, h_s): take the reference press to first order about that point on
        the same reference mesh (:meth:`_linearised_reference`; one linear solve per sample instead
        of two when d or h move) instead of solving it on the morphed mesh; equal at (d_s, h_s)."""
        return self._solve(d, h, E, reference, linearise_at, tangent=False)[0]

    def solve_tangent(
        self,
        d: float,
        h: float,
        E: float,
        reference: Reference | None = None,
        linearise_at: tuple[float, float] | None = None,
    ) -> tuple[SolveResult, np.ndarray]:
        """:meth:`solve` and the derivatives of its difference image ``w − w_ref`` with respect to
        d (mm, at fixed h), h (mm, at fixed d) and E (kPa): ``(result, J)``, ``J`` of shape
        ``(3, ny, nx)`` (mm/mm, mm/mm, mm/kPa), the exact derivative of this discrete map on the
        reference mesh used (:meth:`_Entry.tangent`; w_ref depends on d and h through the mesh only,
        not on E; with ``linearise_at`` its derivative is the constant of the expansion).  Cost: the
        solve, plus a few vector assemblies and one back-solve per parameter with the solves'
        factorisations (about 8 % of a solve on the coarse mesh)."""
        return self._solve(d, h, E, reference, linearise_at, tangent=True)

    @property
    def has_tangent(self) -> bool:
        """Whether :meth:`solve_tangent` and ``linearise_at`` apply: a linear problem (no contact,
        no finite strain) under a prescribed plate travel."""
        return not self.template.nonlinear and self.template.loading.force is None

    def _solve(self, d, h, E, reference, linearise_at, tangent: bool):
        from .image import mirror_quarter
        from .sample import run_sample

        if (tangent or linearise_at is not None) and not self.has_tangent:
            raise UserError(
                "geometry",
                "the tangent and the linearised reference press need a linear problem (tied or bonded "
                "interface, no nonlinearity) under a prescribed plate travel",
            )
        t0 = time.perf_counter()
        p, e, extra = self._place(d, h, E, reference)
        d, h = p.inclusion.d, p.inclusion.h
        model = e.model
        model.timings = {"setup": model.timings.get("setup", 0.0)}
        if linearise_at is not None and extra["morph_fallback"] == 0:
            ref, ref_tan = self._linearised_reference(e, p, d, h, linearise_at)
        else:  # the reference press first, so that its factorisation serves its tangent
            ref, ref_tan = self._reference_press(e, p, tangent)
        ref_timings = dict(model.timings)  # run_sample restarts the model's clock
        res, _ = run_sample(model, p, t0, extra, reference=ref)
        for k, v in ref_timings.items():
            if k != "setup":
                res.timings[k] = round(res.timings.get(k, 0.0) + v, 4)
        if not tangent:
            return res, None
        _E, delta, sol = model.last_solution
        t1 = time.perf_counter()
        tan = e.tangent(sol.u, p.inclusion.E, delta, d, h, ("d", "h", "E"))
        res.timings["tangent"] = round(time.perf_counter() - t1, 4)
        J = [tan["d"] - ref_tan["d"], tan["h"] - ref_tan["h"], tan["E"]]
        if p.disc.symmetry == "quarter":
            J = [mirror_quarter(j) for j in J]
        return res, np.stack(J)

    def close(self) -> None:
        while self._entries:
            _k, e = self._entries.popitem()
            e.destroy()

    def __enter__(self) -> MorphedForward:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


_SHARED: dict = {}


def shared_forward(p: SolveParams) -> MorphedForward:
    """The process's :class:`MorphedForward` for the settings of ``p`` (all but d, h, E); one is
    kept at a time, so a sweep worker reuses its reference meshes from sample to sample."""
    key = repr(p.with_inclusion(d=0.0, h=0.0, E=0.0).to_dict())
    fwd = _SHARED.get(key)
    if fwd is None:
        for old in _SHARED.values():
            old.close()
        _SHARED.clear()
        fwd = _SHARED[key] = MorphedForward(p)
    return fwd
