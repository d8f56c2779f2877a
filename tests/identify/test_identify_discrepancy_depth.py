"""The model-form term's depth mode (:data:`elastimap.identify.discrepancy.DEPTH`) on SYNTHETIC analytic
images: learnt from phantoms whose world puts the inclusion deeper than elastimap's map does, and carried
by the fit as a shift of h alone (:func:`elastimap.identify.fit.depth_shift`)."""

from __future__ import annotations

import numpy as np
import pytest

from elastimap.errors import UserError
from elastimap.identify import discrepancy as dy
from elastimap.identify.coords import FitCoords
from elastimap.identify.fit import DesignPrior, depth_shift, fit_image

PIX = 0.5
_Y, _X = dy._grid((40, 40), PIX)
_R2 = _X**2 + _Y**2
#: the SYNTHETIC world's depth error: its inclusion lies 3 % deeper than the map's
BETA_H = 0.03
PHANTOMS = [
    (5, 8, 80),
    (8, 8, 80),
    (11, 8, 80),
    (8, 6, 80),
    (8, 10, 80),
    (8, 12, 80),
    (8, 8, 30),
    (8, 8, 60),
    (8, 8, 120),
]


def bump(d, h, E):
    """SYNTHETIC difference image (mm, 40 x 40 pixels of 0.5 mm): width following d and h, a depth-damped
    amplitude and a broad negative halo whose share falls as E rises and grows with depth (d, h and E
    all identifiable; a depth change is more than a change of the bump's height and width, as in the
    FEM, where 17–38 % of ``h ∂m/∂h`` lies outside those two modes)."""
    amp = 1e-2 * d**2 / h
    w, w2 = 0.45 * d + 0.35 * h, 0.3 * d + 1.5 * h
    s = E / (E + 40.0)
    return amp * (s * np.exp(-_R2 / (2 * w**2)) - 0.6 * (1 - s) * (h / 8) ** 2 * np.exp(-_R2 / (2 * w2**2)))


def depth_image(d, h, E, eps=1e-4):
    """``h ∂m/∂h`` (mm) of :func:`bump` by central differences."""
    return h * (bump(d, h + eps, E) - bump(d, h - eps, E)) / (2 * eps)


def world(d, h, E):
    return bump(d, h * (1 + BETA_H), E)


def noise(th):
    return 2e-3 * np.abs(bump(*th)).max()


@pytest.fixture(scope="module")
def learnt():
    """The term learnt from nine SYNTHETIC phantoms of the deeper world (one noise draw each)."""
    rng = np.random.default_rng(7)
    R, M, S, D = [], [], [], []
    for th in PHANTOMS:
        m = bump(*th)
        s = np.full(m.shape, noise(th))
        R.append(world(*th) + s * rng.standard_normal(m.shape) - m)
        M.append(m)
        S.append(s)
        D.append(depth_image(*th))
    return dy.learn(R, M, S, PIX, which=dy.DEPTH_MODES, depths=D), (R, M, S, D)


def test_the_depth_mode_is_the_maps_derivative_and_needs_it():
    th = (8, 8, 80)
    P = dy.modes(bump(*th), PIX, dy.DEPTH_MODES, depth_image(*th))
    assert P.shape == (40 * 40, 3) and np.allclose(P[:, 2], depth_image(*th).ravel())
    # first order: m(h (1 + β)) − m(h) ≈ β h ∂m/∂h
    d_img = (world(*th) - bump(*th)).ravel()
    assert np.linalg.norm(d_img - BETA_H * P[:, 2]) < 0.05 * np.linalg.norm(d_img)
    with pytest.raises(UserError, match="depth"):
        dy.modes(bump(*th), PIX, dy.DEPTH_MODES)
    assert dy.MODES == ("amplitude", "width")  # the default term (and gap's prior) has no depth mode


def test_learn_finds_the_worlds_depth_error(learnt):
    disc, _ = learnt
    assert disc.modes == dy.DEPTH_MODES
    mu, var = disc.depth_shift()
    assert mu == pytest.approx(BETA_H, abs=0.005)
    assert np.sqrt(var) < 0.02  # the spread shrinks below the prior's 2 % from nine consistent phantoms
    assert np.abs(disc.mean[:2]).max() < 0.01  # a depth error is not read as an amplitude or a width
    back = dy.Discrepancy.from_dict(disc.to_dict())
    assert back.depth_shift() == pytest.approx(disc.depth_shift())


