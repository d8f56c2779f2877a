"""Mesh morphing (elastimap.solver.morph) on the tiny mesh: exactness at the reference, the
sphere maps onto the new sphere, no inverted cells, smoothness in (d, h), agreement with remeshing.

These compare the morphed forward map with the same code's remeshed one: they check the
morph's own properties and its consistency, not the physics (tests/solver/test_solver.py does that).
"""

import numpy as np
import pytest

from elastimap.errors import UserError
from elastimap.solver.params import Discretisation, SolveParams

TINY = SolveParams(disc=Discretisation(mesh="tiny"))


@pytest.fixture(scope="module")
def fwd():
    from elastimap.solver.morph import MorphedForward

    with MorphedForward(TINY) as f:
        yield f


def _sphere_nodes(e):
    from elastimap.solver.geometry import INCLUSION, PROBE_LAYER0

    raw = e.raw
    inc_nodes = np.unique(raw.cells[raw.markers == INCLUSION])
    other = np.unique(raw.cells[(raw.markers != INCLUSION) & (raw.markers < PROBE_LAYER0)])
    return np.intersect1d(inc_nodes, other)  # nodes shared by inclusion and tissue cells: the sphere


def test_geometry_switch_is_validated_and_omitted_at_default():
    assert "geometry" not in TINY.to_dict()["disc"]
    p = TINY.replace(disc=Discretisation(mesh="tiny", geometry="morph"))
    assert p.to_dict()["disc"]["geometry"] == "morph"
    assert SolveParams.from_dict(p.to_dict()) == p
    with pytest.raises(UserError) as err:
        TINY.replace(disc=Discretisation(geometry="warp")).validate()
    assert err.value.param == "geometry"


def test_reference_bins():
    from elastimap.solver.morph import reference_for

    assert reference_for(8.0, 7.0) == reference_for(8.0, 7.0)
    r = reference_for(8.0, 7.0)
    assert (r.d0, r.h0) == (8.0, 7.0)  # the default sample is a reference
    r = reference_for(8.9, 7.2)
    assert (r.d0, r.h0) == (8.0, 7.0)  # same bin
    assert reference_for(10.0, 7.0).d0 == pytest.approx(8 * 2**0.5)  # next d bin
    for d in (2.0, 3.0, 4.0, 6.0, 12.0, 15.0):
        r = reference_for(d, d / 2 + 3)
        assert 2**-0.25 - 1e-9 <= d / r.d0 <= 2**0.25 + 1e-9


def test_morph_at_reference_is_the_reference_mesh(fwd):
    ref = fwd.reference_for(8.0, 7.0)
    e, _ = fwd._entry(ref)
    x = e.motion.coordinates(ref.d0, ref.h0)
    assert np.array_equal(x, e.raw.x)


def test_sphere_nodes_lie_on_the_new_sphere_and_cells_stay_positive(fwd):
    ref = fwd.reference_for(8.0, 7.0)
    e, _ = fwd._entry(ref)
    T = TINY.tissue.thickness
    s = _sphere_nodes(e)
    r0 = np.linalg.norm(e.raw.x[s] - [0, 0, T - ref.h0], axis=1)
    assert np.allclose(r0, ref.d0 / 2, rtol=1e-3)  # gmsh puts them on the sphere
    for d, h in [(9.4, 7.0), (6.8, 7.0), (8.0, 6.4), (8.0, 7.6), (9.4, 6.4), (6.8, 7.6)]:
        x = e.motion.coordinates(d, h)
        r = np.linalg.norm(x[s] - [0, 0, T - h], axis=1)
        np.testing.assert_allclose(r, r0 * d / ref.d0, rtol=1e-12)
        q = e.motion.quality(x)
        assert q.ok and q.min_volume_ratio > 0.3, (d, h, q)  # bin corners: positive, not squashed
        # the probe, the tissue surface and the chest wall do not move
        top = np.abs(e.raw.x[:, 2] - T) < 1e-9
        assert np.array_equal(x[top], e.raw.x[top])


