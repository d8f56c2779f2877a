"""Camera frames -> the FEM-equivalent difference image (mm) with its per-pixel noise.

The camera does not see the difference deflection.  With the TIR response of
:class:`elastimap.camera.optics.SensorModel`, one camera pixel reads (DN, mean over frames)::

    F = dark + FS * G(x, y) * (stray + level * s(w)),      s(w) = 1 - exp(-w / w_sat)

where ``G`` is that pixel's light gain (illumination, vignetting, exposure; 1 on average for the
nominal sensor) and ``w`` the probe compression (mm).  A lesion frame minus its background frame
is therefore ``FS G level (s(w_b + Δw) - s(w_b)) ≈ FS G level s'(w_b) Δw``: every pixel of the
camera difference is weighted by its own gain and by the local slope of the response at the
background compression ``w_b`` (which grows from about 0.09 mm at the centre to 0.48 mm at the
corners of the default press).  The shape the image network learnt from the FEM never arrives.

This module undoes the response per pixel instead (nothing is learnt, so it holds for lesions
and sensor settings the calibration never saw):

1. ``u = (mean frames - dark) / FS`` for the lesion (``u_F``) and the background (``u_B``) stack;
2. flat field from the background press: ``G = u_B / (stray + level s(w_b))``, with ``w_b`` the
   FEM's reference press (no inclusion; :func:`elastimap.camera.optics.background_deflection`)
   resampled onto the camera pixels.  Whatever the illumination, vignetting or exposure of the
   session are, they cancel here, because the background frames were taken with them;
3. inverse response of the lesion stack: ``s_F = (u_F / G - stray) / level`` and
   ``Δw = w_F - w_b = -w_sat ln((1 - s_F) / (1 - s(w_b)))`` (mm, per camera pixel);
4. onto the FEM image grid by least squares through the camera's sampling (bilinear
   interpolation of the FEM pixel values at the camera pixel centres, ``R``, separable):
   ``I = P Δw Pᵀ`` with ``P = (RᵀR)⁻¹ Rᵀ``;
5. times the calibration's ``scale`` (least-squares factor between these images and the FEM
   difference images of the nine phantoms; 1 for a sensor that follows the model).

Noise: the standard error of each mean comes from the frames' own scatter,
``var(u_F) = var_frames / n_F`` (likewise the background), smoothed over ``var_smooth_px``
camera pixels (shot and read noise vary slowly; 30 frames give a 26 % scatter per pixel),
propagated through steps 2-4 to first order::

    ∂Δw/∂u_F = w_sat (c + s_b) / ((1 - s_F) u_B),   ∂Δw/∂u_B = -w_sat (c + s_F) / ((1 - s_F) u_B),
    c = stray / level,  var(I) = (P∘P) var(Δw) (P∘P)ᵀ  (neighbouring pixels' covariance ignored).

What it assumes: the response *shape* (``w_sat``, ``stray / level``, the dark offset) of the
calibration's sensor and the reference press of the FEM.  What it does not assume: the
illumination, LED powers, vignetting or exposure (absorbed by the flat field), nor the noise
level (measured from the frames).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from elastimap.errors import UserError

MIN_FRAMES = 2  # the scatter needs two frames per stack
MAX_FRAMES = 1000  # frames per press a command takes (30 s of video at the sensor's 30 frames/s)
VAR_SMOOTH_PX = 2.0  # Gaussian sigma (camera pixels) over which the frame variance is averaged
S_MAX = 1.0 - 1e-6  # inverse response: s at or above this is saturated scattering


@dataclass
class DeflectionImage:
    """A lesion's FEM-equivalent difference image (mm) and its per-pixel standard error (mm)."""

    image: np.ndarray  # (ny, nx) mm, on the FEM image grid
    sigma: np.ndarray  # (ny, nx) mm, standard error of each pixel (from the frames' scatter)
    pixel: float  # mm, the FEM grid's pixel side
    camera: np.ndarray  # (n, n) mm, the difference deflection on the camera pixels of the window
    n_frames: int
    n_background: int
    scale: float = 1.0  # the calibration factor applied
    saturated: int = 0  # camera pixels whose inverse response was clipped

    @property
    def peak(self) -> float:
        return float(np.max(self.image))


