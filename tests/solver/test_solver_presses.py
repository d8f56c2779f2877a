"""A sample's two presses share their work (``solve(presses="shared")``, issue 41): the inclusion
press is the difference of the two presses by CG on the reference press's factors, its matrix
updated by the inclusion's cells.  Checked against each press factorised for itself
(``presses="separate"``, the path before) on tiny meshes."""

import dataclasses

import numpy as np
import pytest

from elastimap.errors import UserError
from elastimap.solver.params import Discretisation, Loading, SolveParams

TINY = SolveParams(disc=Discretisation(mesh="tiny"))


@pytest.mark.parametrize(
    "p",
    [
        TINY.with_inclusion(d=8.0, h=7.0, E=50.0),
        TINY.with_inclusion(d=3.0, h=12.0, E=200.0),  # small, deep, stiff: a tiny difference image
        TINY.with_inclusion(d=12.0, h=9.0, E=10.0),
        TINY.replace(loading=Loading(force=1200.0)).with_inclusion(d=8.0, h=7.0, E=50.0),
    ],
    ids=["8-7-50", "3-12-200", "12-9-10", "force"],
)
def test_shared_presses_give_the_separate_presses_numbers(p):
    from elastimap.solver.api import solve

    a, b = solve(p, presses="separate"), solve(p, presses="shared")
    for k in ("O1", "O2", "O3"):
        assert getattr(b, k) == pytest.approx(getattr(a, k), rel=1e-5, abs=1e-12), k
    for k in ("force", "force_ref", "delta"):
        assert getattr(b, k) == pytest.approx(getattr(a, k), rel=1e-9), k
    assert np.abs(b.image.astype(float) - a.image).max() <= 1e-5 * np.abs(a.image).max()
    assert np.abs(b.image_raw.astype(float) - a.image_raw).max() <= 1e-6 * np.abs(a.image_raw).max()


def test_single_precision_factors_keep_a_default_sample(monkeypatch):
    """At the `default` level (SINGLE_MIN_UNKNOWNS) the shared presses run on single-precision
    factors, CG in double to the same tolerances: the sample's features and forces are those of
    double factors to within the presses' CG tolerance; the separate path keeps double factors."""
    from elastimap.solver import fem
    from elastimap.solver.api import solve

    p = SolveParams(disc=Discretisation(mesh="default")).with_inclusion(d=8.0, h=7.0, E=50.0)
    a = solve(p)
    monkeypatch.setattr(fem, "SINGLE_MIN_UNKNOWNS", None)
    b = solve(p)
    assert solve(p, presses="separate").O1 == pytest.approx(b.O1, rel=1e-5)  # separate: double factors
    for k in ("O1", "O2", "O3"):  # PRESS_RTOL_SINGLE: within 1.3e-6 on 64 samples
        assert getattr(a, k) == pytest.approx(getattr(b, k), rel=2e-6, abs=1e-12), k
    for k in ("force", "force_ref"):
        assert getattr(a, k) == pytest.approx(getattr(b, k), rel=1e-8), k
    assert np.abs(a.image.astype(float) - b.image).max() <= 1e-5 * np.abs(b.image).max()


def _model(p):
    from elastimap.solver.fem import Model
    from elastimap.solver.geometry import build_mesh

    return Model(build_mesh(p), p)


def test_the_inclusion_press_updates_the_matrices_and_borrows_the_factors():
    """After the reference press, the inclusion press neither assembles nor reduces the whole
    matrix (A += (E − E_t) A₁ equals a fresh assembly at E to round-off, K likewise) and makes no
    factorisation of its own; the separate path factorises both presses."""
    from dolfinx.fem import petsc as fpetsc

    p = TINY.with_inclusion(d=8.0, h=7.0, E=80.0)
    for share in (True, False):
        model = _model(p)
        model.share_presses = share
        try:
            model.solve(p.tissue.E, 3.0)
            model.solve(p.inclusion.E, 3.0)
            inc = model.recycled["inclusion"]
            assert (inc.factorisations, inc.borrowed) == ((0, 1) if share else (1, 0))
            A = model.A.copy()
            model.A.zeroEntries()
            fpetsc.assemble_matrix(model.A, model.a)
            model.A.assemble()
            A.axpy(-1.0, model.A)
            assert A.norm() <= 1e-13 * model.A.norm()
        finally:
            model.destroy()


