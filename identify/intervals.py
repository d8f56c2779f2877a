r"""Calibrated 95 % intervals of the physics fit (:class:`elastimap.identify.fit.ImageFit`): the
Gauss–Newton interval with its half-width scaled per class of the fit's own relative standard
deviation and per stratum of the estimate (near the slab's base or not), the scales set by
split-conformal prediction on benchmark lesions.

Why.  On the SYNTHETIC camera-frame benchmark (world `fine` sized by d, drifting camera, 30 frames;
docs/camera.md, 'Inference') the Gauss–Newton standard deviation ``sd`` misstates the spread of the fit's
errors, and how depends on how well the image tells the parameter and on where the inclusion lies.
Over 1317 lesions of seeds 2027–2041 the 95 % quantile of ``|θ̂ − θ| / sd`` for d is about 2.4 where
the fit's relative sd is under 3 % and the inclusion is far from the base, 8.7 where it is near the
base (the discretisation's pull along the d–E valley: a bias the noise-only width does not hold), and
0.6 where the relative sd is over 30 % (there the fit starts at the network's estimate and stops once
χ² is flat, inside the box, so it moves less along the valley than the likelihood's width).  One
factor cannot mend both ends.

The interval.  For each parameter q the class of the fit's relative sd ``r_q`` (d and h: sd/θ; E:
sd of ln E) among :data:`CLASS_EDGES` -- half-decades, the product's 10 % threshold one of their
edges -- and the estimate's stratum (:func:`near_base`: does the estimated inclusion's bottom lie
within :data:`NEAR_BASE_MM` of the slab's base?) pick a scale ``k_q`` (:data:`SCALES`), and the
interval is

    θ̂_q ± 1.96 k_q sd_q      (d mm, h mm; for E in the fit's coordinate e, mapped back)

clipped to the design box, as the Gauss–Newton one (``k = 1``).

Why the second axis (docs/history/camera.md, 'A second axis for the intervals: near the slab's
base or not').  Large stiff inclusions close to the fixed base have d and E errors of up to 13–14 sd at a small relative sd: there the world's and the fit's
discretisations differ in a way that moves the estimate along the d–E valley.  Pooled with the rest
of their class they set its scale, so the interval over-covered elsewhere (E's region: 80 of 80) and
still under-covered them (leave one seed out: d 91.8, h 89.6, E 92.3 % of 183).  The stratum is
decided from the estimate alone, so it is known at inference.

The scales (Mondrian split-conformal prediction: Vovk, Gammerman & Shafer, *Algorithmic Learning in a
Random World*, Springer 2005, §4.5; Lei et al., J. Am. Stat. Assoc. 113 (2018) 1094).  The
non-conformity score of a calibration lesion is ``s = |x̂_q − x_q| / sd_q`` (``x`` the fit coordinate:
d, h, e); within a cell (class × stratum) of n scores ``k_q`` = :func:`conformal_quantile` (the
⌈(n + 1) 0.95⌉-th smallest) / 1.96.  For a lesion exchangeable with the calibration lesions -- the
same world, camera, fit and design -- the interval then holds the truth with probability at least
95 % within each cell.  A cell with fewer than :data:`MIN_CLASS` lesions takes its class's scale over
both strata, and a class with fewer than that keeps ``k = 1``.  A real sensor is *not*
exchangeable with the synthetic world: recompute the scales from its own phantoms
(``python -m elastimap.workflows.studies.interval_calibration FOLDERS --install``, which writes them).

The scales and the fit they were calibrated for are data, read from :data:`INTERVALS_FILE`
(``identify/maps/intervals.json``, with its provenance: date, commit, folders, seeds, lesion
counts, method), which that study writes; nothing edits them in code.

Plain numbers in and out; no DOLFINx.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np

from elastimap.dataset.schema import TARGETS, THICKNESS
from elastimap.errors import UserError

#: the 97.5 % point of the standard normal (a 95 % two-sided interval is ±Z95 sd)
Z95 = 1.959963984540054
#: class edges of the fit's relative standard deviation (d, h: sd/θ; E: sd of ln E): the classes are
#: (0, 0.03], (0.03, 0.1], (0.1, 0.3] and above 0.3
CLASS_EDGES = (0.03, 0.10, 0.30)
#: the interval's coverage the scales are set for
LEVEL = 0.95
#: fewer calibration lesions than this in a cell (class × stratum): it takes its class's scale over
#: both strata, and a class with fewer keeps 1 (the conformal quantile at 95 % needs at least 19)
MIN_CLASS = 19
#: the estimate is "near the base" when its inclusion's bottom lies closer than this to the slab's
#: base (mm; the design keeps at least 2, ``solver.params.depth_range``'s floor)
NEAR_BASE_MM = 3.0
#: the strata of :func:`near_base`, in the order of each parameter's rows in :data:`SCALES`
STRATA = ("far", "near")
PARAMS = TARGETS  # (d, h, E): the rows of SCALES
#: the calibrated scales, with their provenance (written by
#: ``python -m elastimap.workflows.studies.interval_calibration --install``)
INTERVALS_FILE = os.path.join(os.path.dirname(__file__), "maps", "intervals.json")


def load_scales(path: str | os.PathLike = INTERVALS_FILE) -> dict:
    """The calibration file at ``path``: ``scales`` (per parameter the two strata's four class
    scales, as tuples), ``calibrated_for`` (fit level, correcting level) and ``provenance``.  Refuses
    a file made with other class edges, strata or base distance than this module's."""
    try:
        with open(path) as fh:
            z = json.load(fh)
        scales = {q: tuple(tuple(float(v) for v in row) for row in z["scales"][q]) for q in PARAMS}
        cal = z["calibrated_for"]
        calibrated_for = (str(cal["mesh"]), None if cal["correct"] is None else str(cal["correct"]))
        same = (
            tuple(z["class_edges"]) == CLASS_EDGES
            and tuple(z["strata"]) == STRATA
            and float(z["near_base_mm"]) == NEAR_BASE_MM
        )
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UserError("intervals", f"{path}: not an interval calibration ({exc})") from None
    shapes = {len(scales[q]) for q in PARAMS} | {len(r) for q in PARAMS for r in scales[q]}
    if not same or shapes - {len(STRATA), len(CLASS_EDGES) + 1} or len(scales["d"]) != len(STRATA):
        raise UserError("intervals", f"{path}: made with other classes or strata than {__name__}")
    return {"scales": scales, "calibrated_for": calibrated_for, "provenance": z.get("provenance", {})}


