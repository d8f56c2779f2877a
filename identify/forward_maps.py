"""The forward maps the physics fit (:mod:`elastimap.identify.fit`) fits through.

A forward map is ``(d mm, h mm, E kPa) -> SolveResult`` (or an image, :func:`image_of`).  The
solver's own (:func:`forward_map`) is the forward model on a mesh that is *morphed* to each (d, h)
(:mod:`elastimap.solver.morph`, :class:`ForwardMap`), so it is smooth in (d, h, E), or, without
morphing, a new gmsh mesh per call.  A fit uses three levels of it (:func:`fit_maps`): its own
level, the neighbouring level whose difference measures the map's discretisation error
(:func:`neighbour_level`) and, optionally, a finer level that defect-corrects it
(:func:`default_correct`).  Each morphed map morphs from the d-bin below (:func:`reference_below`).
One map per level and process (:func:`shared_map`): a morphed map keeps its reference meshes,
compiled forms and factorisation patterns between lesions.

The solver's morphing and solves (DOLFINx, gmsh) are imported only when a map is built or called.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from elastimap.errors import UserError
from elastimap.solver.params import MESH_LEVELS, SIZINGS, SolveParams, coarser, finer

from .intervals import CALIBRATED_FOR


def image_of(out) -> np.ndarray:
    """The difference image (mm) from what a forward map returns: an array, a tuple/list whose first
    item is the image, or an object with ``.image`` (e.g. :class:`elastimap.solver.params.SolveResult`)."""
    if hasattr(out, "image"):
        out = out.image
    elif isinstance(out, (tuple, list)):
        out = out[0]
    return np.asarray(out, dtype=float)


GEOMETRIES = ("morph", "remesh")


def neighbour_level(mesh: str) -> str:
    """The mesh level whose difference from ``mesh`` measures the map's discretisation error: the next
    coarser level (the next finer for the coarsest)."""
    if mesh not in MESH_LEVELS:
        raise UserError("mesh", f"must be one of {', '.join(MESH_LEVELS)} (got {mesh!r})")
    return coarser(mesh) or finer(mesh)


def default_geometry() -> str:
    """``morph`` where :mod:`elastimap.solver.morph` is installed, else ``remesh``."""
    try:
        return "morph" if importlib.util.find_spec("elastimap.solver.morph") else "remesh"
    except ImportError:
        return "remesh"


#: the fit levels whose maps (the fit's, its correcting and its model-error levels) morph from the
#: d-bin below (:func:`reference_below`): those the camera-frame benchmark measured.  A `tiny` fit
#: (tests only: 6 elements a diameter) keeps the nearest bin on all its maps: its two frame-fit tests
#: went from d +13 % to +27 % and lost their coverage with the bin below
BELOW_LEVELS = ("coarse", "default", "fine")
#: the CG tolerance of a fit's morphed maps (:class:`~elastimap.solver.reduction.Recycled`; the
#: solver's default is 1e-12): measured on `fine` and `default` at five points (d 5.5 and
#: 9 mm), it changes the difference image by at most 1.1e-7 of its peak (float32's own resolution;
#: the pixel noise of 30 frames is ~0.5 % of the peak) and saves 0.4–1.0 s a `fine` solve, 0.25–0.35 s
#: a `default` one (1e-7: up to 4.4e-6 of the peak; docs/history/camera.md, 'Calibrated intervals, a cheaper fit')
FIT_CG_RTOL = 1e-9


def reference_below(morphed, d: float, h: float):
    """The reference mesh a fit's map uses at (d, h) (:class:`ForwardMap` with ``below``): the d-bin
    whose reference diameter is the largest not above d (``d₀ ≤ d < √2 d₀``), its depth bin at (d₀, h)
    -- not the nearest bin of :meth:`elastimap.solver.morph.MorphedForward.reference_for`.  A morph
    that shrinks the inclusion costs far more accuracy than one that grows it: on the `fine` level,
    against gmsh meshes at the sample itself, three fresh design points were off by χ² 1 231 / 12 /
    0.3 grown by 8-12 % against 315 667 / 193 / 8.9 shrunk by 21-24 % (units of 0.1 µm a pixel), and
    a benchmark lesion (d 9.2 mm) by 108 grown 15 % against 1 074 shrunk 19 %; over 16 samples the
    bin below won 11, the one above 4 (those within ~10 % of it)
    (docs/history/camera.md, 'Where the valley pull comes from, and fit maps that morph from the bin below')."""
    from elastimap.solver.morph import D_ANCHOR, D_RATIO

    k = math.floor(math.log(float(d) / D_ANCHOR) / math.log(D_RATIO) + 1e-9)
    return morphed.reference_for(D_ANCHOR * D_RATIO**k, float(h))


class ForwardMap:
    """``(d, h, E) -> SolveResult`` on morphed meshes, each (d, h) on the reference mesh of
    :func:`reference_below` (``below``) or of the nearest bin; ``pin(d, h)`` gives the same map on
    the reference mesh of (d, h) for every call (one smooth map over a fit's pass, see
    :mod:`elastimap.solver.morph`), with the reference press (E_inc = E_tissue) taken to first order
    in (d, h) about the pinned point where the problem is linear (``linearise_at``: one linear solve
    per evaluation instead of two when d or h move; equal to the unpinned map at that point);
    ``key`` names the pinned reference and centre (None: each call's own bin, reference press
    re-solved).  ``tangent(d, h, E)`` also returns the image's exact derivative."""

    def __init__(self, morphed, reference=None, centre: tuple[float, float] | None = None, below: bool = True):
        self.morphed, self.reference, self.centre, self.below = morphed, reference, centre, below
        self.key = None if reference is None else (reference.d0, reference.h0, centre)

    def _reference(self, d, h):
        """The pinned reference, else that of (d, h): the bin below (``below``) or the nearest."""
        if self.reference is not None:
            return self.reference
        return reference_below(self.morphed, d, h) if self.below else self.morphed.reference_for(float(d), float(h))

    def __call__(self, d, h, E):
        return self.morphed.solve(
            float(d), float(h), float(E), reference=self._reference(d, h), linearise_at=self.centre
        )

    @property
    def has_tangent(self) -> bool:
        return bool(getattr(self.morphed, "has_tangent", False))

    @property
    def E_tissue(self) -> float:
        """The tissue's modulus (kPa) of the map's template (the fit's E coordinate uses it)."""
        return float(self.morphed.template.tissue.E)

    def tangent(self, d, h, E):
        """``(result, J)``: the solve and its image's exact derivative, ``J`` ``(3, ny, nx)`` =
        ∂image/∂(d mm, h mm, E kPa) (:meth:`elastimap.solver.morph.MorphedForward.solve_tangent`)."""
        return self.morphed.solve_tangent(
            float(d), float(h), float(E), reference=self._reference(d, h), linearise_at=self.centre
        )

    def pin(self, d: float, h: float) -> ForwardMap:
        d, h = float(d), float(h)
        return ForwardMap(self.morphed, self._reference(d, h), (d, h) if self.has_tangent else None, self.below)

    def pin_exact(self, d: float, h: float) -> ForwardMap:
        """:meth:`pin` with the reference press re-solved at every (d, h) (no linearisation): the
        map a model error is measured against, so that the measured difference contains the
        linearisation's error too."""
        return ForwardMap(self.morphed, self._reference(float(d), float(h)), below=self.below)


