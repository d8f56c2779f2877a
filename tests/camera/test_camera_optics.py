"""Synthetic TIR camera model and frame I/O (fast, no solver)."""

import warnings

import numpy as np
import pytest

from elastimap.camera.frames import CameraWarning, read_frame, read_metadata, read_stack, write_frames
from elastimap.camera.optics import SensorModel, render_pair
from elastimap.errors import UserError
from elastimap.solver.synthetic import solve_dhe as toy_solve  # SYNTHETIC stand-in, not physics


@pytest.fixture(scope="module")
def toy():
    return toy_solve(8.0, 8.0, 80.0)


def test_geometry_default_and_full_resolution():
    m = SensorModel()
    assert m.shape == (104, 139)
    assert m.window == (2, 19, 100)
    assert m.pixel_mm == pytest.approx(0.25)
    full = SensorModel(binning=1)
    assert full.shape == (1042, 1392)
    assert full.pixel_mm == pytest.approx(0.025)
    assert full.e_per_dn == pytest.approx(9000 / 65535)


def test_response_monotone_saturating_and_illumination_nonuniform():
    m = SensorModel()
    w = np.linspace(0, 5, 200)
    s = m.scatter(w)
    assert np.all(np.diff(s) > 0) and s[0] == 0 and s[-1] < 1
    L = m.illumination()
    r0, c0, n = m.window
    win = L[r0 : r0 + n, c0 : c0 + n]
    assert win.mean() == pytest.approx(1.0)
    assert win.max() / win.min() > 1.2  # four side LEDs + vignetting: not flat


def test_render_seeded_dtype_and_noise_free(toy):
    m = SensorModel(seed=3)
    a = m.render(toy.image_raw, toy.pixel, 2)
    b = m.render(toy.image_raw, toy.pixel, 2)
    assert a.dtype == np.uint16 and a.shape == (2, 104, 139)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, m.replace(seed=4).render(toy.image_raw, toy.pixel, 2))
    assert not np.array_equal(a[0], a[1])  # independent noise per frame
    clean = m.replace(noise_scale=0)
    assert np.array_equal(
        clean.render(toy.image_raw, toy.pixel)[0], np.rint(clean.expected(toy.image_raw, toy.pixel)).astype(np.uint16)
    )
    m8 = m.replace(bits=8)
    assert m8.render(toy.image_raw, toy.pixel).dtype == np.uint8
    # the lesion press is brighter than the background press at the centre
    F, B = render_pair(clean, toy.image_raw, toy.image, toy.pixel, 1)
    r0, c0, n = m.window
    assert F[0, r0 + n // 2, c0 + n // 2] > B[0, r0 + n // 2, c0 + n // 2]


@pytest.mark.parametrize(
    "bad",
    [
        dict(bits=10),  # 8, 12 and 16 are the bit depths (12 since the sensor description)
        dict(binning=0),
        dict(w_sat=0),
        dict(led_power=(1, 1, 1)),
        dict(noise_scale=-1),
        dict(window_native=2000),
    ],
)
def test_bad_sensor_parameters(bad):
    with pytest.raises(UserError):
        SensorModel(**bad).validate()


def test_sensor_dict_roundtrip():
    m = SensorModel(seed=7, noise_scale=2.0)
    assert SensorModel.from_dict(m.to_dict()) == m
    with pytest.raises(UserError, match="unknown"):
        SensorModel.from_dict({"gain": 2})


@pytest.mark.parametrize("fmt,bits", [("png", 16), ("png", 8), ("tiff", 16), ("tiff", 8)])
def test_write_read_roundtrip_labelled_synthetic(tmp_path, toy, fmt, bits):
    m = SensorModel(bits=bits)
    F = m.render(toy.image_raw, toy.pixel, 2)
    paths = write_frames(F, tmp_path, "lesion", fmt, {"d": 8.0})
    assert all("synthetic" in p for p in paths)
    meta = read_metadata(paths[0])
    assert meta["synthetic"] is True and meta["d"] == 8.0 and meta["bits"] == bits
    stack, full = read_stack(paths, m.shape, m.window)
    assert full == (255 if bits == 8 else 65535)
    assert np.array_equal(stack, F.astype(float))


def test_bad_files_name_the_file(tmp_path, toy):
    m = SensorModel()
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(UserError, match="empty.png: empty file"):
        read_frame(empty)
    corrupt = tmp_path / "corrupt.png"
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 20)
    with pytest.raises(UserError, match="corrupt.png"):
        read_frame(corrupt)
    with pytest.raises(UserError, match="missing.tif: no such file"):
        read_frame(tmp_path / "missing.tif")
    [small] = write_frames(np.zeros((1, 10, 12), np.uint16) + 100, tmp_path, "small", "png")
    with pytest.raises(UserError, match="small_f000.png: wrong size 12x10"):
        read_frame(small, m.shape)
    sat = m.render(toy.image_raw, toy.pixel, 1)
    sat[0, 10:40, 30:60] = 65535
    [p] = write_frames(sat, tmp_path, "sat", "tiff")
    with pytest.warns(CameraWarning, match="sat_f000.tif: .* saturated"):
        read_frame(p, m.shape, m.window)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_frame(write_frames(m.render(toy.image_raw, toy.pixel, 1), tmp_path, "fine", "png")[0], m.shape, m.window)


def test_deflection_noise_map_matches_rendered_frames():
    """The linearised deflection-equivalent noise map (mm per image pixel) against the rendered frames
    themselves: the lesion-minus-background frame means of a press with no inclusion, turned into mm
    by the model's own response slope, scatter like the map predicts (SYNTHETIC camera; quantisation
    and the Poisson draw are in the frames, not in the map)."""
    from elastimap.camera.optics import deflection_noise_map

    m = SensorModel(seed=5)
    bg, pixel, frames = np.full((50, 50), 0.2), 0.5, 8
    sigma = deflection_noise_map(bg, pixel, frames, m)
    assert sigma.shape == bg.shape and np.all(sigma > 0)
    np.testing.assert_allclose(deflection_noise_map(bg, pixel, 4 * frames, m), sigma / 2, rtol=1e-12)
    assert np.all(deflection_noise_map(bg, pixel, frames, m.replace(noise_scale=0.0)) == 0)
    rng = np.random.default_rng(0)
    diff = m.render(bg, pixel, frames, rng).mean(0) - m.render(bg, pixel, frames, rng).mean(0)
    eps = 1e-4
    slope = (m.expected(bg + eps, pixel) - m.expected(bg, pixel)) / eps  # DN per mm
    r0, c0, n = m.window
    win = (slice(r0, r0 + n), slice(c0, c0 + n))
    dw = diff[win] / slope[win]
    dw_img = dw.reshape(50, n // 50, 50, n // 50).mean(axis=(1, 3))
    z = dw_img / sigma
    assert abs(z.mean()) < 0.1 and 0.9 < z.std() < 1.1, (z.mean(), z.std())
