"""Camera frames -> FEM-equivalent difference image, on the REAL tiny-mesh FEM (not the toy).

The lesion is solved once on the tiny mesh; its frames come from the nominal SYNTHETIC camera
with noise.  The inverse uses the reference press of *other* solves (the mean of three
phantoms', as the calibration stores the nine phantoms' mean), so the lesion's own remeshed
reference is not handed to it.  Tolerances are in units of the per-pixel standard error the
frames themselves give.  Measured (seed 1): z rms 1.03 with the lesion's own reference, 1.16
with the three phantoms' (1.33 over the central 15 x 15 mm): on the tiny mesh the reference
press itself moves by ~0.001-0.003 mm at the centre from one mesh to the next, and the flat
field turns that into about 1 % of the difference image.

Open-world: frames from a camera with other LED powers, vignetting, exposure and noise than
the calibration's are inverted with the calibration's (nominal) model; the flat field from the
background frames absorbs the first three and the scatter measures the fourth.
"""

import numpy as np
import pytest

from elastimap.camera.deflection import difference_image, fit_scale, sampling_matrix
from elastimap.camera.optics import SensorModel, background_deflection, render_pair

# its module fixture is costly: under pytest-xdist (make test) this module runs on one worker
pytestmark = pytest.mark.xdist_group("test_camera_frames_fem")

pytest.importorskip("elastimap.solver.api", reason="the DOLFINx solver is not available")

TRUTH = (8.0, 7.0, 50.0)


@pytest.fixture(scope="module")
def solves(tmp_path_factory):
    from elastimap.workflows.solves import cached_solve

    cache = str(tmp_path_factory.mktemp("solves"))
    lesion = cached_solve(*TRUTH, mesh="tiny", cache=cache)
    phantoms = [
        cached_solve(*p, mesh="tiny", cache=cache) for p in ((5.0, 8.0, 80.0), (12.0, 8.0, 80.0), (8.0, 9.0, 80.0))
    ]
    ref = np.mean([background_deflection(o["image_raw"], o["image"]) for o in phantoms], axis=0)
    return {"lesion": lesion, "ref": ref, "phantom": phantoms[1], "cache": cache}


def _recover(solves, sensor, frames=30, seed=1):
    r = solves["lesion"]
    F, B = render_pair(sensor, r["image_raw"], r["image"], 0.5, frames, np.random.default_rng(seed))
    return difference_image(F, B, SensorModel(), solves["ref"], 0.5), r["image"]


def test_sampling_matrix_is_the_cameras_resampling():
    s = SensorModel()
    img = np.random.default_rng(0).random((50, 50))
    R = sampling_matrix(s.window[2], s.pixel_mm, 50, 0.5)
    r0, c0, n = s.window
    np.testing.assert_allclose(R @ img @ R.T, s.deformation_on_frame(img, 0.5)[r0 : r0 + n, c0 : c0 + n], atol=1e-12)


def test_frames_give_the_fem_difference_image_within_their_noise(solves):
    di, fem = _recover(solves, SensorModel(seed=3))
    z = (di.image - fem) / di.sigma
    assert di.image.shape == fem.shape == (50, 50)
    assert np.sqrt(np.mean(z**2)) < 1.5, np.sqrt(np.mean(z**2))  # measured 1.16
    assert np.mean(np.abs(z) > 5) < 0.002  # no structured misfit
    assert di.peak == pytest.approx(fem.max(), rel=0.02)  # measured +0.9 %
    assert np.linalg.norm(di.image - fem) / np.linalg.norm(fem) < 0.05


def test_noise_comes_from_the_frames_scatter(solves):
    a, fem = _recover(solves, SensorModel(seed=4))
    b, _ = _recover(solves, SensorModel(seed=4, noise_scale=3.0))
    ratio = np.median(b.sigma / a.sigma)
    assert ratio == pytest.approx(3.0, rel=0.15), ratio
    z = (b.image - fem) / b.sigma
    assert np.sqrt(np.mean(z**2)) < 1.3  # reference jitter now below the noise


def test_open_world_sensor_differs_from_the_calibrated_one(solves):
    """LED powers, vignetting and noise of the session differ from the calibration's nominal
    sensor: still the FEM image within the noise.  (The response *shape* -- w_sat, stray light,
    dark offset -- must be the calibrated one; see the next test and docs/camera.md.)"""
    other = SensorModel(seed=7, led_power=(1.3, 0.7, 1.0, 1.2), vignetting=0.3, noise_scale=1.5)
    di, fem = _recover(solves, other)
    z = (di.image - fem) / di.sigma
    assert np.sqrt(np.mean(z**2)) < 1.5, np.sqrt(np.mean(z**2))
    assert di.peak == pytest.approx(fem.max(), rel=0.02)


