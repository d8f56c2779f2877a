"""Solver effect switches for the sim-to-real gap diagnosis: interface friction k_t and
finite-strain (neo-Hookean) tissue.  Tiny meshes; defaults stay bit-identical."""

import numpy as np
import pytest

from elastimap.errors import UserError
from elastimap.solver.params import Discretisation, Loading, SolveParams, Tissue

# its module fixture is costly: under pytest-xdist (make test) this module runs on one worker
pytestmark = pytest.mark.xdist_group("test_solver_effects")


def tiny(**disc) -> SolveParams:
    return SolveParams(disc=Discretisation(mesh="tiny", **disc))


@pytest.fixture(scope="module")
def solve():
    from elastimap.solver import solve as _solve

    return _solve


@pytest.fixture(scope="module")
def base(solve):
    return solve(tiny())


def test_effect_switch_validation_and_serialisation():
    with pytest.raises(UserError) as e:
        tiny(friction_kt=-1.0).validate()
    assert e.value.param == "friction_kt"
    with pytest.raises(UserError) as e:
        SolveParams(tissue=Tissue(nonlinearity=1.5)).validate()
    assert e.value.param == "tissue.nonlinearity"
    # defaults are left out of to_dict (sweep manifests written before the switches keep matching)
    d = SolveParams().to_dict()
    assert "friction_kt" not in d["disc"] and "nonlinearity" not in d["tissue"]
    p = SolveParams(tissue=Tissue(nonlinearity=0.5), disc=Discretisation(friction_kt=2.0))
    assert SolveParams.from_dict(p.to_dict()) == p
    assert not SolveParams().nonlinear and p.nonlinear


def test_friction_zero_is_frictionless_and_large_is_bonded(solve, base):
    zero = solve(tiny(friction_kt=0.0))
    assert zero.O2 == base.O2 and np.array_equal(zero.image, base.image)  # bit-identical default path
    bonded = solve(tiny(interface="bonded"))
    stiff = solve(tiny(friction_kt=1e5))
    for f in ("O1", "O2", "O3", "force"):
        assert getattr(stiff, f) == pytest.approx(getattr(bonded, f), rel=2e-3), f


def test_friction_is_monotone_between_the_limits(solve, base):
    lo, hi = solve(tiny(friction_kt=0.1)), solve(tiny(friction_kt=1.0))
    assert base.O2 < lo.O2 < hi.O2
    assert base.force < lo.force < hi.force
    # the contact interface with friction closes as the tied one does under the flat punch
    c = solve(tiny(friction_kt=1.0, interface="contact"))
    assert c.O2 == pytest.approx(hi.O2, rel=1e-3)


def test_neo_hookean_small_strain_limit_is_linear(solve):
    """Tiny δ: the finite-strain model gives the linear answer (features scale with δ)."""
    small = tiny().replace(loading=Loading(delta=1e-3))
    lin = solve(small)
    nh = solve(small.replace(tissue=Tissue(nonlinearity=1.0)))
    assert nh.O1 == pytest.approx(lin.O1, rel=2e-3)
    assert nh.O2 == pytest.approx(lin.O2, rel=2e-3)
    assert nh.force == pytest.approx(lin.force, rel=2e-3)
    assert nh.newton_iterations > 2  # Newton actually ran


def test_neo_hookean_changes_the_image_at_3mm(solve, base):
    nh = solve(tiny().replace(tissue=Tissue(nonlinearity=1.0)))
    assert nh.force > base.force  # compression stiffens the neo-Hookean tissue
    assert abs(nh.O1 / base.O1 - 1) > 0.05
    half = solve(tiny().replace(tissue=Tissue(nonlinearity=0.3)))
    assert base.force < half.force < nh.force


def test_load_stepped_newton_converges_to_the_one_step_solution():
    """The cold Newton solve is load-stepped (δ/4, δ/2, 3δ/4, δ, quadratic predictor) and reuses
    a factorised tangent while it converges fast (modified Newton): the same equilibrium as plain
    Newton from the linear solution in one step, to the solver's tolerance, with fewer tangent
    factorisations; its iteration count holds every step's."""
    from elastimap.solver.fem import Model
    from elastimap.solver.geometry import build_mesh

    p = tiny().replace(tissue=Tissue(nonlinearity=1.0)).validate()
    model = Model(build_mesh(p), p)
    try:
        model.newton.reuse_ratio = 0.0  # plain Newton: a fresh tangent every step
        one = model.solve_nonlinear(p.inclusion.E, p.loading.delta, load_steps=1)
        n_plain = model.newton.factorisations
        model.newton.reuse_ratio, model._warm = 0.25, None  # modified Newton, a cold start again
        four = model.solve_nonlinear(p.inclusion.E, p.loading.delta, load_steps=4)
        n_mod = model.newton.factorisations - n_plain
    finally:
        model.destroy()
    scale = np.abs(one.u).max()
    assert np.abs(four.u - one.u).max() <= 1e-7 * scale
    assert np.allclose(four.reaction, one.reaction, rtol=1e-6, atol=1e-8 * np.abs(one.reaction).max())
    assert one.iterations > 2 and four.iterations > 4
    assert n_plain == one.iterations - 1  # plain Newton factorises every step
    assert 0 < n_mod < n_plain, (n_mod, n_plain)


def test_the_linear_solution_scales_with_the_plate_travel_without_tilt():
    """The load steps take the linear predictor at δ_k as (δ_k/δ) u_lin (no solve): that holds
    for the untilted plate (u_D ∝ δ), and not for a tilted one (u_D = −(δ + tilt x)), which is
    therefore solved."""
    from elastimap.solver.fem import Model
    from elastimap.solver.geometry import build_mesh

    p = tiny().validate()
    model = Model(build_mesh(p), p)
    try:
        full = model.solve_linear(p.inclusion.E, p.loading.delta)
        quarter = model.solve_linear(p.inclusion.E, p.loading.delta / 4)
        model.reduction.tilt = 0.01
        tilted_full = model.solve_linear(p.inclusion.E, p.loading.delta)
        tilted_quarter = model.solve_linear(p.inclusion.E, p.loading.delta / 4)
    finally:
        model.destroy()
    scale = np.abs(full.u).max()
    assert np.abs(quarter.u - full.u / 4).max() <= 1e-10 * scale
    assert np.abs(quarter.reaction - full.reaction / 4).max() <= 1e-9 * np.abs(full.reaction).max()
    assert np.abs(tilted_quarter.u - tilted_full.u / 4).max() > 1e-3 * scale


def test_ellipsoid_quarter_model_meshes_and_scales(solve):
    """Ellipsoidal inclusion (``Inclusion.aspect``) in the quarter model: the mesh builds
    (dilated after the symmetry clip) and a taller inclusion gives a larger image."""
    p = tiny().with_inclusion(d=7.95, h=9.63, E=79.6)
    flat, tall = solve(p.with_inclusion(aspect=0.8)), solve(p.with_inclusion(aspect=1.25))
    sph = solve(p)
    assert flat.O1 < sph.O1 < tall.O1 and flat.O2 < sph.O2 < tall.O2
