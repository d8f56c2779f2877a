"""The fit's calibrated 95 % intervals (elastimap.identify.intervals): the conformal quantile against
numpy's own, the classes, the in-sample guarantee and held-out coverage on SYNTHETIC scores, and the
calibrated interval of fit_image / refine_estimates."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from elastimap.errors import UserError
from elastimap.identify.intervals import (
    CLASS_EDGES,
    NEAR_BASE_MM,
    SCALES,
    STRATA,
    Z95,
    calibrate,
    class_of,
    conformal_quantile,
    near_base,
    scales_for,
)
from elastimap.solver.params import THICKNESS, depth_range


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0, 50, allow_nan=False), min_size=19, max_size=300), st.sampled_from([0.8, 0.9, 0.95]))
@example([0.0] * 29 + [1.0] * 6, 0.8)  # found by hypothesis: 35 · (29 / 35) rounds above 29
def test_conformal_quantile_is_numpys_inverted_cdf_at_the_finite_sample_level(scores, level):
    """The k = ⌈(n+1) level⌉-th smallest score equals numpy's inverted-CDF quantile (an independent
    implementation) inside the k-th step of the empirical CDF, at (k − ½) / n -- at k / n itself
    n·p can round up past k (n 35, k 29 gave the 30th) -- and at least ``level`` of the scores lie
    at or below it."""
    s = np.array(scores)
    n = s.size
    k = math.ceil((n + 1) * level)
    q = conformal_quantile(s, level)
    if k > n:
        assert math.isnan(q)
        return
    assert q == np.quantile(s, (k - 0.5) / n, method="inverted_cdf")
    assert np.mean(s <= q) >= level


def test_conformal_quantile_refuses_bad_scores_and_levels():
    with pytest.raises(UserError, match="scores"):
        conformal_quantile([1.0, -0.5])
    with pytest.raises(UserError, match="level"):
        conformal_quantile([1.0, 2.0], level=1.0)
    assert math.isnan(conformal_quantile(np.arange(10.0)))  # 19 scores at least for 95 %


def test_classes_are_right_closed_half_decades_and_scales_follow_them_and_the_stratum():
    assert CLASS_EDGES == (0.03, 0.10, 0.30)
    np.testing.assert_array_equal(class_of([0.01, 0.03, 0.031, 0.1, 0.2, 0.3, 5.0]), [0, 0, 1, 1, 2, 2, 3])
    table = {
        "d": ((1.0, 2.0, 3.0, 4.0), (11.0, 12.0, 13.0, 14.0)),
        "h": ((5.0, 6.0, 7.0, 8.0), (15.0, 16.0, 17.0, 18.0)),
        "E": ((0.5, 0.6, 0.7, 0.8), (0.1, 0.2, 0.3, 0.4)),
    }
    far, near = (6.0, 5.0, 60.0), (12.0, THICKNESS - 6.0 - 1.0, 60.0)  # bottoms 11 mm and 1 mm above the base
    np.testing.assert_array_equal(scales_for([0.02, 0.05, 0.5], far, table), [1.0, 6.0, 0.8])
    np.testing.assert_array_equal(scales_for([0.02, 0.05, 0.5], near, table), [11.0, 16.0, 0.4])
    np.testing.assert_array_equal(scales_for([np.nan, 0.05, np.inf], far, table), [1.0, 6.0, 1.0])  # not finite: 1
    assert STRATA == ("far", "near")
    assert set(SCALES) == {"d", "h", "E"}
    assert all(len(v) == 2 and all(len(row) == 4 and min(row) > 0 for row in v) for v in SCALES.values())
    with pytest.raises(UserError, match="relstd"):
        scales_for([0.1, 0.2], far)


@settings(max_examples=80, deadline=None)
@given(st.floats(2.0, 15.0), st.floats(0.0, 1.0), st.floats(10.0, 200.0))
def test_near_base_is_the_bottom_within_near_base_mm_of_the_base(d, t, E):
    """Over the design box: an estimate is near the base exactly when the gap under the inclusion,
    thickness − h − d/2 (at least the design's 2 mm floor), is under NEAR_BASE_MM; the deepest allowed
    inclusion of every size is near, the shallowest far."""
    lo, hi = depth_range(d)
    h = lo + t * (hi - lo)
    assert bool(near_base((d, h, E))) == (THICKNESS - h - d / 2 < NEAR_BASE_MM)
    assert near_base((d, hi, E)) and not near_base((d, lo, E))
    np.testing.assert_array_equal(near_base(np.array([[d, hi, E], [d, lo, E]])), [True, False])


def test_calibrated_scales_hold_fresh_draws_at_95_percent_per_class():
    """SYNTHETIC scores whose spread differs by class (a Gauss–Newton sd 3x too narrow in one class,
    2x too wide in another) and, in the first class, by stratum (5x too narrow near the base, on a
    fifth of the lesions): scales from one draw hold 95 % of a fresh, independent draw in each cell
    (within three binomial standard errors), where k = 1 holds 30 % (near) and 49 % (far) of the first
    class and ~100 % of the last, and pooling the strata would hold far fewer near the base; a cell
    with too few lesions takes its class's scale, a class with too few keeps 1 (2·Φ(1.96/5) − 1 = 0.30,
    2·Φ(1.96/3) − 1 = 0.49)."""
    rng = np.random.default_rng(11)

    def draw(n):
        rel = np.exp(rng.uniform(np.log(0.005), np.log(1.0), n))
        near = rng.uniform(size=n) < 0.2
        spread = np.choose(class_of(rel), [3.0, 1.0, 0.5, 0.5]) * np.where(near & (class_of(rel) == 0), 5 / 3, 1.0)
        return rel, near, np.abs(rng.standard_normal(n)) * spread  # |err| / sd ~ |N(0, spread²)|

    rel, near, s = draw(6000)
    k, n = calibrate(rel, s, near)
    assert k.shape == n.shape == (2, 4) and n.sum() == 6000 and (n >= 19).all()
    rel2, near2, s2 = draw(30000)
    cell = (near2.astype(int), class_of(rel2))
    held = s2 <= Z95 * k[cell]
    for i in range(2):
        for c in range(4):
            m = (near2 == bool(i)) & (class_of(rel2) == c)
            se = math.sqrt(0.95 * 0.05 / m.sum())
            assert abs(held[m].mean() - 0.95) < 3 * se + 0.01, (i, c, held[m].mean(), k)
    plain = s2 <= Z95
    assert plain[class_of(rel2) == 0].mean() < 0.6 and plain[class_of(rel2) == 3].mean() > 0.99
    k_pooled, _ = calibrate(rel, s)  # one stratum: the near cells of class 0 under-covered
    m = near2 & (class_of(rel2) == 0)
    assert (s2[m] <= Z95 * k_pooled[0, 0]).mean() < 0.85
    k_few, n_few = calibrate(rel[:60], s[:60], near[:60])
    whole, n_whole = calibrate(rel[:60], s[:60])
    for c in range(4):
        for i in range(2):
            if n_few[i, c] < 19:
                assert k_few[i, c] == (whole[0, c] if n_whole[0, c] >= 19 else 1.0)
    with pytest.raises(UserError, match="scores"):
        calibrate(rel[:5], s[:5], near[:4])


def test_fit_image_calibrated_interval_scales_the_gauss_newton_half_width():
    """SYNTHETIC image model (test_identify_fit's bump): ``intervals="calibrated"`` keeps the estimate and
    the Gauss–Newton interval (``lo_gauss``) and reports θ̂ ± 1.96 k sd with k of :func:`scales_for`
    (d and h exactly; E in the fit's coordinate, so its ends move the same way)."""
    from elastimap.identify.fit import fit_image

    truth = np.array([8.0, 7.0, 60.0])
    I = bump(truth)
    sig = 5e-3 * I.max()
    kw = {"e_scan": 0, "tangent": False}
    g = fit_image(I, sig, truth * [1.05, 1.0, 0.8], bump_map, **kw)
    c = fit_image(I, sig, truth * [1.05, 1.0, 0.8], bump_map, intervals="calibrated", **kw)
    np.testing.assert_array_equal(c.theta, g.theta)
    np.testing.assert_array_equal(c.lo_gauss, g.lo)
    np.testing.assert_array_equal(g.scale, np.ones(3))
    k = scales_for(c.relstd, c.theta)
    np.testing.assert_array_equal(c.scale, k)
    sd = c.sd
    for j in (0, 1):
        if c.lo[j] > 0 and g.lo[j] > 0:
            assert c.theta[j] - c.lo[j] == pytest.approx(k[j] * (g.theta[j] - g.lo[j]), rel=1e-9)
    assert (c.lo[2] < g.lo[2]) == (k[2] > 1) and (c.hi[2] > g.hi[2]) == (k[2] > 1)
    np.testing.assert_allclose(c.relstd_calibrated, c.relstd * k)
    assert np.all(sd > 0)
    with pytest.raises(UserError, match="intervals"):
        fit_image(I, sig, truth, bump_map, intervals="wide", **kw)


_Y, _X = np.mgrid[0:16, 0:16] * 0.75
_R2 = _X.ravel() ** 2 + _Y.ravel() ** 2


def bump(theta):
    """SYNTHETIC difference image (mm), tests/identify/test_identify_fit.py's: a bump whose width follows d and h, a
    depth-damped amplitude and a halo whose share falls as E rises."""
    d, h, E = theta
    amp = 1e-2 * d**2 / h
    w = 0.45 * d + 0.35 * h
    s = E / (E + 40.0)
    return amp * (s * np.exp(-_R2 / (2 * w**2)) - 0.3 * (1 - s) * np.exp(-_R2 / (8 * w**2)))


def bump_map(d, h, E):
    return bump((d, h, E))


def test_default_intervals_are_calibrated_only_for_the_calibrated_fit():
    from elastimap.identify.forward_maps import default_intervals
    from elastimap.identify.intervals import CALIBRATED_FOR

    assert default_intervals(*CALIBRATED_FOR) == "calibrated"
    assert default_intervals("coarse", None) == "gauss"
    assert default_intervals("tiny", None) == "gauss"
    assert default_intervals("coarse", "default") == "gauss"
    assert default_intervals(*CALIBRATED_FOR, geometry="remesh") == "gauss"  # calibrated on morphed maps


def test_fit_maps_share_one_bin_rule_and_say_which_intervals():
    """fit_maps (what fit_forward and infer --refine fit with): the fit's, the model error's and the
    correcting maps at their levels with the fit level's bin rule, and the default intervals."""
    from elastimap.identify.forward_maps import BELOW_LEVELS, fit_maps

    m = fit_maps("coarse", "fine")
    assert m.intervals == "calibrated" and m.forward_fine is not None
    assert {f.morphed.template.disc.mesh for f in (m.forward, m.forward_alt, m.forward_fine)} == {
        "coarse",
        "default",
        "fine",
    }
    assert m.forward.below and m.forward_alt.below and m.forward_fine.below
    t = fit_maps("tiny")
    assert "tiny" not in BELOW_LEVELS and not t.forward.below and not t.forward_alt.below
    assert t.forward_fine is None and t.intervals == "gauss"
    with pytest.raises(UserError, match="correct"):
        fit_maps("fine", "coarse")


def test_refine_estimates_reports_the_sd_its_interval_stands_for():
    """``refine_estimates(intervals="calibrated")`` on a SYNTHETIC map: the estimate's sd and crb are
    the Gauss–Newton ones times the scale, and non_identifiable is decided from them."""
    from elastimap.camera.infer import Estimate, refine_estimates

    truth = np.array([8.0, 7.0, 60.0])
    I = bump(truth)
    nan3 = np.full(3, np.nan)
    start = truth * [1.05, 1, 0.8]
    e = Estimate("1", nan3, nan3, start.copy(), nan3, start, start, 1, [], input="image")
    (r,) = refine_estimates([e], I[None], image_noise=0.01, forward=bump_map, intervals="calibrated")
    np.testing.assert_allclose(r.crb, r.fit.relstd * r.fit.scale)
    np.testing.assert_allclose(r.sd, r.fit.sd * r.fit.scale)
    for j, q in enumerate("dhE"):
        assert (f"non_identifiable:{q}" in r.flags) == (r.crb[j] > 0.10)
    np.testing.assert_array_equal(r.lo, r.fit.lo)


def test_shipped_scales_are_read_from_the_calibration_file_with_provenance():
    """The scales inference uses are data (identify/maps/intervals.json), not code: the file holds the
    numbers the calibration recorded in git at c1a9e14 (seeds 2027-2041, 1317 lesions) and says so."""
    from elastimap.identify.intervals import CALIBRATED_FOR, INTERVALS_FILE, load_scales

    cal = load_scales(INTERVALS_FILE)
    assert cal["scales"] == SCALES and cal["calibrated_for"] == CALIBRATED_FOR == ("coarse", "fine")
    assert SCALES["d"] == ((1.214, 1.076, 0.613, 0.293), (4.428, 0.304, 0.407, 0.271))
    assert SCALES["E"][1] == (1.559, 7.074, 3.538, 0.387)
    prov = cal["provenance"]
    assert prov["git_commit"] == "c1a9e14" and prov["lesions"] == 1317 and "2027-2041" in prov["seeds"]


def test_a_calibration_file_with_other_classes_is_refused(tmp_path):
    import json

    from elastimap.identify.intervals import INTERVALS_FILE, load_scales

    with open(INTERVALS_FILE) as fh:
        doc = json.load(fh)
    doc["class_edges"] = [0.05, 0.1, 0.3]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    with pytest.raises(UserError, match="other classes"):
        load_scales(bad)
    bad.write_text("{}")
    with pytest.raises(UserError, match="not an interval calibration"):
        load_scales(bad)


def _benchmark_folder(root, seed: int, n: int, rng) -> str:
    """A SYNTHETIC frames-benchmark folder: ``n`` lesion records with a fit whose errors are Gaussian
    with twice the stated sd (so the scales come out near 2)."""
    import json
    import os

    from elastimap.identify.coords import FitCoords
    from elastimap.workflows.studies.interval_calibration import FITS

    X = FitCoords()
    folder = os.path.join(root, f"fb{seed}")
    os.makedirs(os.path.join(folder, FITS))
    for i in range(n):
        d = rng.uniform(4.0, 12.0)
        lo, hi = depth_range(d)
        t = np.array([d, rng.uniform(lo, 0.5 * (lo + hi)), rng.uniform(30.0, 150.0)])
        rel = np.array([0.02, 0.02, 0.05])
        x = X.x(t)
        z = 2.0 * rng.standard_normal(3)  # errors twice the stated sd
        e = x[2] + z[2] * rel[2] / abs(X.dtheta(x)[2, 2])
        th = np.array([t[0] * (1 + z[0] * rel[0]), t[1] * (1 + z[1] * rel[1]), X.theta([x[0], x[1], e])[2]])
        rec = {
            "truth": t.tolist(),
            "network": {"flags": []},
            "fit_message": "ok",
            "fit": {"d": th[0], "h": th[1], "E": th[2]},
            "fit_relstd_gauss": rel.tolist(),
            "design": {"n": n, "seed": seed, "inside": None},
        }
        with open(os.path.join(folder, FITS, f"lesion-{i:03d}.json"), "w") as fh:
            json.dump(rec, fh)
    return folder


def test_interval_calibration_writes_the_file_inference_reads(tmp_path):
    """``interval_calibration FOLDERS --out FILE`` (SYNTHETIC records) writes a calibration file that
    load_scales reads, with its provenance: folders, seeds, lesions in all and per cell, method,
    commit and date; the scales are those the study prints (calibrate on the pooled scores)."""
    import json

    from click.testing import CliRunner

    from elastimap.identify.intervals import load_scales
    from elastimap.workflows.studies.interval_calibration import main, read_folder, scales_of

    rng = np.random.default_rng(11)
    folders = [_benchmark_folder(str(tmp_path), s, 30, rng) for s in (3001, 3002)]
    out = tmp_path / "intervals.json"
    r = CliRunner().invoke(main, [*folders, "--out", str(out)])
    assert r.exit_code == 0, r.output
    cal = load_scales(out)
    table, sizes = scales_of([read_folder(f) for f in folders])
    assert cal["scales"] == {q: tuple(tuple(row) for row in table[q]) for q in table}
    prov = json.loads(out.read_text())["provenance"]
    assert prov["folders"] == folders and prov["seeds"] == [3001, 3002] and prov["lesions"] == 60
    assert prov["lesions_per_cell"]["d"] == [list(row) for row in sizes["d"]]
    assert sum(map(sum, prov["lesions_per_cell"]["d"])) == 60
    assert prov["date"] and prov["git_commit"] and "conformal" in prov["method"]
    assert 1.2 < cal["scales"]["d"][0][0] < 3.5  # errors twice the stated sd: k near 2
    r = CliRunner().invoke(main, [*folders, "--out", str(out), "--install"])  # before any work
    assert isinstance(r.exception, UserError) and r.exception.param == "--out" and "not both" in str(r.exception)
