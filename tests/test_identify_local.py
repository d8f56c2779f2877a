"""Local identifiability (identify.local): Fisher / Cramér–Rao on SYNTHETIC Jacobians (no solves)."""

import numpy as np

from identify.local import NoiseSpec, crb_relstd, fisher, from_param, grid, to_param


def _J(n=4, p=30, seed=0):
    rng = np.random.default_rng(seed)
    img0 = np.abs(rng.normal(size=(n, p))) + 1.0
    return {"image": rng.normal(size=(n, p, 3)), "image0": img0,
            "lnF": rng.normal(size=(n, 3, 3)), "dF": rng.normal(size=(n, 3)) * 50.0}


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
    assert np.allclose(r2, 2 * r1)                      # CRB std is linear in the noise std
    C = np.linalg.inv(J["lnF"][0].T @ J["lnF"][0] / 0.01 ** 2)
    assert np.isclose(r1[0, 2], np.sqrt(C[2, 2]))       # ln E: relative std of E
    assert np.isclose(r1[0, 0], np.sqrt(C[0, 0]) / 5.0)


def test_more_measurements_never_worsen_the_bound():
    J = _J()
    F = fisher(J, NoiseSpec())
    th = np.tile([5.0, 6.0, 30.0], (4, 1))
    ri, rf, r2 = (crb_relstd(F[k], th) for k in ("image", "image+force", "two-depths"))
    assert np.all(rf <= ri + 1e-12)
    assert np.allclose(r2, ri / np.sqrt(2))            # linear model: a 2nd depth = noise averaging only


def test_grid_respects_depth_range():
    from solver.params import depth_range

    T, (ds, us, Es) = grid(nd=3, nu=2, nE=2)
    assert T.shape == (12, 3)
    for d, h, _ in T:
        lo, hi = depth_range(d, 20.0)
        assert lo - 1e-9 <= h <= hi + 1e-9
