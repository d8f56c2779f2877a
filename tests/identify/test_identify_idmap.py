"""Identifiability map (elastimap.identify.idmap) and its use by inference; SYNTHETIC maps and models."""

from __future__ import annotations

import numpy as np
import pytest

from elastimap.errors import UserError
from elastimap.identify.idmap import DEFAULT_MAP, IdentifiabilityMap


def _map() -> IdentifiabilityMap:
    """SYNTHETIC map: d, h always 2 %; E 5 % below 50 kPa, rising to 80 % at 200 kPa (log-linear)."""
    d, u, E = np.linspace(2, 15, 6), np.linspace(0.1, 0.9, 3), np.geomspace(10, 200, 7)
    r = np.empty((6, 3, 7, 3))
    r[..., 0] = r[..., 1] = 0.02
    rE = np.where(E <= 50, 0.05, 0.05 * np.exp(np.log(16) * np.log(E / 50) / np.log(4)))
    r[..., 2] = rE[None, None, :]
    return IdentifiabilityMap(d, u, E, {"features": r, "image": r / 2}, 20.0, "SYNTHETIC")


def _theta(d, u, E):
    from elastimap.solver.params import depth_range

    lo, hi = depth_range(d, 20.0)
    return np.array([[d, lo + u * (hi - lo), E]])


def test_bound_interpolates_the_grid_and_flags_outside():
    m = _map()
    r, inside = m.bound(_theta(m.d[2], m.u[1], m.E[3]), "features")
    assert inside.all()
    np.testing.assert_allclose(r[0], m.relstd["features"][2, 1, 3], rtol=1e-10)
    # halfway in ln E between two nodes: the geometric mean of the node values (ln r is interpolated)
    Em = np.sqrt(m.E[5] * m.E[6])
    r, _ = m.bound(_theta(5.0, 0.5, Em), "features")
    assert r[0, 2] == pytest.approx(np.sqrt(m.relstd["features"][0, 0, 5, 2] * m.relstd["features"][0, 0, 6, 2]))
    r, inside = m.bound(np.array([[5.0, 6.0, 400.0]]), "features")
    assert not inside[0] and r[0, 2] == pytest.approx(0.8)  # evaluated at the box edge
    with pytest.raises(UserError, match="no set"):
        m.bound(_theta(5, 0.5, 30), "two-depths")


def test_assess_flags_non_identifiable_outputs_with_wide_intervals():
    m = _map()
    est = np.vstack([_theta(8, 0.5, 20.0), _theta(8, 0.5, 150.0)])
    tr = np.array([[2.0, 3.0, 10.0], [15.0, 17.0, 200.0]])
    a = m.assess(est, "features", 0.10, target_range=tr)
    assert a.flags[0] == [] and a.flags[1] == ["non_identifiable:E"]
    assert a.identifiable[0].all() and not a.identifiable[1, 2]
    # identifiable: the bound's log-normal 95 % interval; non-identifiable E: wide, clipped to training
    np.testing.assert_allclose(a.lo[0], est[0] * np.exp(-2 * a.r[0]))
    np.testing.assert_allclose(a.hi[0], est[0] * np.exp(2 * a.r[0]))
    assert a.r[1, 2] > 0.4 and a.hi[1, 2] == 200.0 and a.lo[1, 2] < 150.0 / 2
    assert np.all(a.lo <= est) and np.all(est <= a.hi)
    # the ensemble's 10-90 % range widens the interval, never narrows it
    b = m.assess(est, "features", 0.10, p10=est * 0.5, p90=est * 1.01, target_range=tr)
    assert np.all(b.lo <= np.maximum(est * 0.5, tr[0]) + 1e-12) and np.all(b.hi >= a.hi - 1e-12)
    # the image set (half the bound here) makes E at 150 kPa ... still not identifiable, 80 kPa yes
    c = m.assess(np.vstack([_theta(8, 0.5, 150.0), _theta(8, 0.5, 60.0)]), "image", 0.10)
    assert c.flags == [["non_identifiable:E"], []]


