"""The model-form error term (:mod:`elastimap.identify.discrepancy`) on SYNTHETIC analytic images:
its modes, what it learns from calibration phantoms, and that the fit carrying it is the marginal
generalised least squares (the covariance holds the discrepancy)."""

from __future__ import annotations

import numpy as np
import pytest

from elastimap.errors import UserError
from elastimap.identify import discrepancy as dy

PIX = 0.5


def bump(amp=0.02, width=3.0, n=50, x0=0.0):
    """SYNTHETIC difference image: a Gaussian bump (mm) on a 25 mm footprint."""
    Y, X = dy._grid((n, n), PIX)
    return amp * np.exp(-((X - x0) ** 2 + Y**2) / (2 * width**2))


def test_modes_are_the_image_its_dilation_and_a_radial_gain():
    m = bump()
    P = dy.modes(m, PIX, dy.ALL_MODES)
    assert P.shape == (m.size, 3)
    assert np.allclose(P[:, 0], m.ravel())
    # m(x / (1 + λ)) ≈ m − λ r ∂m/∂r for small λ: the width mode is the dilation's first order
    lam = 1e-3
    dilated = bump(width=3.0 * (1 + lam))
    assert np.allclose((dilated - m).ravel() / lam, -P[:, 1], atol=1e-2 * np.abs(P[:, 1]).max())
    # the tail is orthogonal to the height and the width, with the norm of m
    assert np.abs(P[:, 2] @ P[:, :2]).max() < 1e-9 * np.sum(m * m)
    assert np.linalg.norm(P[:, 2]) == pytest.approx(np.linalg.norm(m))
    assert dy.modes(m, PIX).shape == (m.size, len(dy.MODES))
    with pytest.raises(UserError, match="modes"):
        dy.modes(m, PIX, ("amplitude", "bogus"))
    with pytest.raises(UserError, match="2-D"):
        dy.modes(m.ravel(), PIX)


def draw_phantoms(n, mu, tau, rho, noise, rng, size=24):
    """SYNTHETIC calibration phantoms: bumps of several sizes, residual = Φ β + ρ a z + noise."""
    R, M, S = [], [], []
    for _ in range(n):
        m = bump(amp=0.005 + 0.03 * rng.random(), width=1.5 + 1.5 * rng.random(), n=size)
        beta = mu + tau * rng.standard_normal(len(mu))
        P = dy.modes(m, PIX)
        rem = rho * dy.envelope(m) * rng.standard_normal(m.size)
        s = np.full(m.shape, noise)
        R.append((P @ beta + rem + noise * rng.standard_normal(m.size)).reshape(m.shape))
        M.append(m)
        S.append(s)
    return R, M, S


def test_learn_recovers_the_mean_spread_and_remainder_of_many_phantoms():
    rng = np.random.default_rng(1)
    mu, tau, rho = np.array([0.015, -0.01]), np.array([0.02, 0.01]), 0.01
    R, M, S = draw_phantoms(200, mu, tau, rho, 2e-5, rng)
    d = dy.learn(R, M, S, PIX, prior_weight=1e-6)
    assert d.n_phantoms == 200
    assert (np.abs(d.mean - mu) < 4 * np.sqrt(np.diag(d.mean_cov))).all()  # within its own stated sd
    assert np.allclose(d.tau, tau, rtol=0.2)
    assert d.rho == pytest.approx(rho, rel=0.25)