def sampling_matrix(n_cam: int, pixel_cam: float, n_img: int, pixel_img: float) -> np.ndarray:
    """``R`` (n_cam, n_img): camera pixel centres sample the FEM pixel values bilinearly (1-D factor).

    Both grids are centred on the probe axis; the same convention as
    :meth:`elastimap.camera.optics.SensorModel.deformation_on_frame` (indices clamped at the border)."""
    c = -n_cam * pixel_cam / 2 + pixel_cam * (np.arange(n_cam) + 0.5)
    f = (c + n_img * pixel_img / 2) / pixel_img - 0.5
    f = np.clip(f, 0.0, n_img - 1.0)
    i0 = np.clip(np.floor(f).astype(int), 0, max(n_img - 2, 0))
    t = f - i0
    R = np.zeros((n_cam, n_img))
    R[np.arange(n_cam), i0] += 1.0 - t
    if n_img > 1:
        R[np.arange(n_cam), i0 + 1] += t
    return R


def backprojector(n_cam: int, pixel_cam: float, n_img: int, pixel_img: float) -> np.ndarray:
    """``P = (RᵀR)⁻¹ Rᵀ`` (n_img, n_cam): least-squares FEM pixel values from camera pixel values."""
    R = sampling_matrix(n_cam, pixel_cam, n_img, pixel_img)
    if np.linalg.matrix_rank(R) < n_img:
        raise UserError(
            "pixel",
            f"the camera's {n_cam} pixels of {pixel_cam:g} mm cannot resolve a {n_img}-pixel image of {pixel_img:g} mm",
        )
    return np.linalg.pinv(R)


def _stack(a, what: str) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3 or 0 in a.shape:
        raise UserError(what, f"must be a stack of 2-D frames (got shape {a.shape})")
    if a.shape[0] < MIN_FRAMES:
        raise UserError(
            what, f"need at least {MIN_FRAMES} frames to measure the noise from their scatter (got {a.shape[0]})"
        )
    if not np.all(np.isfinite(a)):
        raise UserError(what, "contains NaN or inf")
    return a