def test_map_roundtrip_and_bad_files(tmp_path):
    m = _map()
    m.save(tmp_path / "m.npz")
    back = IdentifiabilityMap.load(tmp_path / "m.npz")
    assert set(back.relstd) == {"features", "image"} and back.source == "SYNTHETIC"
    np.testing.assert_allclose(back.relstd["image"], m.relstd["image"])
    with pytest.raises(UserError, match="no such map"):
        IdentifiabilityMap.load(tmp_path / "nope.npz")
    np.savez(tmp_path / "bad.npz", x=np.ones(3))
    with pytest.raises(UserError, match="not an identifiability map"):
        IdentifiabilityMap.load(tmp_path / "bad.npz")


def _camera_map(ny: int = 12) -> IdentifiabilityMap:
    """SYNTHETIC map with a camera set (4 % everywhere but E, 30 %) and its noise map (ny x ny)."""
    m = _map()
    r = np.full(m.relstd["image"].shape, 0.04)
    r[..., 2] = 0.30
    m.relstd["camera"] = r
    m.camera_sigma, m.camera_frames = np.linspace(1e-4, 3e-4, ny * ny).reshape(ny, ny), 30
    return m


def test_camera_bound_of_orthogonal_derivatives_is_the_noise_over_their_norm():
    """Derivatives on disjoint pixels: F is diagonal, so sqrt(C_kk) = 1 / ||J_k / sigma|| (by hand)."""
    from elastimap.workflows.studies.cameramap import camera_bound

    sigma = np.full((4, 4), 2e-4)
    J = np.zeros((3, 4, 4))
    J[0, 0, :] = 1e-3  # per mm of d
    J[1, 1, :2] = 5e-3  # per mm of h
    J[2, 2:, :] = 2e-5  # per kPa of E
    theta = (8.0, 7.0, 50.0)
    r = camera_bound(J, sigma, theta)
    want = [
        2e-4 / (1e-3 * np.sqrt(4)) / 8.0,
        2e-4 / (5e-3 * np.sqrt(2)) / 7.0,
        2e-4 / (50.0 * 2e-5 * np.sqrt(8)),  # ln E: dI/dlnE = E dI/dE
    ]
    np.testing.assert_allclose(r, want, rtol=1e-10)
    # twice the noise, twice the bound (F ~ 1/sigma^2)
    np.testing.assert_allclose(camera_bound(J, 2 * sigma, theta), 2 * np.array(want), rtol=1e-10)


def test_camera_set_scales_with_the_measured_noise_and_round_trips(tmp_path):
    m = _camera_map()
    m.save(tmp_path / "m.npz")
    back = IdentifiabilityMap.load(tmp_path / "m.npz")
    assert {"features", "image", "camera"} <= set(back.relstd) and back.camera_frames == 30
    np.testing.assert_allclose(back.camera_sigma, m.camera_sigma)
    assert back.camera_scale(m.camera_sigma) == pytest.approx(1.0)
    # the nominal camera with 120 frames instead of 30: half the noise, half the bound
    assert back.camera_scale(m.camera_sigma * np.sqrt(30 / 120)) == pytest.approx(0.5)
    th = _theta(8, 0.5, 30.0)
    np.testing.assert_allclose(back.bound(th, "camera", 2.0)[0], 2 * back.bound(th, "camera")[0])
    a = back.assess(th, "camera", 0.10, scale=3.0)  # d, h 12 %: not identifiable any more
    assert a.flags[0] == ["non_identifiable:d", "non_identifiable:h", "non_identifiable:E"]
    # frames: per output the larger of camera x scale and the 1 % image set
    ri, rc = back.bound(th, "image")[0], back.bound(th, "camera")[0]
    np.testing.assert_allclose(back.bound(th, "frames", 0.1)[0], np.maximum(0.1 * rc, ri))
    np.testing.assert_allclose(back.bound(th, "frames", 2.0)[0], np.maximum(2.0 * rc, ri))
    with pytest.raises(UserError, match="pixels"):
        back.camera_scale(np.ones((5, 5)))
    with pytest.raises(UserError, match="scale"):
        back.bound(th, "camera", 0.0)
    m.camera_sigma = None
    m.save(tmp_path / "nosigma.npz")
    with pytest.raises(UserError, match="camera_sigma"):
        IdentifiabilityMap.load(tmp_path / "nosigma.npz")
    with pytest.raises(UserError, match="no camera set"):
        _map().camera_scale(np.ones((12, 12)))