def test_too_large_a_motion_is_refused(fwd):
    ref = fwd.reference_for(8.0, 7.0)
    q = fwd.quality(3.0, 7.0, reference=ref)  # d/d0 = 0.375: cells shrink to 5 % of their volume
    assert not q.ok


def test_morph_solve_at_the_reference_equals_remesh(fwd):
    from elastimap.solver import solve

    a = solve(TINY)
    b = fwd.solve(8.0, 7.0, 50.0)
    assert b.params.disc.geometry == "morph"
    assert np.array_equal(a.image, b.image)
    assert (a.O1, a.O2, a.force) == (b.O1, b.O2, b.force)


def test_morph_agrees_with_remesh_off_the_reference(fwd):
    """Away from the reference the two meshes differ: they agree to the tiny mesh's
    discretisation error (its O1/O2 change from tiny to coarse is about 2–4 %)."""
    from elastimap.solver import solve

    p = TINY.with_inclusion(d=8.9, h=6.6)
    a = solve(p)
    b = solve(p.replace(disc=Discretisation(mesh="tiny", geometry="morph")))
    assert abs(b.O1 / a.O1 - 1) < 0.02
    assert abs(b.O2 / a.O2 - 1) < 0.04
    assert np.linalg.norm(b.image - a.image) / np.linalg.norm(a.image) < 0.04


def test_modulus_only_change_reuses_the_reference_solve(fwd):
    a = fwd.solve(8.3, 7.1, 50.0)
    b = fwd.solve(8.3, 7.1, 80.0)
    assert b.O1 > a.O1
    assert b.force_ref == a.force_ref
    assert b.timings["assemble"] < 0.75 * a.timings["assemble"]  # one solve instead of two


def test_tangent_matches_central_differences_of_the_map(fwd):
    """The exact derivative of the morphed difference image in d, h and E (one back-solve per
    parameter with the solves' factorisations) against central differences of the same pinned map
    (steps 0.02 mm, 0.4 kPa): equal to the differences' truncation error.  Same code and mesh on
    both sides: this checks the tangent's algebra, not the physics."""
    ref = fwd.reference_for(8.0, 7.0)
    theta = np.array([8.3, 7.2, 40.0])
    res, J = fwd.solve_tangent(*theta, reference=ref)
    assert J.shape == (3, *res.image.shape)
    # the same sample, to the image's float32 precision (CG on older factors or its own factors)
    np.testing.assert_allclose(
        res.image, fwd.solve(*theta, reference=ref).image, rtol=0, atol=1e-6 * np.abs(res.image).max()
    )
    for k, step in enumerate((0.02, 0.02, 0.4)):
        e = np.zeros(3)
        e[k] = step
        fd = (
            fwd.solve(*(theta + e), reference=ref).image.astype(float)
            - fwd.solve(*(theta - e), reference=ref).image.astype(float)
        ) / (2 * step)
        assert np.abs(J[k]).max() > 0
        assert np.abs(fd - J[k]).max() < 1e-3 * np.abs(J[k]).max(), k