def test_only_the_shared_path_factorises_in_single_precision(monkeypatch):
    """``separate`` stays the path before: double-precision factors whatever the size; the shared
    presses' reference factors are single precision from SINGLE_MIN_UNKNOWNS (here every size) where
    the model allows them (``single_factors``: a remeshed sample; not a morphed or batched model),
    and the inclusion press then runs to PRESS_RTOL_SINGLE."""
    from elastimap.solver import fem

    monkeypatch.setattr(fem, "SINGLE_MIN_UNKNOWNS", 1)
    p = TINY.with_inclusion(d=8.0, h=7.0, E=80.0)
    for share, allowed in ((True, True), (False, True), (True, False)):
        model = _model(p)
        model.share_presses, model.single_factors = share, allowed
        try:
            model.solve(p.tissue.E, 3.0)
            assert model.recycled["reference"].single == (share and allowed)
        finally:
            model.destroy()
    model = _model(p)
    try:
        assert not model.single_factors  # double unless told (api.solve tells a remeshed sample's model)
    finally:
        model.destroy()


def test_the_stiffness_is_assembled_by_dolfinx_into_the_values_petsc_solves_with():
    """``Model.A`` is a PETSc matrix on the value array of DOLFINx's CSR matrix: DOLFINx's assembly
    (``Model._assemble``) equals PETSc's MatSetValues assembly of the same form to round-off, and a
    change of the CSR values is what PETSc sees (no copy)."""
    p = TINY.with_inclusion(d=8.0, h=7.0, E=80.0)
    model = _model(p)  # imports the solver first (solver/_boot.py), then DOLFINx may be
    from dolfinx.fem import petsc as fpetsc

    try:
        model._assemble(p.inclusion.E)
        want = fpetsc.assemble_matrix(model.a)
        want.assemble()
        assert model.A.getBlockSize() == want.getBlockSize() == 3
        diff = want.copy()
        diff.axpy(-1.0, model.A, structure=diff.Structure.DIFFERENT_NONZERO_PATTERN)
        assert diff.norm() <= 1e-14 * want.norm()
        norm = model.A.norm()
        model._A_values.data[:] *= 2.0
        model.A.assemble()
        assert model.A.norm() == pytest.approx(2.0 * norm, rel=1e-14)
        for m in (want, diff):
            m.destroy()
    finally:
        model.destroy()


def test_new_moduli_or_a_moved_mesh_assemble_afresh():
    """``Model.set_params`` (another tissue modulus: the batch's variants) and ``Model.moved`` (the
    morphed mesh) drop what the matrices held: the next presses equal a fresh model's."""
    from elastimap.solver.sample import run_sample

    p = TINY.with_inclusion(d=8.0, h=7.0, E=50.0)
    q = p.replace(tissue=dataclasses.replace(p.tissue, E=6.5))
    model = _model(p)
    try:
        run_sample(model, p, 0.0, {})
        model.set_params(q)
        got = run_sample(model, q, 0.0, {})[0]
    finally:
        model.destroy()
    fresh = _model(q)
    try:
        want = run_sample(fresh, q, 0.0, {})[0]
    finally:
        fresh.destroy()
    for k in ("O1", "O2", "force", "force_ref"):
        assert getattr(got, k) == pytest.approx(getattr(want, k), rel=1e-5), k


def test_presses_is_checked():
    from elastimap.solver.api import solve

    with pytest.raises(UserError) as err:
        solve(TINY, presses="both")
    assert err.value.param == "presses"