def test_shipped_default_map_says_what_the_study_measured():
    """The shipped map (crbmap on the default 512-sample sweep, scaled with real FD on the morphed map):
    E is far better determined by the whole image than by three features; h is identifiable from the
    image over almost the whole box, d over most of it, all but the smallest inclusions
    (docs/identifiability.md)."""
    m = IdentifiabilityMap.load(DEFAULT_MAP)
    assert {"features", "image"} <= set(m.relstd)
    th = _theta(8.0, 0.5, 30.0)
    rf, _ = m.bound(th, "features")
    ri, _ = m.bound(th, "image")
    assert ri[0, 2] < rf[0, 2] / 3
    ok_d, ok_h = (m.relstd["image"][..., j] <= 0.10 for j in (0, 1))
    assert ok_h.mean() > 0.95 and ok_d.mean() > 0.85
    assert ok_d[m.d >= 8].mean() > 0.95 and ok_d[m.d <= 5].mean() < ok_d[m.d >= 8].mean()
    assert (m.relstd["features"][..., 2] <= 0.10).mean() < (m.relstd["image"][..., 2] <= 0.10).mean()
    assert "sweep" in m.source and "real-FD" in m.source
    # the camera set (cameramap, 2026-11-25): the nominal camera at 30 frames sees E of large shallow
    # inclusions far better than 1 % of the peak, and d of small deep ones far worse
    assert m.camera_frames == 30 and m.camera_sigma.shape == (50, 50) and "cameramap" in m.source
    ok_cam = m.relstd["camera"] <= 0.10
    assert ok_cam[..., 2].mean() > 0.4 > (m.relstd["image"][..., 2] <= 0.10).mean()
    assert ok_cam[m.d <= 3, -1, :, 0].mean() < 0.2 < ok_d[m.d <= 3, -1, :].mean()
    r_big, _ = m.bound(_theta(14.0, 0.1, 100.0), "camera")
    r_deep, _ = m.bound(_theta(2.5, 0.9, 30.0), "camera")
    assert r_big[0, 2] < 0.05 and r_deep[0, 0] > 0.10


# ----------------------------------------------------------------------------- inference
class _Ens:
    """Fixed-prediction ensemble (three members) with a training range."""

    def __init__(self, mean):
        self.mean = np.asarray(mean, float)
        self.feature_range = np.array([[-1e9] * 3, [1e9] * 3])
        self.target_range = np.array([[2.0, 3.0, 10.0], [15.0, 17.0, 200.0]])

    def predict(self, X):
        X = np.atleast_2d(X)
        return np.stack([np.tile(self.mean * f, (len(X), 1)) for f in (0.98, 1.0, 1.02)])

    input_kind = "features"  # an elastimap.training.model.InverseModel

    def outside_training(self, X):
        return [[] for _ in np.atleast_2d(X)]


class _Cal:
    synthetic = True

    def apply(self, cam):
        return np.asarray(cam, float) * 2.0 + np.array([0.001, 0.0, 0.0])

    def outside(self, cam, margin=0.0):
        return np.zeros(np.shape(np.atleast_2d(cam)), bool)


def test_estimate_reports_non_identifiable_E_as_an_interval():
    from elastimap.camera.infer import estimate

    m = _map()
    e_hi = estimate([[0.1, 1.0, 5.0]], _Cal(), _Ens(_theta(8, 0.5, 150.0)[0]), identifiability=m)[0]
    assert "non_identifiable:E" in e_hi.flags and not e_hi.ok
    row = e_hi.to_dict()
    assert row["E_identifiable"] is False and row["d_identifiable"] is True
    assert row["E_lo"] < 150.0 / 2 and row["E_hi"] == 200.0
    e_lo = estimate([[0.1, 1.0, 5.0]], _Cal(), _Ens(_theta(8, 0.5, 20.0)[0]), identifiability=m)[0]
    assert e_lo.ok and e_lo.lo[2] <= 20.0 * 0.98 and e_lo.hi[2] >= 20.0 * 1.02
    # without a map: no interval, no identifiability flag (the old behaviour, explicitly asked for)
    e_none = estimate([[0.1, 1.0, 5.0]], _Cal(), _Ens(_theta(8, 0.5, 150.0)[0]), identifiability=None)[0]
    assert e_none.ok and e_none.lo is None