def forward_map(
    mesh: str = "coarse",
    geometry: str | None = None,
    template=None,
    sizing: str | None = None,
    below: bool | None = None,
) -> Callable:
    """``forward(d, h, E) -> SolveResult`` of the forward model (tied probe, quarter model, default
    loading, or ``template``'s) at mesh level ``mesh`` with element sizing ``sizing`` (``"fixed"`` or
    ``"by_d"``, :class:`elastimap.solver.params.Discretisation`; None: the template's).

    ``geometry="morph"``: one mesh per level, morphed smoothly to each (d, h)
    (:mod:`elastimap.solver.morph`; built on first use and reused); ``"remesh"``: a new mesh per
    call (:func:`elastimap.solver.solve`; jitters in d and h, so central differences are unreliable).
    ``below``: a morphed map's reference is the d-bin below (:func:`reference_below`) or the nearest;
    None: below for the levels of :data:`BELOW_LEVELS` (a fit should pass its fit level's choice to all
    its maps)."""
    geometry = geometry or default_geometry()
    if geometry not in GEOMETRIES:
        raise UserError("geometry", f"must be one of {', '.join(GEOMETRIES)} (got {geometry!r})")
    neighbour_level(mesh)  # checks the level
    if sizing is not None and sizing not in SIZINGS:
        raise UserError("sizing", f"must be one of {', '.join(SIZINGS)} (got {sizing!r})")
    base = template or SolveParams()
    base = base.replace(disc=dataclasses.replace(base.disc, mesh=mesh, sizing=sizing or base.disc.sizing))
    if geometry == "morph":
        from elastimap.solver.morph import MorphedForward

        return ForwardMap(
            MorphedForward(base, cg_rtol=FIT_CG_RTOL), below=mesh in BELOW_LEVELS if below is None else bool(below)
        )

    def forward(d, h, E):
        from elastimap.solver import solve

        return solve(base.with_inclusion(d=float(d), h=float(h), E=float(E)))

    return forward


