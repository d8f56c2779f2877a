"""Radial lens distortion of the SYNTHETIC camera (``lens_k1``; docs/camera.md, 'Synthetic TIR
sensor model')."""

import dataclasses

import numpy as np
import pytest

from elastimap.camera.optics import SensorModel
from elastimap.errors import UserError
from elastimap.sensor import PAPER_HASH, CameraSpec, Sensor
from elastimap.solver.synthetic import solve_dhe as toy_solve  # SYNTHETIC stand-in, not physics

N = 200  # deflection image pixels across the 25 mm footprint
PIX = 25.0 / N


def _spot(x0: float, y0: float = 0.0, sigma: float = 0.6) -> np.ndarray:
    c = -12.5 + PIX * (np.arange(N) + 0.5)
    X, Y = np.meshgrid(c, c)  # row 0 at y = -12.5, as the FEM images
    return 0.3 * np.exp(-((X - x0) ** 2 + (Y - y0) ** 2) / (2 * sigma**2))


def _centroid(m: SensorModel, w: np.ndarray) -> tuple[float, float]:
    """Centroid (mm) of the light the deflection ``w`` adds to the noise-free frame."""
    sig = m.expected(w, PIX) - m.expected(np.zeros_like(w), PIX)
    X, Y = m.frame_coordinates()
    return float((sig * X).sum() / sig.sum()), float((sig * Y).sum() / sig.sum())


def test_zero_is_the_nominal_camera_bit_for_bit():
    m = SensorModel()
    assert m.lens_k1 == 0.0 and "lens_k1" not in m.to_dict()  # stable files and cache keys
    assert set(m.to_dict()) == {f.name for f in dataclasses.fields(CameraSpec)} - {"blur_mm", "gamma", "lens_k1"}
    assert SensorModel.of(Sensor()).lens_k1 == 0.0
    assert "lens_k1" not in Sensor().to_dict()["camera"] and Sensor().hash() == PAPER_HASH  # descriptions of before
    toy = toy_solve(8.0, 8.0, 80.0)
    img = m.illumination()
    assert m.distort(img) is img
    a = m.render(toy.image_raw, toy.pixel, 2, np.random.default_rng(1))
    b = SensorModel(lens_k1=0.0).render(toy.image_raw, toy.pixel, 2, np.random.default_rng(1))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, m.replace(lens_k1=0.1).render(toy.image_raw, toy.pixel, 2, np.random.default_rng(1)))


@pytest.mark.parametrize("k1", [0.2, -0.15])
def test_distortion_moves_a_feature_radially(k1):
    """A spot 10 mm off the axis is imaged at r_u (1 + k1 (r_u/R)^2), R the footprint's
    half-diagonal: outwards for k1 > 0 (pincushion), inwards for k1 < 0 (barrel), along its radius."""
    R = 25.0 / np.sqrt(2.0)
    for x0, y0 in ((10.0, 0.0), (-6.0, 6.0)):
        w = _spot(x0, y0)
        cx0, cy0 = _centroid(SensorModel(), w)
        cx, cy = _centroid(SensorModel(lens_k1=k1), w)
        r0 = np.hypot(x0, y0)
        want = k1 * (r0 / R) ** 2  # fractional radial shift
        assert np.hypot(cx, cy) / np.hypot(cx0, cy0) - 1 == pytest.approx(want, abs=0.1 * abs(want))
        # radial: the shift is along the spot's own direction
        assert abs(cx0 * (cy - cy0) - cy0 * (cx - cx0)) < 0.02 * r0 * np.hypot(cx - cx0, cy - cy0) + 1e-9


def test_centre_stays_and_inverse_is_exact():
    m = SensorModel(lens_k1=0.3)
    cx, cy = _centroid(m, _spot(0.0))
    assert abs(cx) < 0.01 and abs(cy) < 0.01  # the axis does not move
    r = np.linspace(0.0, 22.0, 50)
    a = 0.3 / (25.0 / np.sqrt(2.0)) ** 2
    ru = m.undistorted_radius(r)
    np.testing.assert_allclose(ru * (1 + a * ru**2), r, atol=1e-10)
    assert np.all(ru[1:] < r[1:])  # pincushion: the pixel sees a point nearer the axis


def test_bad_distortion_is_refused_and_dict_roundtrips():
    for bad in (-0.3, 0.6, float("nan")):
        with pytest.raises(UserError, match="lens_k1"):
            SensorModel(lens_k1=bad).validate()
    m = SensorModel(lens_k1=0.12)
    assert m.to_dict()["lens_k1"] == 0.12 and SensorModel.from_dict(m.to_dict()) == m
    # a sensor description may hold its lens's distortion: another sensor, round-tripped
    lab = Sensor(camera=CameraSpec(lens_k1=0.05)).validate()
    assert lab.hash() != PAPER_HASH and Sensor.from_dict(lab.to_dict()) == lab
    assert SensorModel.of(lab).lens_k1 == 0.05 and SensorModel.of(lab).spec() == lab.camera


def test_difference_image_undoes_the_lens_it_is_told_of():
    """Frames through a distorting lens, recovered by ``difference_image`` with the camera that
    knows its k1 (a sensor description that adopted ``lens_distortion``), give the FEM difference
    image back; the nominal camera (k1 = 0) recovers a radially rescaled one.  SYNTHETIC, noise-free."""
    from elastimap.camera.deflection import difference_image
    from elastimap.camera.optics import background_deflection, render_pair

    toy = toy_solve(10.0, 7.0, 60.0)
    ref = background_deflection(toy.image_raw, toy.image)
    lens = SensorModel(lens_k1=-0.15, noise_scale=0.0)
    F, B = render_pair(lens, toy.image_raw, toy.image, toy.pixel, frames=2)
    peak = np.abs(toy.image).max()

    def err(camera):
        rec = difference_image(F, B, camera, ref, toy.pixel).image
        return np.sqrt(np.mean((rec - toy.image) ** 2)) / peak

    told, nominal = err(lens), err(SensorModel(noise_scale=0.0))
    assert told < 0.1 * nominal, (told, nominal)  # 1.6e-4 against 8.8e-3 of the peak, rms
    assert told < 1e-3, told
    frame = F[0].astype(float)
    assert SensorModel().undistort(frame) is frame  # k1 = 0: the frames as they are