def test_a_process_that_keeps_its_models_prints_only_its_own_output():
    """A morphed map kept to the end of the process (``shared_forward``, as ``infer --refine``
    keeps it) whose inclusion solver only borrowed leaves no PETSc option unread: PETSc would print
    them on stdout at exit, after a ``--json`` answer."""
    import subprocess
    import sys

    code = (
        "from elastimap.solver.params import Discretisation, SolveParams\n"
        "from elastimap.solver.morph import shared_forward\n"
        "p = SolveParams(disc=Discretisation(mesh='tiny', geometry='morph'))\n"
        "f = shared_forward(p)\n"
        "f.solve(8.0, 7.0, 50.0)\n"
        "assert next(iter(f._entries.values())).model.recycled['inclusion'].borrowed == 1\n"
        "print('ok')\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "ok", r.stdout[-500:]


def test_the_environment_sets_every_new_models_presses(monkeypatch):
    """``$ELASTIMAP_PRESSES`` (what ``sweep timeit`` sets) decides a new model's presses, so that a
    whole command (morphed or batched models included) runs on the path before; other values are
    refused naming the variable."""
    from elastimap.solver.fem import PRESSES_ENV, default_presses

    p = TINY.with_inclusion(d=8.0, h=7.0, E=50.0)
    for value, share in (("separate", False), ("shared", True), ("", True)):
        monkeypatch.setenv(PRESSES_ENV, value)
        assert default_presses() == (value or "shared")
        model = _model(p)
        try:
            assert model.share_presses is share
            assert model.reduction.ptap_via == ("rap" if share else None)
        finally:
            model.destroy()
    monkeypatch.setenv(PRESSES_ENV, "both")
    with pytest.raises(UserError) as err:
        default_presses()
    assert err.value.param == PRESSES_ENV


def test_an_explicit_presses_overrides_the_environment(monkeypatch):
    from elastimap.solver.api import solve
    from elastimap.solver.fem import PRESSES_ENV

    p = TINY.with_inclusion(d=8.0, h=7.0, E=50.0)
    monkeypatch.setenv(PRESSES_ENV, "separate")
    env = solve(p)
    monkeypatch.delenv(PRESSES_ENV)
    sep = solve(p, presses="separate")
    assert (env.O1, env.O2, env.O3, env.force) == (sep.O1, sep.O2, sep.O3, sep.force)  # bit for bit


def test_a_group_of_inclusion_moduli_keeps_its_reference_press(monkeypatch):
    """``solve_group`` over samples that differ by the inclusion's modulus alone (a sweep's
    ``--moduli-per-mesh``) solves the reference press once and each inclusion press as the
    difference of the two on its factors: the numbers of a single ``solve`` of each sample."""
    from elastimap.solver import batch, sample
    from elastimap.solver.api import solve

    base = TINY.with_inclusion(d=8.0, h=7.0, E=10.0)
    ps = [base.with_inclusion(E=E) for E in (10.0, 35.0, 120.0, 200.0)]
    given = []
    run = sample.run_sample

    def spy(model, p, t0, extra, **kw):
        given.append(kw.get("reference") is not None)
        return run(model, p, t0, extra, **kw)

    monkeypatch.setattr(sample, "run_sample", spy)  # solve_group imports it when called
    got = batch.solve_group(ps, single_factors=True)
    assert given == [False, True, True, True]  # the first sample's reference press serves the others
    for p, r in zip(ps, got):
        want = solve(p)
        for k in ("O1", "O2", "O3", "force", "force_ref"):
            assert getattr(r, k) == pytest.approx(getattr(want, k), rel=1e-9, abs=1e-12), (p.inclusion.E, k)
    # another modulus of the tissue changes the reference press: a group of those solves it again
    q = ps[1].replace(tissue=dataclasses.replace(ps[1].tissue, E=6.5))
    given.clear()
    batch.solve_group([ps[0], q])
    assert given == [False, False]
    assert batch.inclusion_modulus_only(ps[0], ps[2]) and not batch.inclusion_modulus_only(ps[0], q)


@pytest.mark.parametrize("interface", ["tied", "bonded", "contact"])
def test_restrict_is_ptap_bit_for_bit(interface, monkeypatch):
    """``Reduction.restrict`` (PᵀA₁P by moving A₁'s entries) is the matrix ``ptap`` forms: pattern
    and values; the whole A (tied pairs among its rows) goes to ``ptap`` itself."""
    from elastimap.solver import reduction
    from elastimap.solver.fem import Model
    from elastimap.solver.geometry import build_mesh
    from elastimap.solver.reduction import ptap

    calls = []
    monkeypatch.setattr(reduction, "ptap", lambda A, P: calls.append(A) or ptap(A, P))
    p = dataclasses.replace(TINY, disc=Discretisation(mesh="tiny", interface=interface))
    p = p.with_inclusion(d=8.0, h=7.0, E=50.0)
    model = Model(build_mesh(p), p)
    try:
        model._assemble(p.tissue.E)
        A1 = model._unit_inclusion()
        active = model._all_closed()
        if interface == "contact":
            active[::3] = False  # some pairs open
        Pm, _uD, _new = model.reduction.operator(3.0, active)
        for M in (A1, model.A):
            mine, ref = model.reduction.restrict(M, Pm), ptap(M, Pm)
            for a, b in zip(mine.getValuesCSR(), ref.getValuesCSR()):
                assert np.array_equal(a, b)
            mine.destroy()
            ref.destroy()
        assert calls == [model.A]  # A₁ moved, A (tied rows) multiplied
    finally:
        model.destroy()