def test_image_model_inference_from_fem_images(tmp_path):
    from test_identify import _synthetic_data

    from elastimap.camera.infer import estimate, estimate_fem_images, load_model
    from elastimap.identify.image_model import fit_image_model
    from elastimap.training.experiment import TrainConfig

    data = _synthetic_data()
    model = fit_image_model(
        data, "scg", repeats=2, cfg=TrainConfig(hidden=((6, "tansig"),), epochs=20, progress=False), k=4
    )
    model.save(str(tmp_path / "img"))
    back = load_model(tmp_path / "img")
    assert back.shape == (12, 12) and back.pixel == 0.5
    ests = estimate_fem_images(data.images[:3].reshape(3, 12, 12), back, identifiability=_map())
    assert len(ests) == 3 and all(e.input == "image" for e in ests)
    np.testing.assert_allclose(np.array([e.mean for e in ests]), model.predict(data.images[:3]).mean(0))
    assert np.isfinite(ests[0].fem).all() and ests[0].fem[0] == pytest.approx(data.images[0].max())
    assert all(e.lo is not None and np.all(e.lo <= e.mean) for e in ests)
    assert all(e.crb_set == "image" for e in ests)
    # measured per-pixel noise (frames) and a map with a camera set: that set, scaled by the noise
    cm = _camera_map()
    (e,) = estimate_fem_images(
        data.images[:1].reshape(1, 12, 12), back, identifiability=cm, sigma=2 * cm.camera_sigma[None]
    )
    assert e.crb_set == "frames" and e.to_dict()["crb_set"] == "frames"
    want = np.maximum(2 * cm.bound(e.mean[None], "camera")[0][0], cm.bound(e.mean[None], "image")[0][0])
    np.testing.assert_allclose(e.crb, want)
    assert e.crb[2] == pytest.approx(0.6)  # E: the camera set (30 % x 2) is the larger
    (e,) = estimate_fem_images(data.images[:1].reshape(1, 12, 12), back, identifiability=cm)
    assert e.crb_set == "image"  # no measured noise: the 1 % set
    with pytest.raises(UserError, match="image model"):
        estimate([[0.1, 1.0, 5.0]], _Cal(), back)
    with pytest.raises(UserError, match="feature model"):
        estimate_fem_images(data.images[:1], _Ens([5, 6, 30]))