def _mean_and_var(stack: np.ndarray, smooth_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean over frames and the variance of that mean (frame variance / n, spatially smoothed)."""
    m = stack.mean(axis=0)
    v = stack.var(axis=0, ddof=1) / stack.shape[0]
    if smooth_px > 0:
        v = ndimage.gaussian_filter(v, smooth_px, mode="reflect")
    return m, v


def difference_image(
    frames,
    background,
    sensor,
    reference: np.ndarray,
    pixel: float,
    shape: tuple[int, int] | None = None,
    scale: float = 1.0,
    var_smooth_px: float = VAR_SMOOTH_PX,
) -> DeflectionImage:
    """Lesion and background frame stacks (DN, full frames of ``sensor``'s size) -> :class:`DeflectionImage`.

    ``reference``: the FEM reference press (no inclusion) on its grid of ``pixel`` mm (mm of probe
    compression); ``shape`` the FEM grid of the output (default: the reference's);  ``scale`` the
    calibration factor.  See the module docstring for the equations."""
    s = sensor.validate()
    F = _stack(frames, "frames")
    B = _stack(background, "background")
    if F.shape[1:] != s.shape or B.shape[1:] != s.shape:
        raise UserError(
            "frames",
            f"frames of {F.shape[2]}x{F.shape[1]} and background of {B.shape[2]}x{B.shape[1]} "
            f"pixels; the calibration's camera has {s.shape[1]}x{s.shape[0]}",
        )
    ref = np.asarray(reference, dtype=float)
    if ref.ndim != 2 or not np.all(np.isfinite(ref)):
        raise UserError("reference", f"the reference deflection must be a finite 2-D image (got {ref.shape})")
    if not (np.isfinite(scale) and scale > 0):
        raise UserError("scale", f"must be > 0 (got {scale})")
    ny, nx = shape or ref.shape
    if ny != nx:
        raise UserError("shape", f"the FEM image grid must be square (got {ny} x {nx})")
    r0, c0, n = s.window
    win = (slice(r0, r0 + n), slice(c0, c0 + n))
    fs, dark = float(s.full_scale), s.binning**2 * s.dark_e / s.e_per_dn
    mF, vF = _mean_and_var(F, var_smooth_px)
    mB, vB = _mean_and_var(B, var_smooth_px)
    # a distorting lens (``lens_k1``): back to the probe's coordinates first (none at k1 = 0)
    mF, vF, mB, vB = (s.undistort(a) for a in (mF, vF, mB, vB))
    uF, uB = (mF[win] - dark) / fs, (mB[win] - dark) / fs
    vF, vB = vF[win] / fs**2, vB[win] / fs**2
    if np.any(uB <= 0):
        raise UserError(
            "background",
            f"{int(np.count_nonzero(uB <= 0))} footprint pixels of the background frames "
            f"are at or below the dark level: no light reaches them",
        )
    wb = s.deformation_on_frame(ref, pixel)[win]
    sb = s.scatter(wb)
    c = s.stray / s.level
    G = uB / (s.level * (c + sb))  # per-pixel light gain (flat field)
    sF = (uF / G) / s.level - c
    sat = int(np.count_nonzero(sF >= S_MAX))
    if sat:
        warnings.warn(
            f"{sat} camera pixels beyond the response's saturation; their deflection is clipped", stacklevel=2
        )
    sF = np.clip(sF, -np.inf, S_MAX)
    dw = -s.w_sat * np.log((1.0 - sF) / (1.0 - sb))
    gF = s.w_sat * (c + sb) / ((1.0 - sF) * uB)
    gB = -s.w_sat * (c + sF) / ((1.0 - sF) * uB)
    var_dw = gF**2 * vF + gB**2 * vB
    P = backprojector(n, s.pixel_mm, ny, pixel)
    img = P @ dw @ P.T
    P2 = P * P
    var_img = P2 @ var_dw @ P2.T
    return DeflectionImage(
        scale * img, scale * np.sqrt(var_img), float(pixel), dw, F.shape[0], B.shape[0], float(scale), sat
    )


def fit_scale(recovered: list[np.ndarray], fem: list[np.ndarray]) -> tuple[float, list[float]]:
    """Least-squares ``k`` with ``fem ≈ k recovered`` over all pixels of all pairs, and each pair's
    relative rms residual ``‖fem - k rec‖ / ‖fem‖`` after it."""
    if len(recovered) != len(fem) or not recovered:
        raise UserError("calibration", "need matching recovered and FEM difference images")
    num = sum(float(np.sum(np.asarray(r) * np.asarray(f))) for r, f in zip(recovered, fem))
    den = sum(float(np.sum(np.asarray(r) ** 2)) for r in recovered)
    if not den > 0:
        raise UserError("calibration", "the recovered phantom difference images are all zero")
    k = num / den
    rel = [
        float(np.linalg.norm(np.asarray(f) - k * np.asarray(r)) / max(np.linalg.norm(f), 1e-300))
        for r, f in zip(recovered, fem)
    ]
    return k, rel


# ---------------------------------------------------------------- the flat field's press uncertainty
#: radial modes of the press error: Gaussian bumps in r (mm from the probe axis) every PRESS_STEP mm,
#: of sd PRESS_WIDTH mm (docs/camera.md, 'The flat field's press uncertainty')
PRESS_STEP = 3.0
PRESS_WIDTH = 3.0
PRESS_SMOOTH_MM = 1.0  # Gaussian sigma (mm) over which the press spread's square is averaged
#: the press sd is carried where the calibration phantoms do not see it, σ_s (1 − q)^PRESS_POWER
#: (:func:`uninformed`; chosen on the SYNTHETIC variant worlds, docs/camera.md, 'The flat field's press uncertainty')
PRESS_POWER = 1.0


def radius_grid(shape, pixel: float) -> np.ndarray:
    """Distance (mm) of each pixel centre of a centred image of ``shape`` (ny, nx) and ``pixel`` mm
    from the probe axis."""
    ny, nx = shape
    y = (np.arange(ny) - (ny - 1) / 2) * pixel
    x = (np.arange(nx) - (nx - 1) / 2) * pixel
    return np.hypot(*np.meshgrid(y, x, indexing="ij"))


def press_sensitivity(dw, w_b, sensor) -> np.ndarray:
    """``J = ∂Δw/∂w_b`` (dimensionless, per pixel): how a recovered difference deflection ``Δw`` (mm)
    moves when the flat field's background press ``w_b`` (mm) is off, the frames held fixed::

        J = (c + s(w_b + Δw)) / (c + s(w_b)) exp(Δw / w_sat) − 1,     c = stray / level

    (steps 2-3 of :func:`difference_image`: ``s_F = ρ (c + s_b) − c`` with ``ρ = u_F/u_B`` fixed, so
    ``∂Δw/∂w_b = ρ (1 − s_b)/(1 − s_F) − 1``).  About ``Δw (1 − 2a + c)/(w_sat (1 + c − a))``,
    ``a = exp(−w_b/w_sat)``: proportional to the lesion's own image."""
    s = sensor
    c = s.stray / s.level
    w_b = np.asarray(w_b, float)
    dw = np.asarray(dw, float)
    return (c + s.scatter(w_b + dw)) / (c + s.scatter(w_b)) * np.exp(dw / s.w_sat) - 1.0


def press_spread(reference, alternatives, pixel: float) -> np.ndarray:
    """The press's model-form sd ``σ_s`` (mm, per pixel of the reference's grid of ``pixel`` mm): the
    quadrature sum of the differences of elastimap's other models of the same background press
    (``alternatives``: the contact interface, the neighbouring mesh level) from ``reference``, each
    squared and averaged over a Gaussian of :data:`PRESS_SMOOTH_MM`."""
    ref = np.asarray(reference, float)
    sq = sum((np.asarray(a, float) - ref) ** 2 for a in alternatives)
    return np.sqrt(ndimage.gaussian_filter(sq, PRESS_SMOOTH_MM / pixel, mode="nearest"))


def uninformed(sd, phantom_images, power: float) -> np.ndarray:
    """``σ_s (1 − q)^power``: the press sd left where the calibration phantoms do not see the press,
    ``q(x) = max_k |m_k(x)| / max |m_k|`` (the phantoms' FEM difference images, each relative to its
    peak).  Where a phantom's image is large, the flat field's press error is in its residual and so in
    the model-form term learnt from it; the press term carries the rest (docs/camera.md, 'The flat
    field's press uncertainty')."""
    q = np.max([np.abs(np.asarray(m, float)) / max(float(np.abs(m).max()), 1e-300) for m in phantom_images], axis=0)
    return np.asarray(sd, float) * (1.0 - np.clip(q, 0.0, 1.0)) ** power


def press_modes(sd, pixel: float) -> np.ndarray:
    """The press error's low-rank basis ``B`` ``(p, K)`` (mm per unit coefficient): a smooth field
    ``δ(x) = Σ_k γ_k B_k(x)``, ``γ ~ N(0, I)``, with ``B_k = σ_s(x) φ_k(r) / (Σ_j φ_j(r)²)^½`` and
    ``φ_k`` Gaussian bumps in the distance ``r`` from the probe axis (centres every
    :data:`PRESS_STEP` mm, sd :data:`PRESS_WIDTH` mm), so that ``sd δ(x) = σ_s(x)`` and the error of
    one ring is one coefficient shared by every pixel on it (and its neighbours)."""
    sd = np.asarray(sd, float)
    r = radius_grid(sd.shape, pixel).ravel()
    centres = np.arange(0.0, r.max() + PRESS_STEP, PRESS_STEP)
    phi = np.exp(-0.5 * ((r[:, None] - centres[None, :]) / PRESS_WIDTH) ** 2)
    phi /= np.sqrt((phi**2).sum(axis=1, keepdims=True))
    return sd.ravel()[:, None] * phi


@dataclass
class PressTerm:
    """The flat field's press uncertainty as a low-rank error of the recovered difference image: with the
    press off by ``δ = B γ`` (:func:`press_modes`), the recovered image (FEM grid, mm, times ``scale``)
    is off by ``scale J(m/scale) ⊙ δ`` (:func:`press_sensitivity`, taken at the map's image ``m``, not
    the measured one, so that the weights carry no frame noise).  Called with ``m`` (mm, flat) it returns
    ``U = scale J ⊙ B`` ``(p, K)``: the fit's pixel covariance becomes ``diag σ² + U Uᵀ``
    (:class:`elastimap.identify.fit.FitConfig`, ``shared``).  docs/camera.md, 'The flat field's press
    uncertainty'."""

    reference: np.ndarray  # (ny, nx) mm, the flat field's background press on the FEM grid
    basis: np.ndarray  # (p, K) mm, press_modes
    sensor: object  # the SensorModel whose response the flat field inverts
    scale: float = 1.0

    def __call__(self, m) -> np.ndarray:
        dw = np.asarray(m, float).ravel() / self.scale
        J = press_sensitivity(dw, self.reference.ravel(), self.sensor)
        return (self.scale * J)[:, None] * self.basis

    @classmethod
    def of(cls, deflection: dict, sensor) -> PressTerm | None:
        """The term of a calibration's deflection record (None where it holds no ``press_sd``)."""
        sd = deflection.get("press_sd") if deflection else None
        if sd is None:
            return None
        ref = np.asarray(deflection["reference"], float)
        return cls(
            ref,
            press_modes(np.asarray(sd, float), float(deflection["pixel"])),
            sensor,
            float(deflection.get("scale", 1.0)),
        )
