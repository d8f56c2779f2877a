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
   plus, where the calibration has one, the correction ``δ`` learnt from its phantoms' frames
   (:func:`press_correction`; off by default), resampled onto the camera pixels.  Whatever the illumination, vignetting or exposure of the
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
calibration's sensor and the background press (the FEM's reference, or that plus ``δ``; docs/camera.md,
'The press correction').  What it does not assume: the
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


def _window_means(F: np.ndarray, B: np.ndarray, s, var_smooth_px: float):
    """``u_F, u_B`` (dark-corrected, in full scale) on the footprint window and the variances of those
    means (FS²), from the lesion and background stacks (DN)."""
    r0, c0, n = s.window
    win = (slice(r0, r0 + n), slice(c0, c0 + n))
    fs, dark = float(s.full_scale), s.binning**2 * s.dark_e / s.e_per_dn
    mF, vF = _mean_and_var(F, var_smooth_px)
    mB, vB = _mean_and_var(B, var_smooth_px)
    uF, uB = (mF[win] - dark) / fs, (mB[win] - dark) / fs
    if np.any(uB <= 0):
        raise UserError(
            "background",
            f"{int(np.count_nonzero(uB <= 0))} footprint pixels of the background frames "
            f"are at or below the dark level: no light reaches them",
        )
    return uF, uB, vF[win] / fs**2, vB[win] / fs**2


@dataclass
class _Inverse:
    """Steps 2-3 on the camera pixels of the window (module docstring)."""

    dw: np.ndarray  # mm, Δw per camera pixel
    var: np.ndarray  # mm², its variance from the frames' scatter
    saturated: np.ndarray  # bool, inverse response clipped


def _invert(uF, uB, vF, vB, wb: np.ndarray, s) -> _Inverse:
    """Flat field and inverse response at the background press ``wb`` (mm, camera pixels)."""
    sb = s.scatter(wb)
    c = s.stray / s.level
    G = uB / (s.level * (c + sb))  # per-pixel light gain (flat field)
    sF = (uF / G) / s.level - c
    sat = sF >= S_MAX
    sF = np.clip(sF, -np.inf, S_MAX)
    dw = -s.w_sat * np.log((1.0 - sF) / (1.0 - sb))
    gF = s.w_sat * (c + sb) / ((1.0 - sF) * uB)
    gB = -s.w_sat * (c + sF) / ((1.0 - sF) * uB)
    return _Inverse(dw, gF**2 * vF + gB**2 * vB, sat)