def test_cli_infer_fem_image_prints_non_identifiable_as_interval(tmp_path):
    import json
    import subprocess
    import sys

    from test_identify import _synthetic_data

    from elastimap.identify.image_model import fit_image_model
    from elastimap.training.experiment import TrainConfig

    data = _synthetic_data()
    fit_image_model(
        data, "scg", repeats=2, cfg=TrainConfig(hidden=((6, "tansig"),), epochs=10, progress=False), k=4
    ).save(str(tmp_path / "img"))
    m = _map()
    m.relstd["image"][..., 2] = 0.5  # SYNTHETIC: E never identifiable from this "image"
    m.save(tmp_path / "map.npz")
    np.save(tmp_path / "img.npy", data.images[:2].reshape(2, 12, 12))
    base = [
        sys.executable,
        "-m",
        "elastimap.camera.cli",
        "infer",
        "--model",
        str(tmp_path / "img"),
        "--fem-image",
        str(tmp_path / "img.npy"),
        "--identifiability",
        str(tmp_path / "map.npz"),
    ]
    r = subprocess.run(base, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    assert len(lines) == 2 and all("E: not identifiable here" in ln and "non_identifiable:E" in ln for ln in lines)
    r = subprocess.run(base + ["--json"], capture_output=True, text=True)
    rows = json.loads(r.stdout)
    assert rows[0]["input"] == "image" and rows[0]["E_identifiable"] is False
    r = subprocess.run(
        base[:6] + ["--fem-image", str(tmp_path / "nope.npy"), "--identifiability", "none"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and r.stderr.startswith("error: --fem-image")
    r = subprocess.run(base[:-2] + ["--identifiability", "none", "--crb-limit", "0"], capture_output=True, text=True)
    assert r.returncode == 2 and "--crb-limit" in r.stderr


def test_region_score_coverage_of_reported_intervals():
    from elastimap.workflows.studies.region_score import coverage

    m = _map()
    theta = np.vstack([_theta(8, 0.5, 20.0), _theta(8, 0.5, 150.0), _theta(10, 0.3, 15.0)])
    pred = np.stack([theta * 1.01, theta * 0.99])  # close to the truth: every interval covers it
    c = coverage(pred, theta, m, "features")
    assert c["E"]["n_flagged"] == 1 and c["E"]["cover_flagged"] == 100 and c["E"]["cover_rest"] == 100
    assert c["h"]["n_flagged"] == 0 and np.isnan(c["h"]["cover_flagged"])
    theta = np.vstack([theta, _theta(3, 0.5, 30.0), _theta(14, 0.5, 30.0)])
    far = np.stack([theta * 1.01, theta * 0.99])
    far[..., 0] *= 1.5  # d 50 % off with a 2 % bound: not covered, except where clipped to the range edge
    assert coverage(far, theta, m, "features")["d"]["cover_rest"] == 20


def test_mapcheck_compare_counts_dangerous_disagreements():
    from elastimap.workflows.studies.mapcheck import compare

    fd = np.array([[0.05, 0.02, 0.05], [0.05, 0.02, 0.50], [0.20, 0.02, 0.08]])
    mp = np.array([[0.10, 0.02, 0.04], [0.05, 0.04, 0.09], [0.40, 0.01, 0.20]])
    c = compare(mp, fd, 0.10)
    assert c["E"]["false_identifiable"] == 1  # row 1: map 9 %, FD 50 %
    assert c["E"]["fd_identifiable"] == 2 and c["E"]["agree"] == pytest.approx(100 / 3)
    assert c["d"]["conservative"] == 100 and c["d"]["median"] == pytest.approx(2.0)
    assert c["h"]["min"] == pytest.approx(0.5) and c["h"]["false_identifiable"] == 0


def test_crbmap_install_writes_the_map_inference_reads(tmp_path):
    """``crbmap --install`` path: the map file is checked, then replaces the destination atomically;
    a file that is not a map leaves the destination as it was."""
    from elastimap.workflows.studies.crbmap import check_install_target, install_map

    src, dest = tmp_path / "crb_grid.npz", tmp_path / "maps" / "default.npz"
    dest.parent.mkdir()
    _map().save(src)
    assert install_map(str(src), str(dest)) == str(dest)
    got = IdentifiabilityMap.load(dest)
    np.testing.assert_array_equal(got.relstd["image"], _map().relstd["image"])
    assert got.source == "SYNTHETIC"
    before = dest.read_bytes()
    bad = tmp_path / "bad.npz"
    np.savez(bad, x=np.zeros(3))
    with pytest.raises(UserError, match="not an identifiability map"):
        install_map(str(bad), str(dest))
    assert dest.read_bytes() == before and sorted(p.name for p in dest.parent.iterdir()) == ["default.npz"]
    with pytest.raises(UserError, match="--install"):
        check_install_target(str(tmp_path / "missing" / "default.npz"))
    assert check_install_target(None) == DEFAULT_MAP  # the shipped map's folder is writable in a checkout


def test_crbmap_surrogate_from_reuses_the_stored_raw_bounds(tmp_path):
    """``crbmap --surrogate-from``: the raw surrogate bounds of an earlier map file stand in for the GP
    fit (no sweep read): without FD scaling the new map IS those bounds, the surrogate at a point is
    their interpolation, and the file records where they came from.  SYNTHETIC bounds."""
    from elastimap.identify.bounds import grid
    from elastimap.workflows.studies.crbmap import SETS, compute, stored_surrogate

    T, (ds, us, Es) = grid()
    rng = np.random.default_rng(0)
    raw = {s: np.exp(rng.normal(np.log(0.05), 0.5, T.shape)) for s in SETS}
    old = tmp_path / "old.npz"
    np.savez(
        old,
        theta=T,
        d=ds,
        u=us,
        E=Es,
        thickness=20.0,
        source="GP surrogate (k=16) of SYNTHETIC (9 rows), scaled per output by max(1, ...); noise ...",
        **{s: 2 * raw[s] for s in SETS},
        **{f"{s}_surrogate": raw[s] for s in SETS},
    )
    smap, origin = stored_surrogate(str(old))
    assert origin == "GP surrogate (k=16) of SYNTHETIC (9 rows)"
    r, _ = smap.bound(T[:5], "image")
    np.testing.assert_allclose(r, raw["image"][:5], rtol=1e-12)

    R = compute("no-such-sweep", str(tmp_path / "out"), fd_scale=False, surrogate_from=str(old), command="CMD")
    for s in SETS:
        np.testing.assert_allclose(R[s], raw[s], rtol=1e-12)
    new = IdentifiabilityMap.load(tmp_path / "out" / "crb_grid.npz")
    assert new.source.startswith("GP surrogate (k=16) of SYNTHETIC (9 rows) (raw bounds read from")
    assert new.source.endswith("CMD")
    z = np.load(tmp_path / "out" / "crb_grid.npz")
    assert str(z["surrogate_source"]).startswith("GP surrogate (k=16) of SYNTHETIC")
    # a map made this way can feed the next one: its origin is kept as it was
    assert stored_surrogate(str(tmp_path / "out" / "crb_grid.npz"))[1] == str(z["surrogate_source"])

    bad = tmp_path / "nosur.npz"
    _map().save(bad)
    with pytest.raises(UserError, match="--surrogate-from"):
        stored_surrogate(str(bad))
    with pytest.raises(UserError, match="--surrogate-from"):
        stored_surrogate(str(tmp_path / "missing.npz"))


def test_cameramap_install_adds_the_camera_set_and_keeps_the_others(tmp_path):
    """``cameramap install`` on SYNTHETIC column files: every column is needed; the other sets stay."""
    import shutil

    from click.testing import CliRunner

    from elastimap.identify.bounds import grid
    from elastimap.workflows.studies.cameramap import main

    T, (ds, us, Es) = grid()
    cols = T.reshape(len(ds) * len(us), len(Es), 3)
    out = tmp_path / "cm"
    out.mkdir()
    for c in range(cols.shape[0] - 1):
        r = np.full((len(Es), 3), 0.03 + 0.001 * c)
        np.savez(
            out / f"col-{c:03d}.npz", col=c, r=r, theta=cols[c], sigma=np.full((50, 50), 5e-5), mesh="tiny", frames=30
        )
    dest = tmp_path / "map.npz"
    shutil.copyfile(DEFAULT_MAP, dest)
    before = IdentifiabilityMap.load(dest)
    with np.load(dest) as z:
        entries = {k: z[k] for k in z.files if k != "source" and not k.startswith("camera")}
    run = CliRunner().invoke(main, ["install", "--out", str(out), "--map", str(dest)], standalone_mode=False)
    assert isinstance(run.exception, UserError) and "1 of 70 grid columns missing" in run.exception.message
    c = cols.shape[0] - 1
    np.savez(
        out / f"col-{c:03d}.npz",
        col=c,
        r=np.full((len(Es), 3), 0.5),
        theta=cols[c],
        sigma=np.full((50, 50), 5e-5),
        mesh="tiny",
        frames=30,
    )
    run = CliRunner().invoke(main, ["install", "--out", str(out), "--map", str(dest)])
    assert run.exit_code == 0, run.output
    m = IdentifiabilityMap.load(dest)
    np.testing.assert_allclose(m.relstd["image"], before.relstd["image"])
    np.testing.assert_allclose(m.relstd["camera"][0, 0, :, 0], 0.03)
    np.testing.assert_allclose(m.relstd["camera"][-1, -1, :, 2], 0.5)
    assert m.camera_frames == 30 and np.allclose(m.camera_sigma, 5e-5) and m.source.count("camera set:") == 1
    # every other entry of the file stays, also those IdentifiabilityMap does not read (crbmap's raw
    # surrogate bounds and FD scales, which crbmap --surrogate-from needs)
    with np.load(dest) as z:
        for k, v in entries.items():
            np.testing.assert_array_equal(z[k], v, err_msg=k)
    assert any(k.endswith("_surrogate") for k in entries)
