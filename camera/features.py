"""Camera features (O1, O2, O3) from raw frames (paper sections 3.2-3.3).

Pipeline, for a lesion with frames ``F_1..F_n`` and background frames
``B_1..B_m`` (the same press with no inclusion, or the nearest clean press):

1. **temporal denoising**: mean over frames, ``F = mean_i F_i`` and
   ``B = mean_j B_j`` (in DN);  the dark offset cancels in the difference;
2. **background handling**: difference image ``D = (F - B) / full_scale``
   (fraction of full scale, "FS"), cropped to the footprint window;
3. **spatial denoising**: Gaussian filter of ``smooth_px`` camera pixels
   (applied to ``D``; reflect at the window border);
4. **features**, with the same definitions as the FEM (:mod:`elastimap.solver.image`):

   * O1 = max D                                        (FS)
   * O2 = sum D * pixel_mm^2   (integral over the footprint, FS mm^2)
   * O3 = area where D > ``threshold`` (FS), sub-pixel by bilinear
     upsampling, in mm^2 via the pixel scale ``pixel_mm``.

``combine='mean-image'`` (default) averages the frames before the features;
``combine='mean-features'`` computes the features of every frame against the
mean background and averages them (the paper averages per-image estimates;
O1 of single frames is biased upwards by noise, so the default averages
first).  Either way the per-frame scatter is reported.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from elastimap.constraints import check_range
from elastimap.errors import UserError
from elastimap.solver.image import features as image_features

COMBINE = ("mean-image", "mean-features")


@dataclass(frozen=True)
class FeatureSettings:
    """How camera features are computed (stored in the calibration file)."""

    threshold: float = 0.0012  # FS: O3 counts pixels whose difference exceeds this (~ the FEM 1e-3 mm, see docs)
    smooth_px: float = 1.5  # Gaussian sigma in camera pixels (0 = none)
    supersample: int = 8
    combine: str = "mean-image"

    def validate(self) -> FeatureSettings:
        check_range("threshold", self.threshold, 0, 1)  # a fraction of full scale
        check_range("smooth_px", self.smooth_px, 0, 20)
        if not (1 <= self.supersample <= 32):
            raise UserError("supersample", f"must be in [1, 32] (got {self.supersample})")
        if self.combine not in COMBINE:
            raise UserError("combine", f"must be one of {', '.join(COMBINE)} (got {self.combine!r})")
        return self

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> FeatureSettings:
        if not isinstance(d, dict):
            raise UserError("feature_settings", f"must be a JSON object (got {type(d).__name__})")
        known = {f.name for f in dataclasses.fields(cls)}
        try:
            return cls(**{k: v for k, v in d.items() if k in known}).validate()
        except (TypeError, ValueError) as exc:
            if isinstance(exc, UserError):
                raise
            raise UserError("feature_settings", f"a setting has the wrong type ({exc})") from None


@dataclass
class CameraFeatures:
    O1: float
    O2: float
    O3: float
    frame_sd: tuple[float, float, float]  # scatter of single-frame features (sd); 0 for one frame
    n_frames: int
    n_background: int
    difference: np.ndarray  # the denoised difference image over the window (FS)

    @property
    def values(self) -> np.ndarray:
        return np.array([self.O1, self.O2, self.O3])

    def to_dict(self) -> dict:
        return {
            "O1": self.O1,
            "O2": self.O2,
            "O3": self.O3,
            "O1_frame_sd": self.frame_sd[0],
            "O2_frame_sd": self.frame_sd[1],
            "O3_frame_sd": self.frame_sd[2],
            "n_frames": self.n_frames,
            "n_background": self.n_background,
        }


UNITS = {"O1": "FS", "O2": "FS mm^2", "O3": "mm^2"}


def _as_stack(a: np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3 or a.shape[0] == 0 or a.shape[1] == 0 or a.shape[2] == 0:
        raise UserError(what, f"must be a stack of 2-D frames (got shape {a.shape})")
    if not np.all(np.isfinite(a)):
        raise UserError(what, "contains NaN or inf")
    return a


def _difference_features(D: np.ndarray, pixel_mm: float, s: FeatureSettings) -> np.ndarray:
    if s.smooth_px > 0:
        D = ndimage.gaussian_filter(D, s.smooth_px, mode="reflect")
    o1, o2, o3 = image_features(D, pixel_mm, s.threshold, s.supersample)
    return np.array([o1, o2 * pixel_mm**2, o3]), D


def camera_features(
    frames: np.ndarray,
    background: np.ndarray,
    full_scale: float,
    window: tuple[int, int, int],
    pixel_mm: float,
    settings: FeatureSettings | None = None,
) -> CameraFeatures:
    """Features of a lesion from its frames and background frames (arrays in DN).

    ``window`` is (row0, col0, n): the footprint's pixels; ``pixel_mm`` their side on the probe.
    """
    s = (settings or FeatureSettings()).validate()
    F = _as_stack(frames, "frames")
    B = _as_stack(background, "background")
    if F.shape[1:] != B.shape[1:]:
        raise UserError(
            "background",
            f"frame size {F.shape[2]}x{F.shape[1]} differs from the background's {B.shape[2]}x{B.shape[1]}",
        )
    r0, c0, n = window
    if r0 < 0 or c0 < 0 or r0 + n > F.shape[1] or c0 + n > F.shape[2]:
        raise UserError("window", f"footprint window {window} does not fit a {F.shape[2]}x{F.shape[1]} frame")
    check_range("full_scale", full_scale, 0, lo_open=True)
    crop = (slice(None), slice(r0, r0 + n), slice(c0, c0 + n))
    F, B = F[crop] / full_scale, B[crop] / full_scale
    Bm = B.mean(axis=0)
    per = np.array([_difference_features(f - Bm, pixel_mm, s)[0] for f in F]) if F.shape[0] > 1 else None
    if s.combine == "mean-image" or F.shape[0] == 1:
        vals, Dm = _difference_features(F.mean(axis=0) - Bm, pixel_mm, s)
    else:
        vals = per.mean(axis=0)
        Dm = _difference_features(F.mean(axis=0) - Bm, pixel_mm, s)[1]
    sd = tuple(float(x) for x in per.std(axis=0, ddof=1)) if per is not None else (0.0, 0.0, 0.0)
    if vals[0] <= s.threshold:
        warnings.warn(
            f"no deformation above the O3 threshold ({s.threshold:g} FS): no inclusion visible against the background",
            stacklevel=2,
        )
    return CameraFeatures(float(vals[0]), float(vals[1]), float(vals[2]), sd, F.shape[0], B.shape[0], Dm)


def features_from_files(
    images: list[str],
    background: list[str],
    model=None,
    settings: FeatureSettings | None = None,
    params: tuple[str, str] = ("images", "background"),
) -> CameraFeatures:
    """Camera features of a lesion from image files.

    ``model`` (a :class:`elastimap.camera.optics.SensorModel`) gives the footprint window
    and pixel scale; by default the synthetic camera's (the frame size must
    match it).  Raises :class:`UserError` naming the bad file and the parameter it came from
    (``params``: where the lesion and the background frames were given).
    """
    from .frames import read_stack
    from .optics import SensorModel

    model = model or SensorModel()
    shape, window = model.shape, model.window
    F, fs1 = read_stack(images, shape, window, params[0], bits=model.bits)
    B, fs2 = read_stack(background, shape, window, params[1], bits=model.bits)
    if fs1 != fs2:
        raise UserError(params[1], f"{background[0]}: bit depth differs from the lesion frames ({images[0]})")
    return camera_features(F, B, fs1, window, model.pixel_mm, settings)