def _press_slope(wb: np.ndarray, dw: np.ndarray, s) -> np.ndarray:
    """``∂Δw/∂w_b`` (dimensionless) of the inverse response at background press ``wb`` and difference
    ``dw`` (mm): ``(c + s(w_b + Δw)) / (c + s(w_b)) exp(Δw / w_sat) - 1``; 0 where ``w_b <= 0`` (the
    response is clipped there)."""
    c = s.stray / s.level
    r = (c + s.scatter(wb + dw)) / (c + s.scatter(wb))
    return np.where(wb > 0, r * np.exp(dw / s.w_sat) - 1.0, 0.0)


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

    ``reference``: the background press (no inclusion) on its grid of ``pixel`` mm (mm of probe
    compression; the calibration's FEM reference plus its press correction,
    :meth:`elastimap.camera.calibration.Calibration.reference_image`); ``shape`` the FEM grid of the
    output (default: the reference's);  ``scale`` the calibration factor.  See the module docstring
    for the equations."""
    s = sensor.validate()
    F = _stack(frames, "frames")
    B = _stack(background, "background")
    if F.shape[1:] != s.shape or B.shape[1:] != s.shape:
        raise UserError(
            "frames",
            f"frames of {F.shape[2]}x{F.shape[1]} and background of {B.shape[2]}x{B.shape[1]} "
            f"pixels; the calibration's camera has {s.shape[1]}x{s.shape[0]}",
        )
    ref = _reference(reference)
    if not (np.isfinite(scale) and scale > 0):
        raise UserError("scale", f"must be > 0 (got {scale})")
    ny, nx = shape or ref.shape
    if ny != nx:
        raise UserError("shape", f"the FEM image grid must be square (got {ny} x {nx})")
    r0, c0, n = s.window
    uF, uB, vF, vB = _window_means(F, B, s, var_smooth_px)
    inv = _invert(uF, uB, vF, vB, s.deformation_on_frame(ref, pixel)[r0 : r0 + n, c0 : c0 + n], s)
    sat = int(np.count_nonzero(inv.saturated))
    if sat:
        warnings.warn(
            f"{sat} camera pixels beyond the response's saturation; their deflection is clipped", stacklevel=2
        )
    P = backprojector(n, s.pixel_mm, ny, pixel)
    img = P @ inv.dw @ P.T
    P2 = P * P
    var_img = P2 @ inv.var @ P2.T
    return DeflectionImage(
        scale * img, scale * np.sqrt(var_img), float(pixel), inv.dw, F.shape[0], B.shape[0], float(scale), sat
    )


def _reference(reference) -> np.ndarray:
    ref = np.asarray(reference, dtype=float)
    if ref.ndim != 2 or not np.all(np.isfinite(ref)):
        raise UserError("reference", f"the reference deflection must be a finite 2-D image (got {ref.shape})")
    return ref


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


# the press correction's settings, chosen on a SYNTHETIC variant world (docs/camera.md, 'The press
# correction'): Gaussian kernel sigma (mm) over which δ is taken as locally constant, the prior sd of δ
# (mm; where the phantoms carry little it stays near 0), the phantoms' model-form error per pixel as a
# fraction of each one's peak (it caps the weight of a pixel), Gauss-Newton passes
PRESS_ELL_MM = 1.0
PRESS_PRIOR_MM = 0.01
PRESS_FORM = 0.01
PRESS_ITERATIONS = 3


@dataclass
class PressCorrection:
    """The correction ``δ`` (mm) of the reference press learnt from the calibration phantoms' frames."""

    delta: np.ndarray  # (ny, nx) mm on the FEM grid: the background press is reference + delta
    sd: np.ndarray  # (ny, nx) mm, δ's posterior sd (PRESS_PRIOR_MM where the phantoms carry nothing)
    scale: float  # the global factor FEM ≈ scale x recovered at the last pass
    settings: dict

    def to_dict(self) -> dict:
        return {
            "model": "background press = reference + delta (elastimap.camera.deflection.press_correction)",
            "delta": self.delta.tolist(),
            "sd": self.sd.tolist(),
            "settings": self.settings,
        }


def press_correction(
    pairs,
    fem_images,
    sensor,
    reference: np.ndarray,
    pixel: float,
    ell_mm: float = PRESS_ELL_MM,
    prior_mm: float = PRESS_PRIOR_MM,
    form: float = PRESS_FORM,
    iterations: int = PRESS_ITERATIONS,
    var_smooth_px: float = VAR_SMOOTH_PX,
) -> PressCorrection:
    """The reference press's error ``δ(x)`` (mm) from phantoms of known difference image.

    A phantom's frames fix the ratio ``u_F / u_B = (c + s(w_b + Δw)) / (c + s(w_b))`` per camera pixel,
    which depends on the true background press ``w_b``: with a wrong ``w_b`` the recovered ``Δw`` (steps
    2-3 of the module docstring) is off by ``∂Δw/∂w_b δ``, where (dimensionless, at the phantom's FEM
    ``Δw = t / λ``, noise-free)::

        ∂Δw/∂w_b = (c + s(w_b + Δw)) / (c + s(w_b)) exp(Δw / w_sat) - 1
                 ≈ Δw (1 - 2a + c) / (w_sat (1 + c - a)),     a = exp(-w_b / w_sat), c = stray / level

    Gauss-Newton on ``δ`` (``iterations`` passes) with, per pass, the global factor ``λ`` (FEM ≈ λ
    recovered, :func:`fit_scale`) refitted first and ``δ`` taken as locally constant over a Gaussian
    kernel ``K*`` of ``ell_mm`` (normalised; ``n_eff = 4π (ell / pixel)²`` camera pixels).  Each phantom
    ``k`` gives a local estimate of the step with a variance from its frames' noise (independent per
    pixel: it averages down over the kernel) and from its model-form error (``form`` x its peak,
    correlated over the kernel: it does not), and the nine are pooled with the prior ``δ ~ N(0, τ²)``::

        a_k = K*(J_k² / var_k),   e_k = K*(J_k (t_k / λ - Δw_k) / var_k) / a_k                      (mm)
        u_k = 1 / (n_eff a_k) + (form max|t_k| / λ)² / K*(J_k²)                                   (mm²)
        δ ← (Σ_k (δ + e_k) / u_k) / (Σ_k 1 / u_k + 1 / τ²)        (camera pixels, then onto the FEM grid)

    ``J_k = ∂Δw_k/∂w_b``, ``var_k`` the variance of the recovered ``Δw_k`` from the frames' scatter,
    ``t_k`` the phantom's FEM difference image on the camera pixels, ``τ = prior_mm``; the returned
    ``sd`` is ``(Σ_k 1/u_k + 1/τ²)^(-1/2)``.  Where the phantoms' images are small (the footprint's rim)
    ``K*(J_k²)`` is small, the model-form part dominates and ``δ`` stays near 0.  A pattern of ``δ`` whose only effect is a uniform factor on every
    phantom's image costs ``δ`` its prior and ``λ`` nothing, so the uniform part (where a uniform
    amplitude error of the phantoms' FEM images also sits) stays in the global ``scale``, as before.
    ``pairs``: the phantoms' (lesion, background) stacks (DN); ``fem_images`` their FEM difference
    images (mm) on the grid of ``reference`` (mm, ``pixel`` mm)."""
    s = sensor.validate()
    ref = _reference(reference)
    if len(pairs) != len(fem_images) or not pairs:
        raise UserError("calibration", "need the frames and the FEM difference image of every phantom")
    if not (ell_mm >= 0 and prior_mm > 0 and form >= 0 and iterations >= 1):
        raise UserError("press correction", "needs ell_mm >= 0, prior_mm > 0, form >= 0, iterations >= 1")
    ny, nx = ref.shape
    r0, c0, n = s.window

    def on_camera(img):
        return s.deformation_on_frame(img, pixel)[r0 : r0 + n, c0 : c0 + n]

    means = [_window_means(_stack(F, "frames"), _stack(B, "background"), s, var_smooth_px) for F, B in pairs]
    fem = [np.asarray(f, float) for f in fem_images]
    T = [on_camera(f) for f in fem]
    P = backprojector(n, s.pixel_mm, ny, pixel)
    k_px = ell_mm / s.pixel_mm
    n_eff = 4.0 * np.pi * k_px**2 if k_px > 0 else 1.0

    def kernel(x):
        return ndimage.gaussian_filter(x, k_px, mode="reflect") if k_px > 0 else x

    delta = np.zeros_like(ref)
    for _ in range(iterations):
        wb = on_camera(ref + delta)
        invs = [_invert(*m, wb, s) for m in means]
        lam, _ = fit_scale([P @ v.dw @ P.T for v in invs], fem)
        num, den = np.zeros((n, n)), np.full((n, n), 1.0 / prior_mm**2)
        d_cam = on_camera(delta)
        for v, t in zip(invs, T):
            ok = ~v.saturated
            w = np.where(ok, 1.0 / np.maximum(v.var, 1e-24), 0.0)
            # the slope at the phantom's FEM image, not at its measured one: the latter carries the same
            # frame noise as the residual, and their product a bias of -var ∂J/∂Δw (errors in variables)
            J = np.where(ok, _press_slope(wb, t / lam, s), 0.0)
            a = kernel(w * J**2)  # the kernel's mean information (per camera pixel)
            e = kernel(w * J * (t / lam - v.dw)) / np.maximum(a, 1e-300)  # this phantom's local step
            u = 1.0 / np.maximum(n_eff * a, 1e-300) + (form * np.max(np.abs(t)) / lam) ** 2 / np.maximum(
                kernel(J**2), 1e-300
            )
            num += (d_cam + e) / u
            den += 1.0 / u
        delta = delta + P @ (num / den - d_cam) @ P.T
    sd = 1.0 / np.sqrt(den)
    settings = {"ell_mm": ell_mm, "prior_mm": prior_mm, "form": form, "iterations": iterations}
    return PressCorrection(delta, P @ sd @ P.T, float(lam), settings)
