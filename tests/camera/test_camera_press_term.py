"""The flat field's press uncertainty carried by the fit (docs/camera.md, 'The flat field's press
uncertainty'): the whitening it needs, the press sensitivity of the recovered image, and on the tiny mesh
that the term takes the pull of a press error at the footprint's rim off d.  SYNTHETIC throughout."""

from __future__ import annotations

import numpy as np
import pytest

from elastimap.camera.deflection import PressTerm, press_modes, press_sensitivity, press_spread
from elastimap.camera.optics import SensorModel
from elastimap.identify.fit import Whiten


def test_whiten_is_generalised_least_squares_under_diagonal_plus_low_rank():
    """``|W e|² = eᵀ (diag s² + U Uᵀ)⁻¹ e`` for vectors and, column by column, for matrices."""
    rng = np.random.default_rng(3)
    p, K = 40, 5
    s = rng.uniform(0.5, 2.0, p)
    U = rng.standard_normal((p, K))
    S = np.diag(s**2) + U @ U.T
    W = Whiten(s, U)
    e = rng.standard_normal(p)
    assert np.linalg.norm(W(e)) ** 2 == pytest.approx(e @ np.linalg.solve(S, e), rel=1e-10)
    E = rng.standard_normal((p, 3))
    np.testing.assert_allclose(W(E).T @ W(E), E.T @ np.linalg.solve(S, E), rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(Whiten(s)(e), e / s)  # without U: e / s, as before
    np.testing.assert_array_equal(Whiten(s, np.zeros((p, 0)))(e), e / s)


def test_press_sensitivity_is_the_derivative_of_the_inverse_response():
    """``J = ∂Δw/∂w_b`` at fixed frames, against a central difference of steps 2-3 of
    :func:`elastimap.camera.deflection.difference_image` (noise-free, per pixel)."""
    s = SensorModel()
    c = s.stray / s.level
    w_b = np.linspace(0.05, 0.5, 7)
    dw = np.linspace(0.0, 0.04, 7)
    rho = (c + s.scatter(w_b + dw)) / (c + s.scatter(w_b))  # u_F / u_B, fixed by the frames

    def recovered(wb):
        sF = rho * (c + s.scatter(wb)) - c
        return -s.w_sat * np.log((1 - sF) / (1 - s.scatter(wb)))

    np.testing.assert_allclose(recovered(w_b), dw, atol=1e-12)
    h = 1e-6
    fd = (recovered(w_b + h) - recovered(w_b - h)) / (2 * h)
    np.testing.assert_allclose(press_sensitivity(dw, w_b, s), fd, rtol=1e-5, atol=1e-9)
    assert press_sensitivity(0.0, 0.2, s) == pytest.approx(0.0, abs=1e-15)  # no lesion: no error


def test_press_modes_carry_the_stated_sd():
    """``sd δ(x) = σ_s(x)``: the modes' pointwise variance is the prior's."""
    rng = np.random.default_rng(0)
    sd = np.abs(rng.standard_normal((50, 50))) * 1e-3
    B = press_modes(sd, 0.5)
    np.testing.assert_allclose(np.sqrt((B**2).sum(axis=1)), sd.ravel(), rtol=1e-12)
    ref = np.zeros((50, 50))
    assert press_spread(ref, [ref, ref], 0.5).max() == 0.0


@pytest.fixture(scope="module")
def rim_case():
    pytest.importorskip("elastimap.solver.morph", reason="the morphed forward map is not available")
    from elastimap.identify.forward_maps import forward_map

    truth = np.array([10.0, 8.0, 30.0])
    f = forward_map("tiny", "morph").pin(truth[0], truth[1])
    res = f(*truth)
    ref = np.asarray(res.image_raw, float) - np.asarray(res.image, float)
    n = ref.shape[0]
    y = (np.arange(n) - (n - 1) / 2) * 0.5
    r = np.hypot(*np.meshgrid(y, y, indexing="ij"))
    rim = 1 / (1 + np.exp(-(r - 10.0)))  # 0 inside ~9 mm, 1 beyond ~11 mm
    return truth, f, res, ref, r, rim


def test_press_term_takes_a_rim_press_error_off_d(rim_case):
    """Tiny mesh (SYNTHETIC, self-consistency): the image of a lesion recovered with a flat field whose
    press is 4 µm too high beyond ~10 mm of the axis (the error scale J δ of the press term's own
    derivation) pulls the closed fit's d; with the press term (sd 0.3 µm inside, 4 µm at the rim) the
    pixels there are down-weighted and d's error shrinks (measured 2026-11-28: d 9.63 -> 10.00 mm for a
    true 10, E 38.8 -> 30.0 kPa for 30)."""
    from elastimap.identify.fit import fit_image

    truth, f, res, ref, r, rim = rim_case
    s = SensorModel()
    img = np.asarray(res.image, float)
    delta = 4e-3 * rim
    I = img + press_sensitivity(img, ref, s) * delta
    sd = 3e-4 + 4e-3 * rim
    term = PressTerm(ref, press_modes(sd, 0.5), s)
    sigma = 1e-3 * img.max()
    start = truth * [1.05, 0.97, 1.2]
    plain = fit_image(I, sigma, start, f)
    carried = fit_image(I, sigma, start, f, shared=term)
    e_plain = abs(plain.theta[0] / truth[0] - 1)
    e_term = abs(carried.theta[0] / truth[0] - 1)
    assert e_plain > 0.02, plain.theta  # the press error does pull the closed fit
    assert e_term < 0.2 * e_plain, (plain.theta, carried.theta)
    assert carried.lo[0] <= truth[0] <= carried.hi[0]
    # and without any press error the term costs nothing in the estimate
    exact = fit_image(img, sigma, start, f, shared=term)
    np.testing.assert_allclose(exact.theta, truth, rtol=3e-3)


def test_a_calibration_without_the_press_record_fits_as_before():
    """No ``press_sd`` in the deflection record (a calibration made without ``--press-uncertainty``, or
    before it): no term, and the marginal covariance is the one without shared columns, bit for bit."""
    from elastimap.camera.calibration import press_term
    from elastimap.identify.discrepancy import Marginal

    rec = {"reference": np.full((6, 6), 0.1).tolist(), "pixel": 0.5, "scale": 1.0}
    assert press_term(rec) is None and press_term(None) is None
    assert press_term(dict(rec, press_sd=np.full((6, 6), 1e-3).tolist())) is not None
    rng = np.random.default_rng(1)
    m = np.exp(-((np.arange(36).reshape(6, 6) - 17.5) ** 2) / 80.0)
    I = m + 0.01 * rng.standard_normal(m.shape)
    J = rng.standard_normal((36, 3))
    a = Marginal(I, np.full(m.shape, 0.01), m, 0.5).step(m.ravel(), J)
    b = Marginal(I, np.full(m.shape, 0.01), m, 0.5, shared=np.zeros((36, 0))).step(m.ravel(), J)
    np.testing.assert_array_equal(a.cov, b.cov)
    c = Marginal(I, np.full(m.shape, 0.01), m, 0.5, shared=0.02 * m.reshape(-1, 1)).step(m.ravel(), J)
    assert np.all(np.diag(c.cov) >= np.diag(a.cov) - 1e-15)  # a shared error never narrows