def write_scales(path: str | os.PathLike, scales: dict, calibrated_for: tuple, provenance: dict) -> None:
    """Write a calibration file :func:`load_scales` reads, atomically (a temporary file beside
    ``path``, then renamed over it): ``scales`` per parameter (strata x classes), the fit it was
    calibrated for (fit level, correcting level) and its ``provenance``."""
    doc = {
        "calibrated_for": {"mesh": calibrated_for[0], "correct": calibrated_for[1]},
        "class_edges": list(CLASS_EDGES),
        "level": LEVEL,
        "min_class": MIN_CLASS,
        "near_base_mm": NEAR_BASE_MM,
        "scales": {q: [[float(v) for v in row] for row in scales[q]] for q in PARAMS},
        "strata": list(STRATA),
        "provenance": provenance,
    }
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as fh:
        json.dump(doc, fh, indent=2)
        fh.write("\n")
    os.replace(tmp, path)
    load_scales(path)  # what was written reads back


_CALIBRATION = load_scales()
#: the scales per parameter, stratum (:data:`STRATA`) and class (:data:`CLASS_EDGES`), read from
#: :data:`INTERVALS_FILE` (SYNTHETIC; its ``provenance`` says which benchmark lesions made them)
SCALES = _CALIBRATION["scales"]
#: the fit the scales were calibrated on: (fit level, correcting level) of
#: :func:`elastimap.identify.fit.fit_forward` (morphed maps, the fixed sizing, the d-bin below,
#: model error against `default`); other fits report the Gauss–Newton interval by default
#: (:func:`elastimap.identify.forward_maps.default_intervals`)
CALIBRATED_FOR = _CALIBRATION["calibrated_for"]


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


def near_base(theta, thickness: float = THICKNESS) -> np.ndarray:
    """Whether each estimate ``theta`` ((d, h, E) or (n, 3); mm) puts the inclusion's bottom closer
    than :data:`NEAR_BASE_MM` to the slab's base: ``thickness − h − d/2 < NEAR_BASE_MM``."""
    t = np.asarray(theta, dtype=float)
    if t.shape[-1:] != (3,):
        raise UserError("theta", f"need estimates (d, h, E) in the last axis, got shape {t.shape}")
    return thickness - t[..., 1] - t[..., 0] / 2 < NEAR_BASE_MM


def scales_for(relstd, theta, scales: dict | None = None, thickness: float = THICKNESS) -> np.ndarray:
    """The interval scales ``k`` of (d, h, E) for a fit whose relative standard deviations are
    ``relstd`` (3 numbers: sd_d/d, sd_h/h, sd of ln E) at the estimate ``theta`` (d, h, E);
    ``scales``: per parameter the two strata's four class scales (default :data:`SCALES`).  A
    relative sd that is not finite keeps 1."""
    table = SCALES if scales is None else scales
    r = np.asarray(relstd, dtype=float)
    if r.shape != (3,):
        raise UserError("relstd", f"need three relative standard deviations (d, h, E), got shape {r.shape}")
    stratum = int(near_base(theta, thickness))
    out = np.ones(3)
    for j, q in enumerate(PARAMS):
        if np.isfinite(r[j]):
            out[j] = float(table[q][stratum][int(class_of(r[j]))])
    return out


def calibrate(
    relstd, scores, near=None, level: float = LEVEL, min_class: int = MIN_CLASS
) -> tuple[np.ndarray, np.ndarray]:
    """Scales for one parameter from calibration lesions: ``relstd`` (n,) the fits' relative sds,
    ``scores`` (n,) ``|x̂ − x| / sd``, ``near`` (n,) their :func:`near_base` (None: all far).  Returns
    (the scales, the cell sizes), each (2, 4): stratum (:data:`STRATA`) × class.  A cell with fewer
    than ``min_class`` lesions gets its class's scale over both strata; a class with fewer than that, 1."""
    r, s = np.asarray(relstd, dtype=float), np.asarray(scores, dtype=float)
    nb = np.zeros(r.shape, dtype=bool) if near is None else np.asarray(near, dtype=bool)
    if r.shape != s.shape or r.shape != nb.shape or r.ndim != 1:
        raise UserError("scores", f"need one score and stratum per relative sd (got {r.shape}, {s.shape}, {nb.shape})")

    def scale(sc: np.ndarray) -> float:
        q = conformal_quantile(sc, level) if sc.size >= min_class else math.nan
        return q / Z95 if math.isfinite(q) else math.nan

    cls = class_of(r)
    nc = len(CLASS_EDGES) + 1
    k, n = np.ones((len(STRATA), nc)), np.zeros((len(STRATA), nc), dtype=int)
    for c in range(nc):
        pooled = scale(s[cls == c])
        for i in range(len(STRATA)):
            sc = s[(cls == c) & (nb == bool(i))]
            n[i, c] = sc.size
            own = scale(sc)
            k[i, c] = own if math.isfinite(own) else (pooled if math.isfinite(pooled) else 1.0)
    return k, n