def test_learn_with_few_phantoms_leans_on_the_prior_scale_and_no_spread_gives_the_prior():
    rng = np.random.default_rng(2)
    R, M, S = draw_phantoms(9, np.zeros(2), np.zeros(2), 0.0, 1e-6, rng)  # the world equals the model
    d = dy.learn(R, M, S, PIX)
    # no spread: τ² = ν₀ τ₀² / (ν₀ + n − 1), shrunk from the prior scale, never zero
    tau0 = np.array([dy.PRIOR_SCALE[k] for k in dy.MODES])
    assert np.allclose(d.tau, tau0 * np.sqrt(dy.PRIOR_WEIGHT / (dy.PRIOR_WEIGHT + 8)), rtol=0.05)
    assert np.allclose(d.mean, 0, atol=1e-3)
    one = dy.learn(R[:1], M[:1], S[:1], PIX)
    assert np.allclose(one.mean, 0) and (one.tau > 0).all()
    with pytest.raises(UserError, match="phantoms"):
        dy.learn([], [], [], PIX)


def test_augmented_fit_is_the_marginal_generalised_least_squares():
    """(x, β) jointly with the prior rows = GLS in x under Σ = diag s² + Φ C Φᵀ with mean Φ μ."""
    rng = np.random.default_rng(3)
    m = bump(amp=0.01, width=2.0, n=16)
    J = np.column_stack([bump(amp=0.01, width=2.2, n=16).ravel() - m.ravel(), np.roll(m, 1, 0).ravel()])
    disc = dy.Discrepancy(mean=np.array([0.01, 0.0]), tau=np.array([0.02, 0.03]), rho=0.02)
    sigma = 1e-4 * (1 + rng.random(m.shape))
    I = m + 1e-4 * rng.standard_normal(m.shape)
    lf = dy.linear_fit(I, m, J, sigma, PIX, disc)
    Sig = disc.covariance(m, PIX, sigma)
    Si = np.linalg.inv(Sig)
    r = I.ravel() - m.ravel() - disc.mean_image(m, PIX)
    cov = np.linalg.inv(J.T @ Si @ J)
    assert np.allclose(lf.cov, cov, rtol=1e-6)
    assert np.allclose(lf.dx, cov @ J.T @ Si @ r, rtol=1e-6, atol=1e-12)


def test_a_confounded_parameter_gets_the_interval_the_prior_allows():
    """A parameter whose image change is the amplitude mode (a stiff inclusion's E along the d–E
    valley): a 3 % amplitude difference moves it far beyond its noise-only interval; with the
    discrepancy the 95 % interval holds the truth and is as wide as the prior allows."""
    rng = np.random.default_rng(4)
    m = bump(amp=0.01, width=2.5)
    J = np.column_stack([0.1 * m.ravel(), dy.modes(m, PIX)[:, 1] * 0.2])  # x0 scales the image by 10 % a unit
    sigma = np.full(m.shape, 2e-5)
    I = 1.03 * m + 2e-5 * rng.standard_normal(m.shape)  # the world: 3 % higher, x true = 0
    closed = dy.linear_fit(I, m, J, sigma, PIX)
    assert abs(closed.dx[0]) / np.sqrt(closed.cov[0, 0]) > 20  # confidently wrong
    disc = dy.Discrepancy(tau=np.array([0.02, 0.02]), rho=0.005)
    open_ = dy.linear_fit(I, m, J, sigma, PIX, disc)
    sd = np.sqrt(open_.cov[0, 0])
    assert abs(open_.dx[0]) < 1.96 * sd
    assert sd == pytest.approx(0.2, rel=0.1)  # τ_amplitude / 0.1 per unit: the prior bounds it


def test_record_round_trips_and_refuses_bad_shapes():
    d = dy.Discrepancy(mean=np.array([0.01, 0]), tau=np.array([0.02, 0.0]), rho=0.003, n_phantoms=9)
    e = dy.Discrepancy.from_dict(d.to_dict())
    assert np.allclose(e.tau, d.tau) and e.rho == d.rho and e.n_phantoms == 9
    with pytest.raises(UserError, match="tau"):
        dy.Discrepancy(tau=np.array([0.1, 0.1, 0.1]))
    with pytest.raises(UserError, match="discrepancy"):
        dy.Discrepancy.from_dict({"modes": []})
    none = dy.Discrepancy.none()
    m = bump()
    assert np.allclose(none.sd_image(m, PIX), 0)
    # the misfit alone (no parameters, no discrepancy): χ² of the whitened residual
    lf = dy.linear_fit(m + 1e-4, m, np.zeros((m.size, 0)), 1e-4, PIX)
    assert lf.chi2 == pytest.approx(m.size) and lf.dx.size == 0