def test_response_shape_error_is_a_scale_the_phantoms_fit(solves):
    """A camera whose response saturates later (w_sat 0.7 mm, calibrated 0.5) gives images off by a
    nearly uniform factor near the lesion; the least-squares scale of a phantom (another inclusion)
    reduces it.  Noise-free frames, so only the systematic error is compared.  Measured: 3.2 % ->
    2.0 % relative rms (the rest: the error's non-uniform part and the reference's mesh jitter)."""
    other = SensorModel(w_sat=0.7, noise_scale=0.0)
    ph = solves["phantom"]
    F, B = render_pair(other, ph["image_raw"], ph["image"], 0.5, 2)
    k, _ = fit_scale([difference_image(F, B, SensorModel(), solves["ref"], 0.5).image], [ph["image"]])
    raw, fem = _recover(solves, other, frames=2)
    err_raw = np.linalg.norm(raw.image - fem) / np.linalg.norm(fem)
    err_cal = np.linalg.norm(k * raw.image - fem) / np.linalg.norm(fem)
    assert err_raw > 0.02 and err_cal < 0.75 * err_raw, (err_raw, err_cal, k)


@pytest.fixture(scope="module")
def refined(solves):
    """frames -> difference image + per-pixel noise -> the library's fit (morphed tiny map, model
    error against the coarse level), from a start 10 % off in every parameter; and the same fit of
    the noise-free FEM image itself (the frames' σ).  The lesion was made by the remeshing solver,
    not the fit's map."""
    pytest.importorskip("elastimap.solver.morph")
    from elastimap.camera.infer import Estimate, refine_estimates

    di, fem = _recover(solves, SensorModel(seed=9))
    start = np.array(TRUTH) * np.array([1.1, 0.9, 1.1])

    def est(img, sigma):
        return Estimate(
            "1",
            np.full(3, np.nan),
            np.full(3, np.nan),
            start.copy(),
            np.zeros(3),
            start,
            start,
            1,
            [],
            input="frames",
            image=img.ravel(),
            sigma=sigma.ravel(),
        )

    r, r_fem = refine_estimates([est(di.image, di.sigma), est(fem, di.sigma)], None, mesh="tiny")
    print("refined from frames", r.mean, r.lo, r.hi, "from the FEM image", r_fem.mean)
    return r, r_fem


@pytest.mark.slow
def test_refine_from_frames_holds_the_truth_and_moves_by_the_noise_only(refined):
    """The camera --refine path on the real tiny-mesh FEM: the 95 % intervals hold the truth, and
    the frames' noise moves the estimate from the noise-free image's fit by no more than 2.5 of
    the fit's own standard deviations (d, h; ln E) -- the camera chain adds noise, not bias.
    Measured 2026-11-26 (contrast coordinate): frames 8.65 [7.31, 9.99] / 6.87 [6.35, 7.40] / 24.5
    [13.7, 128], FEM image 8.16 / 6.95 / 41.5, truth 8 / 7 / 50."""
    r, r_fem = refined
    assert r.input == "frames+fem_refined"
    assert np.all(r.lo <= TRUTH) and np.all(np.array(TRUTH) <= r.hi), r.to_dict()
    sd = np.array([r.sd[0], r.sd[1], r.crb[2]])  # mm, mm, ln E
    moved = np.abs(np.array([r.d - r_fem.d, r.h - r_fem.h, np.log(r.E / r_fem.E)]))
    assert np.all(moved <= 2.5 * sd), (moved, sd)


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="measured 2026-11-26 (the contrast coordinate): the intervals now hold the truth (frames 8.65 "
    "[7.31, 9.99] / 6.87 [6.35, 7.40] / 24.5 [13.7, 128]) but d from frames is 8 % off and 6 % from the fit of "
    "the noise-free FEM image (8.16 / 6.95 / 41.5; truth 8 / 7 / 50): on the tiny map the frames' noise moves "
    "the estimate along the flat d-E valley by about one of its standard deviations (d sd 0.68 mm)",
)
def test_refine_from_frames_on_the_tiny_mesh(refined):
    """The accuracy asked of the benchmark (docs/camera.md), on the tiny mesh: d and h within 5 %,
    within 3 % of the noise-free image's fit.  Not met on the tiny map (strict xfail with the
    measured numbers); the benchmark on `coarse` corrected by `fine` is docs/camera.md 4f-4g."""
    r, r_fem = refined
    np.testing.assert_allclose(r.mean[:2], r_fem.mean[:2], rtol=0.03, err_msg=f"{r.mean} vs {r_fem.mean}")
    d, h, E = TRUTH
    assert r.d == pytest.approx(d, rel=0.05) and r.h == pytest.approx(h, rel=0.05), r.to_dict()
