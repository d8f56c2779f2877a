"""The model-form study (:mod:`elastimap.workflows.studies.modelform`) on a SYNTHETIC analytic world:
no solves, the scoring itself."""

from __future__ import annotations

import numpy as np

from elastimap.workflows.studies import modelform as mf


def bump(d, h, E, n=50):
    """SYNTHETIC forward image (mm): a bump whose height grows with d and E (E alone: a pure height change,
    as a stiff inclusion's), whose width grows with d and h and whose flank (the exponent) with both."""
    Y, X = np.meshgrid(*(2 * [(np.arange(n) - (n - 1) / 2) * mf.PIXEL]), indexing="ij")
    amp = 5e-3 * d * E / (E + 20.0)
    w = 0.4 * d + 0.3 * h
    p = 1.0 + 0.1 * h + 0.05 * d
    return amp * (1 + (X * X + Y * Y) / (2 * w * w)) ** (-p)


def jac(th, eps=1e-4):
    return np.array([(bump(*(th + eps * e)) - bump(*(th - eps * e))) / (2 * eps) for e in np.eye(3)])


def test_score_set_learns_from_nine_and_the_discrepancy_mends_the_coverage():
    """A world 2 ± 1 % higher than the model: today's budget (noise alone) misses, the learnt term covers."""
    rng = np.random.default_rng(0)
    Y, X = np.meshgrid(*(2 * [(np.arange(50) - 24.5) * mf.PIXEL]), indexing="ij")
    ref = 0.09 + 0.4 * (X * X + Y * Y) / 12.5**2  # a background press, mm
    world, model = [], {}
    for i in range(12):
        th = np.array([6.0 + 0.5 * i, 8.0, 40.0 + 5 * i])
        world.append(
            {
                "phantom": f"P{i + 1:02d}",
                "theta": th,
                "diff": bump(*th) * (1.02 + 0.01 * rng.standard_normal()),
                "ref": ref,
                "effect": "",
            }
        )
        model[mf.key(th)] = (bump(*th), jac(th))
    rows, disc = mf.score_set(world, model, None, 30, 3, 0, ("amplitude", "width"), 2.0, (0.0,))
    assert len(rows) == 12 and sum(r["calibration"] for r in rows) == 9
    assert 0.005 < disc.mean[0] < 0.035 and disc.beyond() == []
    closed, open_ = mf.summary(rows, "closed"), mf.summary(rows, "open")
    assert min(open_["coverage_pct"]) >= 85 and closed["coverage_pct"][2] < 50
    assert open_["n_identifiable"][2] == 0 < closed["n_identifiable"][2]  # E: a pure height change, confounded
    assert 0.5 < open_["chi2_px_median"] < 2


def test_cli_refuses_without_a_world():
    """One error line naming the flag, exit 2, before any work."""
    import subprocess
    import sys

    r = subprocess.run(
        [sys.executable, "-m", "elastimap.workflows.studies.modelform"], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 2 and r.stderr.strip().startswith("error: --world:") and "Traceback" not in r.stderr
