"""The physics fit: maximum likelihood through the forward model (elastimap.identify.fit, .coords, .forward_maps).

The fast tests use a SYNTHETIC analytic image model; one test fits the real FEM on the tiny mesh."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from elastimap.errors import UserError
from elastimap.identify.coords import COORDS, FitCoords, to_theta, to_x
from elastimap.identify.fit import fit_image

_Y, _X = np.mgrid[0:16, 0:16] * 0.75
_R2 = _X.ravel() ** 2 + _Y.ravel() ** 2


def bump(theta):
    """SYNTHETIC difference image (mm): a bump whose width follows d and h, a depth-damped amplitude,
    and a broad negative halo whose share falls as E rises (so d, h and E are all identifiable)."""
    d, h, E = theta
    amp = 1e-2 * d**2 / h
    w = 0.45 * d + 0.35 * h
    s = E / (E + 40.0)
    return amp * (s * np.exp(-_R2 / (2 * w**2)) - 0.3 * (1 - s) * np.exp(-_R2 / (8 * w**2)))


def bump_map(d, h, E):
    return bump((d, h, E))


def test_parametrisation_roundtrip_keeps_h_inside_the_depth_range():
    for th in ([2.0, 3.0, 10.0], [8.0, 8.0, 55.0], [15.0, 10.5, 200.0]):
        np.testing.assert_allclose(to_theta(to_x(th)), th, rtol=1e-12)
    x = to_x([8.0, 8.0, 50.0])
    assert 0 <= x[1] <= 1 and x[2] == pytest.approx(np.log(50.0))


@settings(max_examples=60, deadline=None)
@given(
    coord=st.sampled_from(COORDS),
    d=st.floats(2.0, 15.0),
    u=st.floats(0.0, 1.0),
    E=st.floats(10.0, 200.0),
    Et=st.floats(0.5, 30.0),
)
def test_fit_coordinates_roundtrip_and_their_derivative(coord, d, u, E, Et):
    """FitCoords: theta -> x -> theta is the identity over the design box (also for a tissue stiffer
    than the box's softest inclusion), and dtheta is the derivative of (d, h, ln E) in x (central
    differences)."""
    X = FitCoords(coord=coord, E_tissue=Et)
    th = to_theta([d, u, np.log(E)])
    x = X.x(th)
    np.testing.assert_allclose(X.theta(x), th, rtol=1e-9)
    lb, ub = X.box((2.0, 15.0), (10.0, 200.0))
    assert np.all(lb - 1e-12 <= x) and np.all(x <= ub + 1e-12)

    def q(x):
        t = X.theta(x)
        return np.array([t[0], t[1], np.log(t[2])])

    eps = 1e-6
    num = np.column_stack([(q(x + eps * e) - q(x - eps * e)) / (2 * eps) for e in np.eye(3)])
    np.testing.assert_allclose(X.dtheta(x), num, rtol=1e-5, atol=1e-7)


def test_contrast_coordinate_straightens_the_equal_amplitude_valley():
    """On the curve d³ c(E) = const (equal image amplitude to first order, c Eshelby's contrast) the
    contrast coordinate e moves linearly with ln d (slope −3), while ln E bends: a stiff inclusion's
    ln E runs away as c saturates."""
    X, L = FitCoords(coord="contrast", E_tissue=5.0), FitCoords(coord="log", E_tissue=5.0)
    a, b = 5.0, 7.5
    c0 = (20.0 - a) / (20.0 + b) * 8.0**3  # E from about 60 kPa (d 7 mm) to 11 kPa (d 9.5 mm)
    d = np.linspace(7.0, 9.5, 6)
    c = c0 / d**3
    E = (a + b * c) / (1 - c)
    e = np.array([X.x([di, 8.0, Ei])[2] for di, Ei in zip(d, E)])
    lnE = np.array([L.x([di, 8.0, Ei])[2] for di, Ei in zip(d, E)])
    np.testing.assert_allclose(np.diff(e) / np.diff(np.log(d)), -3.0, rtol=1e-9)
    slopes = np.diff(lnE) / np.diff(np.log(d))
    assert slopes.max() / slopes.min() < 0.5  # ln E's slope changes by more than a factor of two


def test_fit_coordinates_name_a_bad_choice():
    with pytest.raises(UserError, match="coords"):
        FitCoords(coord="sqrt")
    with pytest.raises(UserError, match="E_tissue"):
        FitCoords(E_tissue=0.0)


def test_bad_input_is_a_user_error():
    I = bump([8.0, 7.0, 60.0])
    with pytest.raises(UserError, match="sigma"):
        fit_image(I, 0.0, [8, 7, 60], bump_map)
    with pytest.raises(UserError, match="image"):
        fit_image(np.full_like(I, np.nan), 1e-3, [8, 7, 60], bump_map)
    with pytest.raises(UserError, match="theta0"):
        fit_image(I, 1e-3, [8, 7, -1], bump_map)
    with pytest.raises(UserError, match="sigma"):
        fit_image(I, -1.0, [8, 7, 60], bump_map)
    with pytest.raises(UserError, match="tangent"):  # a plain function has no exact derivative
        fit_image(I, 1e-3, [8, 7, 60], lambda d, h, E: bump([d, h, E]), tangent=True)


def test_physics_fit_on_the_tiny_mesh():
    """The real forward model through the inference API (elastimap.camera.infer.refine_estimates):
    a noise-free image of the REMESHING tiny-mesh solver (not the fit's map), 1 % pixel noise
    assumed, start 30 % off in E and 6 % in d; the fit runs the morphed tiny map and measures its
    error against the coarse level.  The tiny mesh is far from converged, so this checks the
    direction of the fit and that its intervals hold the truth; accuracy: workflows/frames_benchmark.py."""
    pytest.importorskip("elastimap.solver.morph")
    from elastimap.camera.infer import Estimate, refine_estimates
    from elastimap.identify.forward_maps import forward_map

    truth = np.array([8.0, 7.0, 40.0])
    I = forward_map("tiny", "remesh")(*truth).image
    start = np.array([8.5, 7.0, 52.0])
    nan3 = np.full(3, np.nan)
    e = Estimate("x", nan3, nan3, start.copy(), nan3, start, start, 1, ["non_identifiable:E"], input="image")
    (e,) = refine_estimates([e], I[None], image_noise=0.01, mesh="tiny")
    assert e.input == "image+fem_refined"
    assert abs(e.d / truth[0] - 1) < 0.05 and abs(e.h / truth[1] - 1) < 0.05, e
    assert np.all(e.lo <= truth) and np.all(truth <= e.hi), (e.mean, e.lo, e.hi)
    assert np.all(np.isfinite(e.crb)) and e.fit.n_solves >= 7 and e.fit.n_alt >= 1
    assert "model_mismatch" not in e.flags
    # the flag now follows the fit's own standard deviation
    assert ("non_identifiable:E" in e.flags) == (e.crb[2] > 0.10)


@pytest.mark.parametrize(("truth", "outside"), [((8.0, 7.0, 60.0), False), ((17.0, 7.0, 60.0), True)])
def test_a_fit_that_ends_on_the_design_edge_reports_no_number(truth, outside):
    """SYNTHETIC bump map through refine_estimates: a lesion inside the box is fitted and reported;
    one larger than the design box allows (d 17 mm > 15) ends on the box's edge (measured: h and E
    there, compensating for d), is flagged ``at_design_edge:q`` and reports none of d, h, E as a
    number (the likelihood's maximum is outside the box, so the Gauss–Newton interval holds for
    none of them)."""
    from elastimap.camera.infer import Estimate, refine_estimates

    I = bump(np.array(truth))
    start = np.array([9.0, 7.0, 50.0])
    nan3 = np.full(3, np.nan)
    e = Estimate("x", nan3, nan3, start.copy(), nan3, start, start, 1, [], input="image")
    (e,) = refine_estimates([e], I[None], image_noise=0.01, forward=lambda d, h, E: bump((d, h, E)))
    edges = [f for f in e.flags if f.startswith("at_design_edge:")]
    reportable = [e.reportable(q) for q in "dhE"]
    if not outside:
        assert edges == [] and all(reportable), e.flags
        np.testing.assert_allclose(e.mean, truth, rtol=1e-2)
    else:
        assert edges and not any(reportable), e.flags
        assert not any(e.to_dict()[f"{q}_reportable"] for q in "dhE")


def _infer(*args: str):
    """``elastimap camera infer ARGS`` in a subprocess (what a user's shell gets)."""
    import subprocess
    import sys

    return subprocess.run(
        [sys.executable, "-m", "elastimap.camera.cli", "infer", *args], capture_output=True, text=True
    )


def test_cli_refine_needs_a_fem_image(tmp_path):
    r = _infer("--model", str(tmp_path), "--features", "1", "2", "3", "--refine")
    assert r.returncode == 2 and "--refine" in r.stderr and "Traceback" not in r.stderr


def test_several_model_error_levels_add_their_variances():
    """fit_image with two 'other levels' (SYNTHETIC: the bump with d off by ±1 %): each level
    difference adds its own systematic term, so the interval is at least as wide as with either
    alone and as with the same level twice it is √2 times one (C_sys = Σ b_k b_kᵀ)."""
    truth = np.array([8.0, 7.0, 60.0])
    I = bump(truth)
    sig = 2e-3 * I.max()

    def level(f):
        return lambda d, h, E: bump((d * f, h, E))

    lo_, hi_, fit_map = level(0.99), level(1.01), level(1.0)
    kw = {"e_scan": 0, "tangent": False}
    one = fit_image(I, sig, truth, fit_map, forward_alt=lo_, **kw)
    other = fit_image(I, sig, truth, fit_map, forward_alt=hi_, **kw)
    both = fit_image(I, sig, truth, fit_map, forward_alt=[lo_, hi_], **kw)
    twice = fit_image(I, sig, truth, fit_map, forward_alt=[lo_, lo_], **kw)
    np.testing.assert_allclose(both.theta, truth, rtol=1e-3)  # noise-free, the map is right
    assert np.all(both.relstd >= np.maximum(one.relstd, other.relstd) * (1 - 1e-6))
    assert both.n_alt == one.n_alt + other.n_alt
    assert twice.model_error == pytest.approx(np.sqrt(2) * one.model_error, rel=1e-6)


def test_defect_correction_by_a_finer_level_removes_the_cheaper_maps_bias():
    """fit_image with ``forward_fine`` (SYNTHETIC: the 'finer level' is the bump itself, the cheaper
    map the bump with d scaled by 0.97): the cheaper map alone lands ~3 % off in d; corrected at the
    start of each pass by the finer level's defect, the fit converges to the truth (the fixed point
    of m(x) + m_fine(x_s) − m(x_s) = I is m_fine(x) = I), with a few finer evaluations."""
    truth = np.array([8.0, 7.0, 60.0])
    I = bump(truth)
    sig = 2e-3 * I.max()

    def cheap(d, h, E):
        return bump((0.97 * d, h, E))

    kw = {"e_scan": 0, "tangent": False, "max_passes": 4}
    plain = fit_image(I, sig, truth, cheap, **kw)
    corrected = fit_image(I, sig, truth, cheap, forward_fine=lambda d, h, E: bump((d, h, E)), **kw)
    assert abs(plain.theta[0] / truth[0] - 1) > 0.02  # the cheaper map's bias
    np.testing.assert_allclose(corrected.theta, truth, rtol=2e-3)
    assert 1 <= corrected.n_fine <= 4 and plain.n_fine == 0
    assert corrected.chi2_red < 1e-2  # the corrected map reproduces the image (so does the biased one here)
    # the stopping rule is reported: with one corrected pass the fit cannot settle after the
    # correction moved it (~3 % in d), and says so
    assert corrected.converged
    short = fit_image(I, sig, truth, cheap, forward_fine=lambda d, h, E: bump((d, h, E)), **{**kw, "max_passes": 1})
    assert not short.converged and "still moving after 1 passes" in short.message
    # and which parameter: the correction moves d (the cheaper map's bias), not h or E by as much
    assert corrected.moving == [] and "d" in short.moving


def test_model_error_is_measured_where_the_first_corrected_pass_starts_and_at_the_estimate():
    """The other level is solved twice per fit however many corrected passes run (SYNTHETIC maps of
    the test above, an 'other level' with d off by 1 %): once where the first corrected pass starts
    (its weights, held for the later passes) and once at the estimate (the covariance)."""
    truth = np.array([8.0, 7.0, 60.0])
    I = bump(truth)
    calls = []

    def alt(d, h, E):
        calls.append((d, h, E))
        return bump((1.01 * d, h, E))

    def cheap(d, h, E):
        return bump((0.97 * d, h, E))

    fit = fit_image(
        I,
        2e-3 * I.max(),
        truth * [1.04, 1, 1],
        cheap,
        forward_alt=alt,
        forward_fine=lambda d, h, E: bump((d, h, E)),
        e_scan=0,
        tangent=False,
        max_passes=3,
    )
    assert fit.n_fine >= 2  # more than one corrected pass ran
    assert fit.n_alt == len(calls) == 2
    np.testing.assert_allclose(calls[-1], fit.theta)


@pytest.mark.parametrize(
    ("extra", "says"),
    [
        (["--refine-correct", "fine"], "only applies with --refine"),
        (["--refine", "--mesh", "default", "--refine-correct", "coarse"], "finer than default: fine, finer"),
        (
            ["--refine", "--refine-correct", "huge"],
            "must be auto, none or a mesh level finer than coarse: default, fine, finer (got 'huge')",
        ),
    ],
)
def test_cli_refine_correct_names_what_is_allowed(tmp_path, extra, says):
    """``--refine-correct`` takes auto (the default), none or a level finer than --mesh; anything else
    is one line naming the flag and what it allows."""
    fem = tmp_path / "img.npy"
    np.save(fem, np.zeros((4, 4)))
    r = _infer("--model", str(tmp_path), "--fem-image", str(fem), *extra)
    assert r.returncode == 2 and "--refine-correct" in r.stderr and says in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_refine_estimates_checks_the_correcting_level():
    from elastimap.camera.infer import refine_estimates

    with pytest.raises(UserError, match="correct"):
        refine_estimates([], None, mesh="default", correct="coarse")


def test_default_correct_is_the_benchmarked_configuration():
    """``infer --refine`` corrects the coarse map by ``fine`` unless told otherwise (the camera-frame benchmark
    measured that configuration, docs/camera.md, 'Inference'); the other levels fit their map alone."""
    from elastimap.identify.forward_maps import check_correct, default_correct

    assert default_correct("coarse") == "fine"
    for mesh in ("tiny", "default", "fine", "finer"):
        assert default_correct(mesh) is None
    check_correct("coarse", default_correct("coarse"))
    with pytest.raises(UserError, match="mesh"):
        default_correct("huge")


def test_direct_passes_fit_the_finer_level_itself_and_agree_with_the_defect_correction():
    """``fine="direct"`` (SYNTHETIC, the maps of the test above): passes after the first fit the finer
    map itself, so they land on its fit as the defect-corrected passes do (their fixed point), the
    finer level's evaluations counted in ``n_fine``; a mode that does not exist is named."""
    truth = np.array([8.0, 7.0, 60.0])
    I = bump(truth)
    sig = 2e-3 * I.max()

    def cheap(d, h, E):
        return bump((0.97 * d, h, E))

    def finer(d, h, E):
        return bump((d, h, E))

    kw = {"e_scan": 0, "tangent": False, "max_passes": 4}
    direct = fit_image(I, sig, truth * [1.05, 1.0, 0.8], cheap, forward_fine=finer, fine="direct", **kw)
    corrected = fit_image(I, sig, truth * [1.05, 1.0, 0.8], cheap, forward_fine=finer, **kw)
    np.testing.assert_allclose(direct.theta, truth, rtol=2e-3)
    np.testing.assert_allclose(direct.theta, corrected.theta, rtol=2e-3)
    assert direct.converged and direct.n_fine > corrected.n_fine  # it evaluates the finer map at every step
    # the reported interval is the Gauss–Newton one by default; the posterior interval is gone
    assert np.array_equal(direct.lo, direct.lo_gauss) and np.array_equal(direct.hi, direct.hi_gauss)
    with pytest.raises(UserError, match="intervals"):
        fit_image(I, sig, truth * [1.05, 1.0, 0.8], cheap, forward_fine=finer, intervals="posterior", **kw)
    with pytest.raises(UserError, match="fine"):
        fit_image(I, sig, truth, cheap, forward_fine=finer, fine="both", **kw)


def test_a_fit_map_morphs_from_the_reference_below_never_shrinks_by_more_than_a_rounding():
    """:func:`reference_below`: the d-bin reference ``d₀ ≤ d < √2 d₀`` (the nearest bin would shrink
    a mesh by up to 16 %, which costs far more accuracy than growing it), also for
    what ``pin`` and ``pin_exact`` hold; ``below=False`` (a `tiny` fit's maps) keeps the nearest bin
    (a stub morphed map: no DOLFINx; this checks the bin algebra, the accuracy: docs/history/camera.md, 'Where the valley pull comes from, and fit maps that morph from the bin below')."""
    import math

    from elastimap.identify.forward_maps import BELOW_LEVELS, ForwardMap, reference_below
    from elastimap.solver.morph import D_RATIO, Reference, reference_for

    class Stub:
        has_tangent = False

        def reference_for(self, d, h):
            return reference_for(d, h)

    for d in (2.0, 2.3, 3.0, 7.9, 8.0, 9.2, 9.8, 13.4, 15.0):
        ref = reference_below(Stub(), d, 8.0)
        assert ref.d0 <= d * (1 + 1e-9) and d < D_RATIO * ref.d0, (d, ref)
        assert ForwardMap(Stub()).pin(d, 8.0).reference == ref == ForwardMap(Stub()).pin_exact(d, 8.0).reference
    assert reference_for(9.8, 8.0).d0 == pytest.approx(8 * math.sqrt(2))  # the nearest bin: above 9.8
    assert reference_below(Stub(), 9.8, 8.0).d0 == pytest.approx(8.0)
    assert isinstance(reference_below(Stub(), 9.8, 8.0), Reference)
    assert ForwardMap(Stub(), below=False).pin(9.8, 8.0).reference == reference_for(9.8, 8.0)  # the nearest bin
    assert "tiny" not in BELOW_LEVELS and "coarse" in BELOW_LEVELS and "fine" in BELOW_LEVELS


def test_a_fits_morphed_maps_solve_to_the_fits_cg_tolerance():
    """forward_map's morphed maps carry FIT_CG_RTOL to their solvers (tests/solver/test_morph.py checks
    that a MorphedForward passes it on), looser than the solver's default."""
    from elastimap.identify.forward_maps import FIT_CG_RTOL, forward_map
    from elastimap.solver.reduction import CG_RTOL

    f = forward_map("tiny", "morph")
    assert f.morphed.cg_rtol == FIT_CG_RTOL and CG_RTOL < FIT_CG_RTOL <= 1e-9
