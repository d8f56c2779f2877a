r"""Calibrated 95 % intervals of the physics fit (:func:`elastimap.identify.refine.fit_image`): the
Gauss–Newton interval with its half-width scaled per class of the fit's own relative standard
deviation, the scales set by split-conformal prediction on benchmark lesions.

Why.  On the SYNTHETIC camera-frame benchmark (world `fine` sized by d, drifting camera, 30 frames;
docs/camera.md 4l, 4m) the Gauss–Newton standard deviation ``sd`` misstates the spread of the fit's
errors, and how depends on how well the image tells the parameter.  Over 1007 lesions of seeds 2027,
2029–2038 the 95 % quantile of ``|θ̂ − θ| / sd`` for d is about 3.7 where the fit's relative sd is under
3 % (the discretisation's pull along the d–E valley: a bias the noise-only width does not hold) and
0.5 where it is over 30 % (there the fit starts at the network's estimate and stops once χ² is flat,
inside the box, so it moves less along the valley than the likelihood's width); for E (in the fit's
coordinate ``e``) it is 6–8 where its sd is under 10 %.  One factor cannot mend both ends.

The interval.  For each parameter q the class of the fit's relative sd ``r_q`` (d and h: sd/θ; E:
sd of ln E) among :data:`CLASS_EDGES` -- half-decades, the product's 10 % threshold one of their
edges -- picks a scale ``k_q`` (:data:`SCALES`), and the interval is

    θ̂_q ± 1.96 k_q sd_q      (d mm, h mm; for E in the fit's coordinate e, mapped back)

clipped to the design box, as the Gauss–Newton one (``k = 1``).

The scales (Mondrian split-conformal prediction: Vovk, Gammerman & Shafer, *Algorithmic Learning in a
Random World*, Springer 2005, §4.5; Lei et al., J. Am. Stat. Assoc. 113 (2018) 1094).  The
non-conformity score of a calibration lesion is ``s = |x̂_q − x_q| / sd_q`` (``x`` the fit coordinate:
d, h, e); within a class of n scores ``k_q`` = :func:`conformal_quantile` (the ⌈(n + 1) 0.95⌉-th
smallest) / 1.96.  For a lesion exchangeable with the calibration lesions -- the same world, camera,
fit and design -- the interval then holds the truth with probability at least 95 % within each class.
A class with fewer than :data:`MIN_CLASS` lesions keeps ``k = 1``.  Known limit (docs/camera.md 4m):
the classes do not separate large stiff inclusions close to the slab's base, whose d and E errors
reach 13–14 sd at a small relative sd, from the rest; they set the first classes' scales, so
elsewhere there (E's region: large soft inclusions) the interval is wider than it needs to be.  A real sensor is *not*
exchangeable with the synthetic world: recompute the scales from its own phantoms
(``python -m elastimap.workflows.studies.interval_calibration``, which made :data:`SCALES`).

Plain numbers in and out; no DOLFINx.
"""

from __future__ import annotations

import math

import numpy as np

from elastimap.dataset.schema import TARGETS
from elastimap.errors import UserError

#: the 97.5 % point of the standard normal (a 95 % two-sided interval is ±Z95 sd)
Z95 = 1.959963984540054
#: class edges of the fit's relative standard deviation (d, h: sd/θ; E: sd of ln E): the classes are
#: (0, 0.03], (0.03, 0.1], (0.1, 0.3] and above 0.3
CLASS_EDGES = (0.03, 0.10, 0.30)
#: the interval's coverage the scales are set for
LEVEL = 0.95
#: fewer calibration lesions than this in a class: its scale stays 1 (the conformal quantile at 95 %
#: needs at least 19)
MIN_CLASS = 19
#: the scales per parameter and class (:data:`CLASS_EDGES`), from
#: ``python -m elastimap.workflows.studies.interval_calibration runs/fb27 runs/fb29 ... runs/fb38``
#: (SYNTHETIC: 1007 lesions with a signal, seeds 2027 and 2029–2038, world `fine` by_d, drifting camera,
#: 30 frames, fit `coarse` corrected by `fine`; docs/camera.md 4l, 4m); a class that had fewer than
#: MIN_CLASS lesions is 1.0
SCALES = {
    "d": (1.9, 1.049, 0.608, 0.261),
    "h": (0.99, 0.706, 1.0, 1.0),
    "E": (3.189, 4.191, 1.661, 0.615),
}
PARAMS = TARGETS  # (d, h, E): the rows of SCALES
#: the fit the scales were calibrated on: (fit level, correcting level) of
#: :func:`elastimap.identify.refine.fit_forward` (morphed maps, the fixed sizing, the d-bin below,
#: model error against `default`); other fits report the Gauss–Newton interval by default
#: (:func:`elastimap.identify.refine.default_intervals`)
CALIBRATED_FOR = ("coarse", "fine")


def conformal_quantile(scores, level: float = LEVEL) -> float:
    """The split-conformal quantile of ``scores`` (n finite non-negative numbers): the
    ⌈(n + 1) level⌉-th smallest; NaN when ``n`` is too small for it (⌈(n + 1) level⌉ > n)."""
    s = np.sort(np.asarray(scores, dtype=float).ravel())
    if not np.isfinite(s).all() or (s < 0).any():
        raise UserError("scores", "must be finite and non-negative")
    if not 0 < level < 1:
        raise UserError("level", f"must be in (0, 1) (got {level})")
    k = math.ceil((s.size + 1) * level)
    return float(s[k - 1]) if k <= s.size else math.nan


def class_of(relstd) -> np.ndarray:
    """The class index (0–3) of each relative standard deviation (:data:`CLASS_EDGES`, right-closed)."""
    return np.searchsorted(np.asarray(CLASS_EDGES), np.asarray(relstd, dtype=float), side="left")


def scales_for(relstd, scales: dict | None = None) -> np.ndarray:
    """The interval scales ``k`` of (d, h, E) for a fit whose relative standard deviations are
    ``relstd`` (3 numbers: sd_d/d, sd_h/h, sd of ln E); ``scales``: per parameter the four class
    scales (default :data:`SCALES`).  A relative sd that is not finite keeps 1."""
    table = SCALES if scales is None else scales
    r = np.asarray(relstd, dtype=float)
    if r.shape != (3,):
        raise UserError("relstd", f"need three relative standard deviations (d, h, E), got shape {r.shape}")
    out = np.ones(3)
    for j, q in enumerate(PARAMS):
        if np.isfinite(r[j]):
            out[j] = float(table[q][int(class_of(r[j]))])
    return out


def calibrate(relstd, scores, level: float = LEVEL, min_class: int = MIN_CLASS) -> tuple[np.ndarray, np.ndarray]:
    """Scales for one parameter from calibration lesions: ``relstd`` (n,) the fits' relative sds,
    ``scores`` (n,) ``|x̂ − x| / sd``.  Returns (the four class scales, the four class sizes); a class
    with fewer than ``min_class`` lesions gets 1."""
    r, s = np.asarray(relstd, dtype=float), np.asarray(scores, dtype=float)
    if r.shape != s.shape or r.ndim != 1:
        raise UserError("scores", f"need one score per relative sd (got {r.shape} and {s.shape})")
    cls = class_of(r)
    k, n = np.ones(len(CLASS_EDGES) + 1), np.zeros(len(CLASS_EDGES) + 1, dtype=int)
    for c in range(k.size):
        sc = s[cls == c]
        n[c] = sc.size
        if sc.size >= min_class:
            q = conformal_quantile(sc, level)
            if math.isfinite(q):
                k[c] = q / Z95
    return k, n