def test_linearised_reference_press_is_exact_at_its_centre_and_close_off_it(fwd):
    """``linearise_at``: the reference press to first order about the pinned point (one linear
    solve per sample).  At the centre it is the map; 0.3 mm away the images differ by far less
    than the tiny mesh's own discretisation error (second order in the move); its tangent is the
    derivative of the linearised map."""
    ref = fwd.reference_for(8.0, 7.0)
    centre = (8.2, 7.1)
    a = fwd.solve(*centre, 40.0, reference=ref)
    b = fwd.solve(*centre, 40.0, reference=ref, linearise_at=centre)
    np.testing.assert_allclose(a.image, b.image, rtol=0, atol=1e-6 * np.abs(a.image).max())  # to float32 round-off
    off = (8.5, 7.4, 40.0)
    full = fwd.solve(*off, reference=ref)
    lin = fwd.solve(*off, reference=ref, linearise_at=centre)
    assert lin.timings["assemble"] < 0.75 * full.timings["assemble"]  # one solve instead of two
    gap = np.abs(lin.image.astype(float) - full.image).max()
    assert 0 < gap < 1e-3 * np.abs(full.image).max(), gap
    theta = np.array(off)
    _, J = fwd.solve_tangent(*theta, reference=ref, linearise_at=centre)
    step = 0.02
    for k in (0, 1):
        e = np.zeros(3)
        e[k] = step
        fd = (
            fwd.solve(*(theta + e), reference=ref, linearise_at=centre).image.astype(float)
            - fwd.solve(*(theta - e), reference=ref, linearise_at=centre).image.astype(float)
        ) / (2 * step)
        assert np.abs(fd - J[k]).max() < 1e-3 * np.abs(J[k]).max(), k


def _central(f, x, step):
    return (f(x + step) - f(x - step)) / (2 * step)


def test_derivatives_are_smooth_with_morph_not_with_remesh(fwd):
    """Central differences of O2 in d at steps 0.05 and 0.25 mm: the morphed map is smooth, so
    the two agree to the truncation error; the remeshed map jitters."""
    from elastimap.solver import solve

    ref = fwd.reference_for(8.0, 7.0)

    def morph_o2(d):
        return fwd.solve(d, 7.0, 50.0, reference=ref).O2

    def remesh_o2(d):
        return solve(TINY.with_inclusion(d=d, h=7.0)).O2

    dm = [_central(morph_o2, 8.0, s) for s in (0.05, 0.25)]
    dr = [_central(remesh_o2, 8.0, s) for s in (0.05, 0.25)]
    spread_m = abs(dm[0] / dm[1] - 1)
    spread_r = abs(dr[0] / dr[1] - 1)
    assert spread_m < 0.01, dm
    assert spread_r > 5 * spread_m, (dr, dm)


def test_sizing_by_d_drops_the_floor_and_refines_around_the_inclusion():
    from elastimap.solver.geometry import _sizes

    fixed = SolveParams().with_inclusion(d=2.0, h=4.0)
    by_d = fixed.replace(disc=Discretisation(sizing="by_d"))
    *_, h_inc_f, g_f = _sizes(fixed)
    *_, h_inc_d, g_d = _sizes(by_d)
    assert h_inc_f == 0.25 and h_inc_d == pytest.approx(2.0 / 12)  # elements per diameter kept for d = 2
    assert g_d < g_f
    assert "sizing" not in fixed.to_dict()["disc"] and by_d.to_dict()["disc"]["sizing"] == "by_d"


def test_sweep_and_verify_reject_bad_switches():
    import subprocess
    import sys

    from elastimap.sweep.run import SweepConfig

    with pytest.raises(UserError) as err:
        SweepConfig(geometry="warp").validate()
    assert err.value.param == "geometry"
    r = subprocess.run(
        [sys.executable, "-m", "elastimap.solver.verify_morph", "--steps", "0.1,-1"], capture_output=True, text=True
    )
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "--steps" in r.stderr