def test_learn_tells_a_smooth_remainder_from_a_white_one():
    """The remainder's correlation length is chosen by the phantoms' likelihood: smooth (ℓ = 2 mm)
    remainders give ℓ > 0, white ones ℓ = 0; the smooth one's pull on a parameter does not average
    down, so its covariance is wider."""
    rng = np.random.default_rng(5)
    shape = (24, 24)
    Lk = np.linalg.cholesky(dy.correlation(shape, PIX, 2.0) + 1e-9 * np.eye(24 * 24))
    R_s, R_w, M, S = [], [], [], []
    for _ in range(6):
        m = bump(amp=0.02, width=2.0 + rng.random(), n=24)
        a = dy.envelope(m)
        noise = 1e-5 * rng.standard_normal(m.size)
        R_s.append((0.02 * a * (Lk @ rng.standard_normal(m.size)) + noise).reshape(shape))
        R_w.append((0.02 * a * rng.standard_normal(m.size) + noise).reshape(shape))
        M.append(m)
        S.append(np.full(shape, 1e-5))
    smooth = dy.learn(R_s, M, S, PIX)
    white = dy.learn(R_w, M, S, PIX)
    assert smooth.ell > 0 and white.ell == 0
    m = M[0]
    J = dy.modes(m, PIX, dy.ALL_MODES)[:, 2:]  # a parameter the modes do not hold
    wide = dy.linear_fit(m, m, J, S[0], PIX, smooth)
    narrow = dy.linear_fit(m, m, J, S[0], PIX, dy.Discrepancy(**{**smooth.__dict__, "ell": 0.0}))
    assert wide.cov[0, 0] > 2 * narrow.cov[0, 0]


def test_calibrate_learns_from_measured_phantoms_and_scores_each_left_out():
    """calibrate: elastimap's image at each phantom's known design, the measured minus it learnt, and a
    leave-one-phantom-out check that holds the held-out phantoms (SYNTHETIC: the world is the model
    with a 2 ± 1 % amplitude difference)."""
    rng = np.random.default_rng(6)
    thetas = [(4 + i, 6.0, 50.0) for i in range(8)]

    def forward(d, h, E):
        return bump(amp=0.002 * d, width=0.4 * d, n=24)

    measured, sigmas = [], []
    for th in thetas:
        m = forward(*th)
        s = np.full(m.shape, 1e-5)
        measured.append(m * (1.02 + 0.01 * rng.standard_normal()) + s * rng.standard_normal(m.shape))
        sigmas.append(s)
    d, loo = dy.calibrate(measured, sigmas, thetas, forward, PIX)
    assert d.n_phantoms == 8 and d.mean[0] == pytest.approx(0.02, abs=0.01)
    assert len(loo) == 8
    assert np.mean([h.covered[0] for h in loo]) >= 0.75
    assert 0.3 < np.median([h.chi2_px for h in loo]) < 3
    with pytest.raises(UserError, match="at least 3"):
        dy.leave_one_out(measured[:2], [forward(*t) for t in thetas[:2]], sigmas[:2], PIX)


def test_a_learnt_difference_far_beyond_the_prior_scale_is_flagged():
    small = dy.Discrepancy(mean=np.array([0.012, 0.0]), tau=np.array([0.014, 0.009]), rho=0.005)
    assert small.beyond() == []
    big = dy.Discrepancy(mean=np.array([-0.17, 0.0]), tau=np.array([0.014, 0.009]), rho=0.06)
    assert big.beyond() == ["amplitude", "remainder"]