def test_without_the_depth_mode_a_term_is_unchanged(learnt):
    disc, _ = learnt
    old = disc.image_term()
    assert old.modes == dy.MODES and old.depth_shift() is None
    assert np.allclose(old.mean, disc.mean[:2]) and np.allclose(old.prior_cov, disc.prior_cov[:2, :2])
    X, prior = FitCoords(), DesignPrior()
    lb, ub = X.box(prior.d_range, prior.E_range)
    x, C = X.x([8.0, 8.0, 60.0]), np.diag([0.01, 0.001, 0.04])
    x2, C2 = depth_shift(X, x, C, old, lb, ub)
    assert np.array_equal(x2, x) and np.array_equal(C2, C)


def test_the_depth_shift_moves_h_alone(learnt):
    disc, _ = learnt
    mu, var = disc.depth_shift()
    X, prior = FitCoords(), DesignPrior()
    lb, ub = X.box(prior.d_range, prior.E_range)
    th = np.array([8.0, 8.0 * (1 + mu), 60.0])
    C = np.diag([0.01, 0.001, 0.04])
    x2, C2 = depth_shift(X, X.x(th), C, disc, lb, ub)
    th2 = X.theta(x2)
    assert th2[0] == pytest.approx(th[0], rel=1e-12) and th2[2] == pytest.approx(th[2], rel=1e-12)
    assert np.log(th2[1] / th[1]) == pytest.approx(-mu, rel=1e-9)  # ln h ← ln ĥ − μ_h
    G = X.dtheta(x2)
    dvar = np.diag(G @ (C2 - C) @ G.T)  # in (d, h, ln E)
    assert dvar[0] == pytest.approx(0, abs=1e-15) and dvar[2] == pytest.approx(0, abs=1e-15)
    assert np.sqrt(dvar[1]) / th[1] == pytest.approx(np.sqrt(var), rel=1e-9)  # sd of ln h grows by v_h


def test_marginal_carries_the_depth_mode_only_with_the_maps_derivative(learnt):
    disc, (R, M, S, D) = learnt
    assert dy.Marginal(M[0] + R[0], S[0], M[0], PIX, disc).P_w.shape[1] == 2
    assert dy.Marginal(M[0] + R[0], S[0], M[0], PIX, disc, D[0]).P_w.shape[1] == 3
    loo = dy.leave_one_out(R, M, S, PIX, depths=D, which=dy.DEPTH_MODES)
    assert all(h.z.shape == (3,) for h in loo)
    assert np.median([h.chi2_px for h in loo]) < 1.5  # the depth error is held, not left in the residual


def test_forward_images_take_the_depth_mode_from_the_maps_exact_derivative():
    class Map:
        has_tangent = True

        def tangent(self, d, h, E):
            eps = 1e-4
            J = np.stack([np.zeros_like(_R2), (bump(d, h + eps, E) - bump(d, h - eps, E)) / (2 * eps), 0 * _R2])
            return bump(d, h, E), J

    models, depths = dy.forward_images(Map(), PHANTOMS[:2])
    assert np.allclose(models[1], bump(*PHANTOMS[1])) and np.allclose(depths[1], depth_image(*PHANTOMS[1]).ravel())
    models, depths = dy.forward_images(bump, PHANTOMS[:2])
    assert depths is None and np.allclose(models[0], bump(*PHANTOMS[0]))


def test_the_fit_carrying_the_depth_mode_corrects_h_and_moves_neither_d_nor_e(learnt):
    """A lesion of the deeper world: the closed world's h is 3 % deep and its interval misses; with the
    learnt depth mode h is within 1 % and covered, d and E are the closed world's."""
    disc, _ = learnt
    truth = np.array([7.0, 9.0, 60.0])
    rng = np.random.default_rng(3)
    s = noise(truth)
    image = world(*truth) + s * rng.standard_normal(_R2.shape)
    kw = dict(intervals="gauss", pixel=PIX, e_scan=1)
    closed = fit_image(image, s, truth * [1.05, 0.95, 1.2], bump, **kw)
    image_only = fit_image(image, s, truth * [1.05, 0.95, 1.2], bump, discrepancy=disc.image_term(), **kw)
    open_ = fit_image(image, s, truth * [1.05, 0.95, 1.2], bump, discrepancy=disc, **kw)
    assert closed.theta[1] / truth[1] - 1 == pytest.approx(BETA_H, abs=0.01)
    assert not (closed.lo[1] <= truth[1] <= closed.hi[1])
    assert abs(open_.theta[1] / truth[1] - 1) < 0.01 and open_.lo[1] <= truth[1] <= open_.hi[1]
    assert open_.theta[[0, 2]] == pytest.approx(image_only.theta[[0, 2]], rel=1e-12)
    assert open_.relstd[[0, 2]] == pytest.approx(image_only.relstd[[0, 2]], rel=1e-9)
