"""Synthetic TIR camera: probe deformation -> raw camera frames (SYNTHETIC).

The real sensor (paper section 2) is a PDMS waveguide lit from its four sides
by LEDs so that light is totally internally reflected; where the contact layer
is pressed and deformed, light escapes the waveguide, is scattered downwards
and reaches a cooled mono camera (1392 x 1042 pixels, 4.65 um) below the
glass plate.  This module is a *documented stand-in* for that optics, used to
exercise the camera chain end to end.  It is not a ray-optics simulation.

Model, per camera pixel (electrons, for one frame)::

    e(x, y) = b^2 * FW * ( stray * L(x, y) + level * L(x, y) * s(w(x, y)) )
    s(w)    = 1 - exp(-max(w, 0) / w_sat)            (monotone, saturating)
    L(x, y) = vignette(x, y) * sum_k p_k / (1 + (r_k / r0)^2), normalised to mean 1
    frame   = clip(round(FS * clip((dark + e + shot + read) / (b^2 FW), 0, 1)^gamma), 0, FS)

Two effect switches are off in the nominal camera: ``blur_mm`` convolves the light image
(stray + scattered) with a Gaussian point-spread of that sigma (mm on the probe), and
``gamma`` != 1 makes the response a power law (FS = 2^bits - 1; gamma = 1 is the linear ADC).
A third, ``lens_k1`` (0 in the nominal camera; a sensor description may give its lens's value),
is radial lens distortion of the imaging (Brown-Conrady, first radial term),

    r_d = r_u * (1 + k1 * (r_u / R)^2),    R = footprint_mm / sqrt(2) (the footprint's half-diagonal)

r_u the distance (mm on the probe) of a probe point from the optical axis (the probe axis, the
window's centre), r_d where the camera images it (in the same mm); so k1 is the fractional radial
displacement of the footprint's corner (0.02: a point at the corner imaged 2 % farther out;
k1 > 0 pincushion, k1 < 0 barrel).  The light image (stray + scattered, before the blur) is
resampled at r_u(r_d) (Newton on the cubic; bilinear); k1 = 0 skips it (the nominal camera, bit
for bit).  It is the effect ``lens_distortion`` of :mod:`elastimap.gap.effects` (a default
candidate of the diagnosis; docs/gap.md, 'Effects library').

* ``w`` is the raw probe-bottom deflection of the FEM (``SolveResult.image_raw``,
  mm of probe compression *including* the flat-punch edge peaks), bilinearly
  resampled onto the camera pixels.  The camera sees the whole deformation;
  the inclusion is isolated later by subtracting a *background frame*: the
  same press with no inclusion (``image_raw - image`` of the same solve).
* ``L`` is the illumination of four side LEDs at the middle of each side,
  ``led_gap`` mm outside the footprint, relative powers ``led_power``
  (left, right, bottom, top) and radial fall-off ``r0``, times a quadratic
  lens vignetting ``1 - vignetting * (r / R)^2``.
* ``b`` is the software binning: the default frame is the full sensor
  averaged in ``binning x binning`` blocks (104 x 139 pixels for b = 10), so a
  binned pixel collects b^2 native pixels' electrons (shot noise and read
  noise add accordingly: the noise of the average, not of one pixel).
* shot noise is Poisson in the electrons; read noise is Gaussian
  (``read_noise_e`` per native pixel, so ``b * read_noise_e`` per binned one);
  ``noise_scale`` multiplies both noise terms (0 = noise-free; >1 for
  harder detection studies).  The ADC maps ``b^2 * FW`` to full scale
  ``2^bits - 1`` and adds ``dark_e`` electrons of offset.

Geometry: the 25 x 25 mm probe footprint is imaged onto a centred square
window of ``window_native`` native pixels (1000 by default: 25 um per native
pixel on the probe, magnification 0.186); binned, that is
``window_native // binning`` pixels (100 at b = 10, 0.25 mm each).  Frames
keep the FEM image orientation (row 0 at y = -size/2, column 0 at
x = -size/2); a real camera below the plate sees a mirror image, flip real
frames before use if the inclusion position matters (features do not care).

Every parameter lives in :class:`SensorModel` (declared and checked in
:class:`elastimap.sensor.CameraSpec`, the camera part of the sensor description); randomness comes only from the
``numpy.random.Generator`` passed in (or the ``seed``).  Pure numpy/scipy:
no solver is imported.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from elastimap.errors import UserError
from elastimap.sensor import MAX_NOISE_SCALE, CameraSpec

__all__ = ["MAX_NOISE_SCALE", "SensorModel"]


@dataclass(frozen=True)
class SensorModel(CameraSpec):
    """The synthetic TIR camera (see the module docstring): the camera's parameters, declared and
    checked once in :class:`elastimap.sensor.CameraSpec` (the camera part of the sensor
    description), with the optics that turn a deflection image into frames."""

    def validate(self) -> SensorModel:
        """The sensor description's checks (:meth:`elastimap.sensor.CameraSpec.validate`), and a
        barrel distortion (``lens_k1`` < 0) one-to-one over the whole frame (dr_d/dr_u =
        1 + 3 k1 (r_u/R)^2 > 0 out to the frame's corner); returns self."""
        super().validate()
        if self.lens_k1 >= 0.0:  # pincushion (or none) never folds
            return self
        rho2 = self._frame_corner_mm() ** 2 / self._distortion_radius() ** 2
        if 1.0 + 3.0 * self.lens_k1 * rho2 <= 0.0:
            raise UserError(
                "lens_k1", f"folds the image inside the frame (k1 {self.lens_k1:g} < {-1 / (3 * rho2):.3g})"
            )
        return self

    def replace(self, **changes) -> SensorModel:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["led_power"] = list(self.led_power)
        for k, v in SWITCH_DEFAULTS.items():  # effect switches omitted at their defaults (stable files)
            if d[k] == v:
                del d[k]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> SensorModel:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise UserError("sensor", f"unknown sensor parameter(s): {', '.join(sorted(unknown))}")
        d = dict(d)
        try:
            if "led_power" in d:
                d["led_power"] = tuple(float(p) for p in d["led_power"])
            return cls(**d).validate()
        except (TypeError, ValueError) as exc:
            if isinstance(exc, UserError):
                raise
            raise UserError("sensor", f"a sensor parameter has the wrong type ({exc})") from None

    @classmethod
    def of(cls, sensor) -> SensorModel:
        """The camera of a sensor description (:class:`elastimap.sensor.Sensor`)."""
        return cls(**{f.name: getattr(sensor.camera, f.name) for f in dataclasses.fields(CameraSpec)})

    def spec(self) -> CameraSpec:
        """The plain parameters (the camera part of a sensor description)."""
        return CameraSpec(**{f.name: getattr(self, f.name) for f in dataclasses.fields(CameraSpec)})

    # ------------------------------------------------------------- geometry
    @property
    def shape(self) -> tuple[int, int]:
        """Frame shape (rows, cols) after binning."""
        return self.sensor_rows // self.binning, self.sensor_cols // self.binning

    @property
    def window(self) -> tuple[int, int, int]:
        """(row0, col0, n): the footprint occupies ``frame[row0:row0+n, col0:col0+n]``."""
        n = self.window_native // self.binning
        rows, cols = self.shape
        return (rows - n) // 2, (cols - n) // 2, n

    @property
    def pixel_mm(self) -> float:
        """Side of one (binned) camera pixel on the probe, mm."""
        return self.footprint_mm / self.window[2]

    @property
    def full_scale(self) -> int:
        return 2**self.bits - 1

    @property
    def e_per_dn(self) -> float:
        return self.binning**2 * self.full_well_e / self.full_scale

    def window_centres(self) -> np.ndarray:
        """Coordinates (mm) of the window pixel centres along one axis."""
        n = self.window[2]
        return -self.footprint_mm / 2 + self.pixel_mm * (np.arange(n) + 0.5)

    def frame_coordinates(self) -> tuple[np.ndarray, np.ndarray]:
        """(X, Y): mm on the probe of every frame pixel's centre (the probe axis at 0), each of
        the frame's shape."""
        rows, cols = self.shape
        r0, c0, _ = self.window
        p = self.pixel_mm
        y = -self.footprint_mm / 2 + p * (np.arange(rows) - r0 + 0.5)
        x = -self.footprint_mm / 2 + p * (np.arange(cols) - c0 + 0.5)
        return np.meshgrid(x, y)

    def _distortion_radius(self) -> float:
        """R of the distortion (mm): the footprint's half-diagonal."""
        return self.footprint_mm / math.sqrt(2.0)

    def _frame_corner_mm(self) -> float:
        X, Y = self.frame_coordinates()
        return float(np.sqrt(X**2 + Y**2).max())

    # --------------------------------------------------------------- optics
    def undistorted_radius(self, r_d: np.ndarray) -> np.ndarray:
        """r_u (mm) of the probe point the camera images at r_d (mm): the root of
        r_u (1 + k1 (r_u/R)^2) = r_d (Newton from r_u = r_d; one-to-one where :meth:`validate`
        allows k1, converged to 1e-12 mm)."""
        r_d = np.asarray(r_d, dtype=float)
        a = self.lens_k1 / self._distortion_radius() ** 2
        r = r_d.copy()
        for _ in range(50):
            step = (r + a * r**3 - r_d) / (1.0 + 3.0 * a * r**2)
            r -= step
            if np.all(np.abs(step) < 1e-12):
                break
        return r

    def distort(self, img: np.ndarray) -> np.ndarray:
        """The frame-shaped light image ``img`` as the distorting lens images it: the camera pixel
        at (x_d, y_d) sees the probe point (x_d, y_d) r_u/r_d (bilinear; edge values beyond the
        frame).  k1 = 0: ``img`` itself."""
        if self.lens_k1 == 0.0:
            return img
        X, Y = self.frame_coordinates()
        r_d = np.sqrt(X**2 + Y**2)
        scale = np.ones_like(r_d)
        nz = r_d > 0
        scale[nz] = self.undistorted_radius(r_d[nz]) / r_d[nz]
        return self._read_radially_scaled(img, X, Y, scale)

    def undistort(self, img: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`distort` for a frame-shaped camera image ``img``: the value at the
        probe point (x_u, y_u) is read at the camera pixel that images it, (x_u, y_u) (1 + k1 (r_u/R)²)
        (bilinear; edge values beyond the frame).  k1 = 0: ``img`` itself."""
        if self.lens_k1 == 0.0:
            return img
        X, Y = self.frame_coordinates()
        scale = 1.0 + self.lens_k1 * (X**2 + Y**2) / self._distortion_radius() ** 2
        return self._read_radially_scaled(img, X, Y, scale)

    def _read_radially_scaled(self, img: np.ndarray, X: np.ndarray, Y: np.ndarray, scale: np.ndarray) -> np.ndarray:
        """The frame-shaped ``img`` read (bilinear; edge values beyond the frame) at the frame points
        (X, Y) · scale, mm on the probe from its axis."""
        r0, c0, _ = self.window
        p = self.pixel_mm
        col = (X * scale + self.footprint_mm / 2) / p + c0 - 0.5
        row = (Y * scale + self.footprint_mm / 2) / p + r0 - 0.5
        return ndimage.map_coordinates(img, [row, col], order=1, mode="nearest")

    def illumination(self) -> np.ndarray:
        """Relative illumination L over the full frame (mean 1 over the window)."""
        r0, c0, n = self.window
        X, Y = self.frame_coordinates()
        a = self.footprint_mm / 2 + self.led_gap
        leds = ((-a, 0.0), (a, 0.0), (0.0, -a), (0.0, a))
        L = np.zeros_like(X)
        for (lx, ly), pk in zip(leds, self.led_power):
            L += pk / (1.0 + ((X - lx) ** 2 + (Y - ly) ** 2) / self.led_r0**2)
        R = math.hypot(self.footprint_mm / 2, self.footprint_mm / 2)
        L *= np.clip(1.0 - self.vignetting * (X**2 + Y**2) / R**2, 0.0, None)
        L /= L[r0 : r0 + n, c0 : c0 + n].mean()
        return L

    def scatter(self, w: np.ndarray) -> np.ndarray:
        """Saturating monotone response s(w) in [0, 1) of the probe compression w (mm)."""
        return -np.expm1(-np.clip(w, 0.0, None) / self.w_sat)

    def deformation_on_frame(self, w_img: np.ndarray, pixel: float) -> np.ndarray:
        """Resample a deflection image (mm, square pixels of ``pixel`` mm over the footprint,
        row 0 at y = -size/2) onto the camera frame; 0 outside the footprint."""
        w_img = np.asarray(w_img, dtype=float)
        if w_img.ndim != 2 or w_img.size == 0 or not np.all(np.isfinite(w_img)):
            raise UserError("deflection", f"must be a finite non-empty 2-D image (got shape {w_img.shape})")
        c = self.window_centres()
        fy = (c + self.footprint_mm / 2) / pixel - 0.5  # fractional index into the FEM image
        fx = fy
        FY, FX = np.meshgrid(fy, fx, indexing="ij")
        win = ndimage.map_coordinates(w_img, [FY, FX], order=1, mode="nearest")
        out = np.zeros(self.shape)
        r0, c0, n = self.window
        out[r0 : r0 + n, c0 : c0 + n] = win
        return out

    def expected_electrons(self, w_img: np.ndarray, pixel: float) -> np.ndarray:
        """Noise-free electrons per (binned) pixel, without the dark offset."""
        w = self.deformation_on_frame(w_img, pixel)
        inside = np.zeros(self.shape, dtype=bool)
        r0, c0, n = self.window
        inside[r0 : r0 + n, c0 : c0 + n] = True
        L = self.illumination()
        rel = self.stray * L + self.level * L * self.scatter(w) * inside
        rel = self.distort(rel)  # radial lens distortion of the light image (module docstring; none at k1 = 0)
        if self.blur_mm > 0:  # point-spread of the light image: Gaussian, sigma blur_mm on the probe
            rel = ndimage.gaussian_filter(rel, self.blur_mm / self.pixel_mm, mode="nearest")
        return self.binning**2 * self.full_well_e * rel

    def response(self, electrons: np.ndarray) -> np.ndarray:
        """DN (float, unquantised) of a total charge per binned pixel (signal + dark, electrons):
        FS * clip(x, 0, 1)^gamma with x = electrons / (b^2 FW); gamma = 1 is the linear ADC."""
        x = np.clip(electrons / (self.binning**2 * self.full_well_e), 0.0, 1.0)
        return self.full_scale * (x if self.gamma == 1.0 else x**self.gamma)

    def expected(self, w_img: np.ndarray, pixel: float) -> np.ndarray:
        """Noise-free, unquantised frame in DN (float): the reference for noise tests."""
        e = self.expected_electrons(w_img, pixel) + self.binning**2 * self.dark_e
        return self.response(e)

    def render(
        self, w_img: np.ndarray, pixel: float, frames: int = 1, rng: np.random.Generator | None = None
    ) -> np.ndarray:
        """``frames`` independent noisy, quantised frames: array (frames, rows, cols) of uint8/uint16."""
        self.validate()
        if frames < 1:
            raise UserError("frames", f"must be >= 1 (got {frames})")
        rng = np.random.default_rng(self.seed) if rng is None else rng
        e = self.expected_electrons(w_img, pixel)
        dark = self.binning**2 * self.dark_e
        read_sd = self.binning * self.read_noise_e * self.noise_scale
        dtype = np.uint8 if self.bits == 8 else np.uint16
        out = np.empty((frames,) + self.shape, dtype=dtype)
        for i in range(frames):
            if self.noise_scale > 0:
                shot = rng.poisson(e) - e
                sig = e + self.noise_scale * shot + rng.normal(0.0, read_sd, e.shape)
            else:
                sig = e
            dn = np.rint(self.response(sig + dark))
            out[i] = np.clip(dn, 0, self.full_scale).astype(dtype)
        return out

    def describe(self) -> str:
        rows, cols = self.shape
        r0, c0, n = self.window
        return (
            f"SYNTHETIC TIR camera: {cols}x{rows} px (sensor {self.sensor_cols}x{self.sensor_rows} "
            f"at {self.pixel_um} um, binning {self.binning}), footprint window {n}x{n} px at "
            f"({r0},{c0}), {self.pixel_mm:.4g} mm/px, {self.bits}-bit, noise_scale {self.noise_scale:g}, "
            f"seed {self.seed}"
        )


# effect switches of the camera left out of ``SensorModel.to_dict`` while at these defaults
SWITCH_DEFAULTS = {"blur_mm": 0.0, "gamma": 1.0, "lens_k1": 0.0}


def background_deflection(image_raw: np.ndarray, image_diff: np.ndarray) -> np.ndarray:
    """The same press with no inclusion: raw deflection minus the difference image."""
    return np.asarray(image_raw, dtype=float) - np.asarray(image_diff, dtype=float)


def render_pair(
    model: SensorModel,
    image_raw: np.ndarray,
    image_diff: np.ndarray,
    pixel: float,
    frames: int = 30,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Frames of the lesion press and of the background press (no inclusion), independent noise."""
    rng = np.random.default_rng(model.seed) if rng is None else rng
    lesion = model.render(image_raw, pixel, frames, rng)
    bg = model.render(background_deflection(image_raw, image_diff), pixel, frames, rng)
    return lesion, bg


def deflection_noise_map(background: np.ndarray, pixel: float, frames: int = 30, sensor=None) -> np.ndarray:
    """Deflection-equivalent noise (mm) per image pixel of the SYNTHETIC camera difference image.

    Linearised at the background deflection ``w``: per binned camera pixel the electron count is
    ``e = b² FW L (stray + level s(w))`` with variance ``noise_scale² (e + b² read²)``;
    ``de/dw = b² FW L level exp(-w / w_sat) / w_sat``.  The lesion and background frame means
    (``frames`` each) are differenced (variance x 2 / frames) and the camera pixels falling in
    one image pixel averaged.  Returns an array of the image's shape (mm), usable as the
    ``sigma_map`` of :func:`elastimap.identify.measure.add_image_noise` and
    :class:`elastimap.identify.bounds.NoiseSpec`.
    """
    s = (sensor or SensorModel()).validate()
    bg = np.asarray(background, dtype=float)
    w = s.deformation_on_frame(bg, pixel)
    r0, c0, n = s.window
    w = w[r0 : r0 + n, c0 : c0 + n]
    L = s.illumination()[r0 : r0 + n, c0 : c0 + n]
    b2fw = s.binning**2 * s.full_well_e
    e = b2fw * L * (s.stray + s.level * s.scatter(w))
    var_e = s.noise_scale**2 * (e + s.binning**2 * s.read_noise_e**2)
    dedw = b2fw * L * s.level * np.exp(-np.clip(w, 0, None) / s.w_sat) / s.w_sat
    var_w = var_e / dedw**2 * 2.0 / frames
    ny, nx = bg.shape
    fy, fx = n // ny, n // nx
    if fy * ny != n or fx * nx != n:
        raise UserError("pixel", f"camera window of {n} pixels is not a multiple of the image's {ny} x {nx}")
    var_img = var_w.reshape(ny, fy, nx, fx).mean(axis=(1, 3)) / (fy * fx)
    return np.sqrt(var_img)