def check_correct(mesh: str, correct: str | None) -> None:
    """``correct`` (the level a fit's map is defect-corrected by) must be None or a level finer than
    ``mesh``; raises :class:`~elastimap.errors.UserError` naming ``correct`` otherwise."""
    neighbour_level(mesh)  # checks the level
    if correct is not None and (correct not in MESH_LEVELS or MESH_LEVELS.index(correct) <= MESH_LEVELS.index(mesh)):
        finer = ", ".join(MESH_LEVELS[MESH_LEVELS.index(mesh) + 1 :]) or "none"
        raise UserError("correct", f"must be a mesh level finer than {mesh}: {finer} (got {correct!r})")


#: the level that defect-corrects a fit's map by default (:func:`default_correct`): the benchmarked
#: configuration, `coarse` corrected by `fine` (docs/camera.md, 'Inference')
DEFAULT_CORRECT = {"coarse": "fine"}


def default_correct(mesh: str) -> str | None:
    """The level that corrects a fit's map at ``mesh`` unless told otherwise: ``fine`` for ``coarse``
    (what the camera-frame benchmark measured), none for the other levels (``tiny`` is for tests,
    ``default`` and finer are themselves the finer maps)."""
    neighbour_level(mesh)  # checks the level
    return DEFAULT_CORRECT.get(mesh)


def default_intervals(mesh: str, correct: str | None, geometry: str | None = None) -> str:
    """The intervals a fit on ``mesh`` corrected by ``correct`` (``geometry``: None, the default)
    reports unless told otherwise: ``"calibrated"`` for the configuration the scales of
    :mod:`elastimap.identify.intervals` were calibrated on (:data:`elastimap.identify.intervals.CALIBRATED_FOR`,
    morphed maps), else the Gauss–Newton ones."""
    morphed = (geometry or default_geometry()) == "morph"
    return "calibrated" if morphed and (mesh, correct) == CALIBRATED_FOR else "gauss"


@dataclass(frozen=True)
class FitMaps:
    """A fit's maps built from mesh levels (:func:`fit_maps`) and the intervals it reports by default."""

    forward: Callable
    forward_alt: Callable
    forward_fine: Callable | None
    intervals: str


def sensor_template(sensor=None) -> SolveParams | None:
    """The solve parameters of ``sensor``'s mechanics (:func:`elastimap.solver.params.from_sensor`:
    probe layers, footprint, slab, loading, interface), or None for the paper's (``SolveParams()``)
    and for ``sensor`` None."""
    if sensor is None:
        return None
    from elastimap.solver.params import from_sensor

    p = from_sensor(sensor)
    return None if p == SolveParams() else p


def fit_maps(mesh: str = "coarse", correct: str | None = None, geometry: str | None = None, sensor=None) -> FitMaps:
    """The process's maps of a fit at ``mesh``: the fit's map, the neighbouring level of the level it
    stands for (``correct`` or ``mesh``; the model error) and, with ``correct`` (a finer level), the
    correcting map -- all with the fit level's bin rule (:data:`BELOW_LEVELS`) -- and
    :func:`default_intervals`.  What :func:`elastimap.identify.fit.fit_forward` and ``infer --refine`` fit with.

    ``sensor`` (:class:`elastimap.sensor.Sensor`; None: the paper's): the maps press with its probe,
    slab, loading and interface (:func:`sensor_template`).  The calibrated intervals were calibrated
    on the paper's sensor, so another sensor's fit reports the Gauss–Newton ones
    (docs/howto/your-own-sensor.md, "Infer from lesion frames")."""
    check_correct(mesh, correct)
    below = mesh in BELOW_LEVELS  # one bin rule for all the fit's maps
    template = sensor_template(sensor)
    return FitMaps(
        shared_map(mesh, geometry, below=below, template=template),
        shared_map(neighbour_level(correct or mesh), geometry, below=below, template=template),
        shared_map(correct, geometry, below=below, template=template) if correct else None,
        default_intervals(mesh, correct, geometry) if template is None else "gauss",
    )


_SHARED_MAPS: dict = {}


def shared_map(
    mesh: str,
    geometry: str | None = None,
    sizing: str | None = None,
    below: bool | None = None,
    template: SolveParams | None = None,
) -> Callable:
    """The process's :func:`forward_map` for ``mesh``, ``geometry``, ``sizing`` and ``template``
    (None: the paper's sensor; built once: a morphed map keeps its reference meshes, compiled forms
    and factorisation patterns between lesions)."""
    below = mesh in BELOW_LEVELS if below is None else bool(below)
    k = (mesh, geometry or default_geometry(), sizing or "fixed", None if template is None else repr(template))
    if k not in _SHARED_MAPS:  # one per process: a morphed map keeps its mesh and forms
        _SHARED_MAPS[k] = forward_map(mesh, geometry, template=template, sizing=sizing)
    f = _SHARED_MAPS[k]
    if isinstance(f, ForwardMap) and f.below != below:  # the same mesh and forms, the other bin rule
        return ForwardMap(f.morphed, below=below)
    return f