def test_inclusion_press_on_the_reference_press_factors(monkeypatch):
    """An inclusion press whose own factors are missing or far is solved by CG on the reference
    press's factors.  Right after the reference press on the same mesh (every sample's second
    press) it solves for the difference of the two presses, on any mesh size (``fem.PRESS_*``);
    otherwise only large meshes borrow (``Model._borrow``), here forced on the tiny mesh (every size
    borrows).  Either way the image and its tangent (whose back-solves factorise the inclusion's
    matrix first) equal those of a model that factorises, and the inclusion solver made no
    factorisation for the image; a modulus beyond ``PRESS_MAX_RATIO`` of the tissue's factorises."""
    import functools

    import elastimap.solver.fem as fem
    from elastimap.solver.morph import MorphedForward
    from elastimap.solver.reduction import Recycled

    theta = (8.3, 7.2, 40.0)

    def inclusion_solver(f):
        return next(iter(f._entries.values())).model.recycled["inclusion"]

    with monkeypatch.context() as m:
        m.setattr(fem, "PRESS_MAX_RATIO", 0.0)  # no difference press: the tiny mesh factorises
        with MorphedForward(TINY) as f:
            plain = f.solve(*theta).image.astype(float)
            plain_J = f.solve_tangent(*theta)[1]
            assert inclusion_solver(f).borrowed == 0
        m.setattr(fem, "BORROW_MIN_UNKNOWNS", 1)  # every size borrows
        m.setattr(fem, "Recycled", functools.partial(Recycled, blr_min=1))  # with block low-rank factors
        with MorphedForward(TINY) as f:
            img = f.solve(*theta).image.astype(float)
            rec = inclusion_solver(f)
            assert rec.borrowed == 1 and rec.factorisations == 0
            np.testing.assert_allclose(img, plain, rtol=0, atol=1e-6 * np.abs(plain).max())
            f.solve(theta[0], theta[1], 300.0)  # beyond BORROW_MAX_RATIO of the tissue: its own factors
            assert rec.borrowed == 1 and rec.factorisations == 1
    with MorphedForward(TINY) as f:  # the difference press (the shipped rule)
        img = f.solve(*theta).image.astype(float)
        rec = inclusion_solver(f)
        assert rec.borrowed == 1 and rec.factorisations == 0
        np.testing.assert_allclose(img, plain, rtol=0, atol=1e-6 * np.abs(plain).max())
        f.solve(theta[0], theta[1], 1.2 * fem.PRESS_MAX_RATIO * TINY.tissue.E)  # beyond PRESS_MAX_RATIO
        assert rec.borrowed == 1 and rec.factorisations == 1
    with MorphedForward(TINY) as f:
        _res, J = f.solve_tangent(*theta)
        rec = inclusion_solver(f)
        assert rec.borrowed == 1 and rec.factorisations == 1  # the tangent's back-solves factorised it
        np.testing.assert_allclose(J, plain_J, rtol=0, atol=1e-6 * np.abs(plain_J).max())


def test_a_looser_cg_tolerance_reaches_the_solvers_and_keeps_the_image(monkeypatch):
    """``MorphedForward(cg_rtol=)`` (what a fit's maps use, identify.forward_maps.FIT_CG_RTOL) sets the
    tolerance of every recycled CG solver of its models; forced to solve by CG on the tiny mesh
    (borrowed factors, as the large meshes do), the image at 1e-9 equals the default 1e-12's to
    1e-6 of its peak, in fewer iterations; a tolerance outside (0, 1) is refused by name."""
    import functools

    import elastimap.solver.fem as fem
    from elastimap.solver.morph import MorphedForward
    from elastimap.solver.reduction import CG_RTOL, Recycled

    monkeypatch.setattr(fem, "BORROW_MIN_UNKNOWNS", 1)
    monkeypatch.setattr(fem, "Recycled", functools.partial(Recycled, blr_min=1))
    monkeypatch.setattr(fem, "PRESS_MAX_RATIO", 0.0)  # the full press by CG, not the difference of the two
    theta = (8.3, 7.2, 40.0)
    out = {}
    for rtol in (None, 1e-9):
        with MorphedForward(TINY, cg_rtol=rtol) as f:
            img = f.solve(*theta).image.astype(float)
            model = next(iter(f._entries.values())).model
            rec = model.recycled["inclusion"]
            assert rec.borrowed == 1
            assert rec.ksp.getTolerances()[0] == pytest.approx(rtol or CG_RTOL)
            out[rtol] = (img, rec.iterations)
    (a, n_a), (b, n_b) = out[None], out[1e-9]
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-6 * np.abs(a).max())
    assert n_b < n_a
    with pytest.raises(UserError, match="cg_rtol"):
        MorphedForward(TINY, cg_rtol=0.0)
