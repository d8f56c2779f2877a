"""Local identifiability (elastimap.identify.bounds): Fisher / Cramér–Rao on SYNTHETIC Jacobians (no solves)."""

import numpy as np

from elastimap.identify.bounds import NoiseSpec, crb_relstd, fisher, from_param, grid, to_param


def _J(n=4, p=30, seed=0):
    rng = np.random.default_rng(seed)
    img0 = np.abs(rng.normal(size=(n, p))) + 1.0
    return {
        "image": rng.normal(size=(n, p, 3)),
        "image0": img0,
        "lnF": rng.normal(size=(n, 3, 3)),
        "dF": rng.normal(size=(n, 3)) * 50.0,
    }


def test_param_roundtrip_uses_log_E():
    th = np.array([[5.0, 6.0, 30.0], [10.0, 12.0, 150.0]])
    assert np.allclose(to_param(th)[:, 2], np.log(th[:, 2]))
    assert np.allclose(from_param(to_param(th)), th)


def test_crb_matches_closed_form_and_scales_with_noise():
    J = _J()
    F1 = fisher(J, NoiseSpec(feature=0.01, image=0.01))
    F2 = fisher(J, NoiseSpec(feature=0.02, image=0.02))
    th = np.tile([5.0, 6.0, 30.0], (4, 1))
    r1, r2 = crb_relstd(F1["features"], th), crb_relstd(F2["features"], th)
    assert np.allclose(r2, 2 * r1)  # CRB std is linear in the noise std
    C = np.linalg.inv(J["lnF"][0].T @ J["lnF"][0] / 0.01**2)
    assert np.isclose(r1[0, 2], np.sqrt(C[2, 2]))  # ln E: relative std of E
    assert np.isclose(r1[0, 0], np.sqrt(C[0, 0]) / 5.0)


def test_more_measurements_never_worsen_the_bound():
    J = _J()
    F = fisher(J, NoiseSpec())
    th = np.tile([5.0, 6.0, 30.0], (4, 1))
    ri, rf, r2 = (crb_relstd(F[k], th) for k in ("image", "image+force", "two-depths"))
    assert np.all(rf <= ri + 1e-12)
    assert np.allclose(r2, ri / np.sqrt(2))  # linear model: a 2nd depth = noise averaging only


def test_grid_respects_depth_range():
    from elastimap.solver.params import depth_range

    T, (ds, us, Es) = grid(nd=3, nu=2, nE=2)
    assert T.shape == (12, 3)
    for d, h, _ in T:
        lo, hi = depth_range(d, 20.0)
        assert lo - 1e-9 <= h <= hi + 1e-9


def test_region_score_splits_rows_by_the_bound():
    from elastimap.workflows.studies.region_score import score

    theta = np.array([[5.0, 6.0, 20.0], [8.0, 8.0, 100.0], [10.0, 9.0, 150.0]])
    pred = np.full((2, 3, 3), np.nan)
    pred[0] = theta * np.array([1.1, 1.0, 1.5])  # +10 % d, +50 % E
    pred[1, :2] = theta[:2] * np.array([0.9, 1.0, 1.1])  # row 2 not held out in repeat 1
    crb = np.array([[0.05, 0.05, 0.05], [0.05, 0.05, 0.5], [0.05, 0.05, 0.5]])
    s = score(pred, theta, crb, threshold=0.10)
    assert np.isclose(s[("d", "all")][0], 10.0) and s[("d", "all")][1] == 3
    assert np.isclose(s[("E", "identifiable")][0], (50 + 10) / 2) and s[("E", "identifiable")][1] == 1
    assert np.isclose(s[("E", "rest")][0], (50 + 50 + 10) / 3) and s[("E", "rest")][1] == 2
    assert np.isnan(s[("h", "rest")][0]) and s[("h", "rest")][1] == 0


def test_fd_relstd_isolates_a_point_without_a_finite_bound():
    from elastimap.identify.bounds import fd_relstd

    J = _J()
    th = np.tile([5.0, 6.0, 30.0], (4, 1))
    ref = fd_relstd(J, th, NoiseSpec())
    J["lnF"][1, 2, 0] = np.nan  # e.g. O3 = 0 at that point: ln O3 undefined
    r = fd_relstd(J, th, NoiseSpec())
    assert np.isnan(r["features"][1]).all()
    np.testing.assert_allclose(r["features"][[0, 2, 3]], ref["features"][[0, 2, 3]])
    np.testing.assert_allclose(r["image"], ref["image"])  # other sets untouched
