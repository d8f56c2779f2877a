"""Inputs and outputs of one forward solve, as plain dataclasses.

Units everywhere: lengths in mm, moduli and pressures in kPa, forces in mN
(kPa * mm^2 = mN).  Coordinates: x, y in the tissue surface plane with the
probe centred on the origin, z upward, the chest wall at z = 0 and the tissue
surface at z = thickness.

All validation lives here so that every entry point (Python API, CLI, sweep)
rejects the same bad input with the same one-line :class:`UserError`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from elastimap.constraints import Interval, Options, check_range, validate_params
from elastimap.errors import UserError
from elastimap.sensor import WALL_COMPLIANCE_MAX, InterfaceSpec, Layer, LoadingSpec, ProbeSpec, SlabSpec

if TYPE_CHECKING:  # numpy is not imported with the parameters (the `solve` command pins BLAS first)
    import numpy as np

MESH_LEVELS = ("tiny", "coarse", "default", "fine", "finer")


def finer(level: str) -> str | None:
    """The mesh level one step finer than ``level`` (None for the finest)."""
    i = MESH_LEVELS.index(level)
    return MESH_LEVELS[i + 1] if i + 1 < len(MESH_LEVELS) else None


def coarser(level: str) -> str | None:
    """The mesh level one step coarser than ``level`` (None for the coarsest)."""
    i = MESH_LEVELS.index(level)
    return MESH_LEVELS[i - 1] if i > 0 else None


INTERFACES = ("tied", "contact", "bonded")
SYMMETRIES = ("quarter", "full")
#: how the mesh of a sample is made: gmsh for every (d, h), or a reference mesh morphed to (d, h)
GEOMETRIES = ("remesh", "morph")
#: how the element size near the inclusion is chosen (solver/geometry.py): the first sweeps' rule, or
#: scaled with d so that small inclusions converge like large ones
SIZINGS = ("fixed", "by_d")

#: mm, the default tissue slab thickness (``Tissue.thickness``; every room's default): the paper's
#: sensor's slab (elastimap/sensor.py, where the paper's sensor is defined)
THICKNESS = SlabSpec().thickness
#: the design box of the paper and of the default sweep: diameter d (mm) and inclusion modulus E
#: (kPa); the centre depth h spans :func:`depth_range` of each d
DESIGN_BOX = {"d": (2.0, 15.0), "E": (10.0, 200.0)}

_POSITIVE_MM = Interval(float, 0, None, closed="neither", unit="mm")
_POSITIVE_KPA = Interval(float, 0, None, closed="neither", unit="kPa")
#: kPa, the moduli a solve accepts (1 Pa to 10 GPa): beyond them the linear solve loses every
#: digit (1e308 kPa gave NaN displacements); checked after the table, which says "> 0" first
MODULUS_RANGE = (1e-3, 1e7)
#: an inclusion below 0.1 mm is smaller than any mesh level resolves (gmsh failed at 1e-300 mm)
_INCLUSION_MM = Interval(float, 0.1, None, unit="mm")
_POISSON = Interval(float, -1, 0.5, closed="neither")

#: What each solve parameter alone must be, under the name errors report (``d``, ``tissue.E``, ...).
PARAMETER_CONSTRAINTS = {
    "tissue.size": [_POSITIVE_MM],
    "tissue.thickness": [_POSITIVE_MM],
    "tissue.E": [_POSITIVE_KPA],
    "tissue.nu": [_POISSON],
    "tissue.skin_E": [_POSITIVE_KPA],
    "tissue.nonlinearity": [Interval(float, 0, 1)],
    "tissue.wall_compliance": [Interval(float, 0, WALL_COMPLIANCE_MAX, unit="mm/kPa")],
    "d": [_INCLUSION_MM],
    "E": [_POSITIVE_KPA],
    "inclusion.nu": [_POISSON],
    "inclusion.aspect": [Interval(float, 0.2, 5.0)],
    "inclusion.core": [Interval(float, 0, 0.9)],
    "inclusion.core_ratio": [Interval(float, 0, None, closed="neither")],
    "probe.nu": [_POISSON],
    "force": [None, Interval(float, 0, None, closed="neither", unit="mN")],
    "tilt": [Interval(float, -0.1, 0.1, unit="rad")],
    "mesh": [Options(MESH_LEVELS)],
    "degree": [Options((1, 2))],
    "interface": [Options(INTERFACES)],
    "friction_kt": [Interval(float, 0, None, unit="kPa/mm")],
    "symmetry": [Options(SYMMETRIES)],
    "geometry": [Options(GEOMETRIES)],
    "sizing": [Options(SIZINGS)],
    "threshold": [Interval(float, 0, None, unit="mm")],
    "supersample": [Interval(int, 1, 32)],
}


@dataclass(frozen=True)
class Tissue:
    r"""Tissue slab on the chest wall z = 0: rigid (bottom face fixed, the default) or compliant.

    ``wall_compliance`` c_w (mm/kPa) > 0 puts the bottom face Γ_w on an elastic (Winkler)
    foundation of stiffness k_w = 1 / c_w (kPa/mm) in every direction: the traction there is
    t = −k_w u, and the weak form gains ∫_Γw k_w u·v ds (:mod:`elastimap.solver.fem`); a soft chest
    wall (muscle over the ribs).  c_w = 0 is the rigid wall (u = 0 on Γ_w), exactly the model
    before the switch (docs/forward-model.md, 'Chest wall').
    """

    size: float = 120.0  # mm, square side length
    thickness: float = THICKNESS  # mm
    E: float = 5.0  # kPa
    nu: float = 0.49
    skin_thickness: float = 0.0  # mm; > 0 adds a bonded skin layer of modulus skin_E (effect switch)
    skin_E: float = 5.0  # kPa
    # effect switch: 0 = linear elastic (default); 1 = compressible neo-Hookean finite strain for
    # the tissue, skin and inclusion; in between the stored energy is blended (solver/materials.py)
    nonlinearity: float = 0.0
    # effect switch: chest-wall compliance c_w (mm/kPa); 0 = rigid chest wall (default)
    wall_compliance: float = 0.0


@dataclass(frozen=True)
class Inclusion:
    """Spherical (or ellipsoidal) inclusion bonded to the tissue.

    ``h`` is the depth of the **centre** below the tissue surface.
    ``aspect`` scales the vertical semi-axis (1 = sphere; the horizontal
    diameter stays ``d``).  ``offset_x``/``offset_y`` move the centre off the
    probe axis (breaks quarter symmetry: needs ``symmetry='full'``).
    ``core`` > 0 makes it a core/shell inclusion: a concentric core of the same
    shape, diameter ``core * d``, modulus ``core_ratio * E`` (``E`` the shell's).
    """

    d: float = 8.0  # mm
    h: float = 7.0  # mm, centre depth below the surface
    E: float = 50.0  # kPa
    nu: float = 0.49
    aspect: float = 1.0
    offset_x: float = 0.0  # mm
    offset_y: float = 0.0  # mm
    # effect switch (0 = a uniform inclusion); the core's modulus is core_ratio * E
    core: float = 0.0
    core_ratio: float = 1.0


@dataclass(frozen=True)
class Probe:
    """Soft three-layer PDMS waveguide; ``layers`` run from the tissue side up.

    Each layer is ``(thickness mm, E kPa)``.  The top face is bonded to the
    rigid glass plate.
    """

    size: float = 25.0
    layers: tuple[tuple[float, float], ...] = ((2.0, 300.0), (3.0, 150.0), (5.0, 50.0))
    nu: float = 0.49

    @property
    def height(self) -> float:
        return float(sum(t for t, _ in self.layers))


@dataclass(frozen=True)
class Loading:
    """Plate motion: an indentation ``delta`` (mm, downward) or a total ``force`` (mN).

    When ``force`` is given it wins and ``delta`` is found by the solver
    (linear interfaces scale exactly; the contact interface iterates).
    """

    delta: float = 3.0
    force: float | None = None
    # effect switch: probe tilt, a rigid rotation of the plate about the y axis by a small angle
    # (rad): the plate travel varies across the probe top, u_z = -(delta + tilt * x); breaks
    # the quarter symmetry (needs symmetry='full'), needs delta (not force)
    tilt: float = 0.0


@dataclass(frozen=True)
class Discretisation:
    """Mesh level, element degree, interface model, symmetry and how the mesh is made.

    ``geometry``: ``"remesh"`` (default) meshes every sample with gmsh; ``"morph"`` moves a
    reference mesh (one per bin of (d, h), :mod:`elastimap.solver.morph`) to the sample's
    (d, h), which makes the forward map smooth in (d, h) and skips gmsh and the setup.
    ``sizing``: ``"fixed"`` (default, the first sweeps' meshes) or ``"by_d"``, the element size
    near the inclusion scaled with d and a finer zone around it (:mod:`elastimap.solver.geometry`).
    The converged, smooth forward model is ``geometry="morph", sizing="by_d"``.
    """

    mesh: str = "default"
    degree: int = 2
    interface: str = "tied"
    symmetry: str = "quarter"
    # effect switch: tangential probe-tissue interface stiffness k_t (kPa/mm) of the tied/contact
    # interface; 0 = frictionless (default), -> infinity approaches ``bonded`` (solver/interface.py)
    friction_kt: float = 0.0
    geometry: str = "remesh"
    sizing: str = "fixed"


@dataclass(frozen=True)
class ImageSpec:
    """Pixel grid of the elasticity image over the full probe footprint.

    ``threshold`` is the level (mm) above which a pixel of the difference
    image counts as deformed for O3; the area is measured with sub-pixel
    (bilinear, ``supersample``x) resolution so that it varies smoothly.
    """

    pixel: float = 0.5  # mm
    threshold: float = 1e-3  # mm
    supersample: int = 8


@dataclass(frozen=True)
class SolveParams:
    inclusion: Inclusion = field(default_factory=Inclusion)
    tissue: Tissue = field(default_factory=Tissue)
    probe: Probe = field(default_factory=Probe)
    loading: Loading = field(default_factory=Loading)
    disc: Discretisation = field(default_factory=Discretisation)
    image: ImageSpec = field(default_factory=ImageSpec)

    def replace(self, **changes) -> SolveParams:
        return dataclasses.replace(self, **changes)

    def with_inclusion(self, **changes) -> SolveParams:
        return dataclasses.replace(self, inclusion=dataclasses.replace(self.inclusion, **changes))

    def to_dict(self) -> dict:
        """Plain dict.  The effect switches added after the first sweeps (``EFFECT_DEFAULTS``)
        are left out while at their defaults, so stored sweep manifests keep matching."""
        d = dataclasses.asdict(self)
        for (part, name), default in EFFECT_DEFAULTS.items():
            if d[part].get(name) == default:
                del d[part][name]
        return d

    @property
    def nonlinear(self) -> bool:
        """True when the mechanics is not linear in δ (finite strain or unilateral contact)."""
        return self.tissue.nonlinearity > 0 or self.disc.interface == "contact"

    @classmethod
    def from_dict(cls, d: dict) -> SolveParams:
        probe = dict(d.get("probe", {}))
        if "layers" in probe:
            probe["layers"] = tuple(tuple(map(float, l)) for l in probe["layers"])
        return cls(
            inclusion=Inclusion(**d.get("inclusion", {})),
            tissue=Tissue(**d.get("tissue", {})),
            probe=Probe(**probe),
            loading=Loading(**d.get("loading", {})),
            disc=Discretisation(**d.get("disc", {})),
            image=ImageSpec(**d.get("image", {})),
        )

    def _named_values(self) -> dict:
        """Every parameter under the name errors report it by (the keys of ``PARAMETER_CONSTRAINTS``)."""
        t, inc, p, ld, ds, im = self.tissue, self.inclusion, self.probe, self.loading, self.disc, self.image
        return {
            "tissue.size": t.size,
            "tissue.thickness": t.thickness,
            "tissue.E": t.E,
            "tissue.nu": t.nu,
            "tissue.skin_E": t.skin_E,
            "tissue.nonlinearity": t.nonlinearity,
            "tissue.wall_compliance": t.wall_compliance,
            "d": inc.d,
            "E": inc.E,
            "inclusion.nu": inc.nu,
            "inclusion.aspect": inc.aspect,
            "inclusion.core": inc.core,
            "inclusion.core_ratio": inc.core_ratio,
            "probe.nu": p.nu,
            "force": ld.force,
            "tilt": ld.tilt,
            "mesh": ds.mesh,
            "degree": ds.degree,
            "interface": ds.interface,
            "friction_kt": ds.friction_kt,
            "symmetry": ds.symmetry,
            "geometry": ds.geometry,
            "sizing": ds.sizing,
            "threshold": im.threshold,
            "supersample": im.supersample,
        }

    def validate(self) -> SolveParams:
        """Raise :class:`UserError` naming the first bad parameter; return self.

        What each parameter alone must be is declared in ``PARAMETER_CONSTRAINTS``; the rules
        that tie parameters together (depth range for the diameter, probe inside the slab,
        pixel grid over the probe) follow as code, in this order: the moduli, the inclusion in
        the slab, the probe and its travel, the symmetry and the pixel grid, the size of what
        can be meshed.
        """
        validate_params(self._named_values(), PARAMETER_CONSTRAINTS)
        self._check_moduli()
        self._check_inclusion()
        self._check_probe_and_loading()
        self._check_symmetry_and_grid()
        self._check_resolvable()
        return self

    def _check_moduli(self) -> None:
        """Every modulus (tissue, skin, inclusion, its core, each probe layer) in ``MODULUS_RANGE`` kPa."""
        t, inc, p = self.tissue, self.inclusion, self.probe
        moduli = {"tissue.E": t.E, "tissue.skin_E": t.skin_E, "E": inc.E, "inclusion.core_E": inc.core_ratio * inc.E}
        moduli.update({f"probe.layer{i}.E": E for i, (_, E) in enumerate(p.layers, 1)})
        for name, value in moduli.items():
            check_range(name, value, *MODULUS_RANGE, unit="kPa")

    def _check_inclusion(self) -> None:
        """The inclusion inside the slab: the skin at most T/2; the centre depth h in
        :func:`depth_range` for d (1 mm cover, 2 mm above the chest wall); a core only with a
        shell modulus unlike the tissue's and with geometry "remesh"; below the skin
        (h − aspect · d/2 ≥ skin thickness); ≥ 5 mm inside the slab's sides (all mm)."""
        t, inc, ds = self.tissue, self.inclusion, self.disc
        check_range("tissue.skin_thickness", t.skin_thickness, 0, t.thickness / 2, unit="mm")
        half_height = inc.aspect * inc.d / 2
        lo, hi = depth_range(inc.d, t.thickness, inc.aspect)
        if not (lo <= inc.h <= hi):
            if lo > hi:
                raise UserError(
                    "d",
                    f"an inclusion of diameter {inc.d:g} mm (vertical semi-axis {half_height:g} mm) "
                    f"does not fit in a {t.thickness:g} mm slab with 1 mm cover and 2 mm above the chest wall",
                )
            raise UserError(
                "h",
                f"centre depth must be in [{lo:g}, {hi:g}] mm for d = {inc.d:g} mm "
                f"(>= 1 mm below the surface, >= 2 mm above the chest wall; got {inc.h:g})",
            )
        if inc.core > 0 and inc.E == t.E:
            raise UserError("inclusion.core", "a core needs the shell's modulus E to differ from the tissue's")
        if inc.core > 0 and ds.geometry == "morph":
            raise UserError("inclusion.core", "a core/shell inclusion needs geometry 'remesh'")
        if inc.h - half_height < t.skin_thickness:
            raise UserError("h", "the inclusion must lie below the skin layer")
        reach = max(abs(inc.offset_x), abs(inc.offset_y)) + inc.d / 2
        if reach > t.size / 2 - 5:
            raise UserError(
                "inclusion.offset",
                f"the inclusion must stay >= 5 mm inside the slab (|offset| + d/2 <= {t.size / 2 - 5:g} mm)",
            )

    def _check_probe_and_loading(self) -> None:
        """The probe no wider than the slab, at least one layer of positive thickness (mm) and
        modulus (kPa); under travel control the plate travel δ in (0, :func:`delta_limit`] mm;
        a tilted plate (full model, travel control) at most that far down at the probe's edge,
        δ + |tilt| · P/2."""
        t, p, ld, ds = self.tissue, self.probe, self.loading, self.disc
        check_range("probe.size", p.size, 0, t.size, lo_open=True, unit="mm")
        if len(p.layers) < 1:
            raise UserError("probe.layers", "at least one (thickness, E) layer is required")
        for i, (th, E) in enumerate(p.layers, 1):
            validate_params(
                {f"probe.layer{i}.thickness": th, f"probe.layer{i}.E": E},
                {f"probe.layer{i}.thickness": [_POSITIVE_MM], f"probe.layer{i}.E": [_POSITIVE_KPA]},
            )
        if ld.force is None:
            check_range("delta", ld.delta, 0, delta_limit(self), lo_open=True, unit="mm")
        if ld.tilt != 0:
            if ds.symmetry == "quarter":
                raise UserError("symmetry", "a tilted probe breaks quarter symmetry: use the full model")
            if ld.force is not None:
                raise UserError("tilt", "a tilted plate needs the plate travel delta, not force control")
            reach = ld.delta + abs(ld.tilt) * p.size / 2
            if reach > delta_limit(self):
                raise UserError(
                    "tilt",
                    f"the plate travels up to {reach:.3g} mm at the probe edge; at most {delta_limit(self):g} mm",
                )

    def _check_symmetry_and_grid(self) -> None:
        """An on-axis inclusion for the quarter model; the pixel in (0, P/4] mm dividing the probe
        size P into a whole number n = P / pixel of pixels, n even for the quarter model."""
        inc, p, ds, im = self.inclusion, self.probe, self.disc, self.image
        if ds.symmetry == "quarter" and (inc.offset_x != 0 or inc.offset_y != 0):
            raise UserError("symmetry", "an off-axis inclusion breaks quarter symmetry: use the full model")
        check_range("pixel", im.pixel, 0, p.size / 4, lo_open=True, unit="mm")
        n = p.size / im.pixel
        if abs(n - round(n)) > 1e-9:
            raise UserError(
                "pixel", f"must divide the probe size {p.size:g} mm into a whole number of pixels (got {im.pixel:g})"
            )
        if ds.symmetry == "quarter" and round(n) % 2:
            raise UserError("pixel", "the quarter model needs an even number of pixels across the probe")

    def _check_resolvable(self) -> None:
        """Geometry the mesh and the image can resolve in reasonable time and memory: the slab no
        thicker than wide, the probe no taller than half the slab size (mm), at most
        ``MAX_PIXELS`` pixels across the probe."""
        t, p, im = self.tissue, self.probe, self.image
        n = p.size / im.pixel
        if t.thickness > t.size:
            raise UserError(
                "tissue.thickness",
                f"must be <= the slab size {t.size:g} mm (got {t.thickness:g} mm); "
                "a thicker slab would need an unreasonable mesh",
            )
        if p.height > t.size / 2:
            raise UserError(
                "probe.layers",
                f"the probe layers add up to {p.height:g} mm; at most {t.size / 2:g} mm "
                "(half the slab size) can be meshed in reasonable time",
            )
        if round(n) > MAX_PIXELS:
            raise UserError(
                "pixel",
                f"gives {round(n)} pixels across the probe; at most {MAX_PIXELS} (pixel >= {p.size / MAX_PIXELS:g} mm)",
            )


def from_sensor(sensor, inclusion: Inclusion | None = None, disc=None, image=None) -> SolveParams:
    """Solve parameters of one lesion pressed by the sensor ``sensor`` (:class:`elastimap.sensor.Sensor`).

    The description gives the probe, tissue slab, loading and interface; ``inclusion`` (default: the
    default lesion with the slab's Poisson ratio), ``disc`` and ``image`` the rest (the interface
    model and friction of ``disc`` are the sensor's; a tilted plate needs the full model).
    ``from_sensor(Sensor()) == SolveParams()``.  Not validated: call ``.validate()``.
    """
    pr, t, ld, itf = sensor.probe, sensor.tissue, sensor.loading, sensor.interface
    disc = dataclasses.replace(disc or Discretisation(), interface=itf.model, friction_kt=itf.friction_kt)
    if ld.tilt != 0:
        disc = dataclasses.replace(disc, symmetry="full")
    return SolveParams(
        inclusion=inclusion or Inclusion(nu=t.nu),
        tissue=Tissue(**dataclasses.asdict(t)),
        probe=Probe(size=pr.footprint, layers=tuple((l.thickness, l.E) for l in pr.layers), nu=pr.nu),
        loading=Loading(delta=ld.delta, force=ld.force, tilt=ld.tilt),
        disc=disc,
        image=image or ImageSpec(),
    )


def to_sensor(p: SolveParams, like):
    """The sensor description of ``p``'s probe, slab, loading and interface; the name and camera of
    ``like`` (a :class:`elastimap.sensor.Sensor`).  ``to_sensor(from_sensor(s), s) == s``."""
    pr, ld = p.probe, p.loading
    return like.replace(
        probe=ProbeSpec(footprint=pr.size, nu=pr.nu, layers=tuple(Layer(t, E) for t, E in pr.layers)),
        tissue=SlabSpec(**dataclasses.asdict(p.tissue)),
        loading=LoadingSpec(delta=ld.delta, force=ld.force, tilt=ld.tilt),
        interface=InterfaceSpec(model=p.disc.interface, friction_kt=p.disc.friction_kt),
        camera=dataclasses.replace(like.camera, footprint_mm=pr.size),
    )


#: most image pixels across the probe (an image of MAX_PIXELS² float32 values is 16 MiB)
MAX_PIXELS = 2048


def delta_limit(params: SolveParams) -> float:
    """Largest plate travel δ (mm) a solve may use, with ``--delta`` or found under force control:
    half the thinner of probe and tissue (beyond it the small-strain model means nothing)."""
    return min(params.probe.height, params.tissue.thickness) / 2


# effect switches omitted from ``SolveParams.to_dict`` while at these defaults
EFFECT_DEFAULTS = {
    ("tissue", "nonlinearity"): 0.0,
    ("tissue", "wall_compliance"): 0.0,
    ("disc", "friction_kt"): 0.0,
    ("disc", "geometry"): "remesh",
    ("disc", "sizing"): "fixed",
    ("loading", "tilt"): 0.0,
    ("inclusion", "core"): 0.0,
    ("inclusion", "core_ratio"): 1.0,
}


def depth_range(
    d: float, thickness: float = THICKNESS, aspect: float = 1.0, cover: float = 1.0, floor: float = 2.0
) -> tuple[float, float]:
    """Allowed centre depths (mm) keeping ``cover`` mm above and ``floor`` mm below the inclusion."""
    half = aspect * d / 2
    return cover + half, thickness - floor - half


@dataclass
class SolveResult:
    """Output of one sample: features of the difference image, images, force and statistics.

    ``image`` is the elasticity image used for features: the probe-bottom
    deflection with the inclusion minus the same with the inclusion's modulus
    set to the tissue's, on the same mesh (mm, shape ``(ny, nx)``, row 0 at
    y = -size/2).  ``image_raw`` is the deflection itself (relative to the
    plate motion: how much the probe is compressed, mm).
    """

    params: SolveParams
    O1: float  # mm, maximum of the difference image
    O2: float  # mm, sum over pixels of the difference image
    O3: float  # mm^2, area where the difference image exceeds the threshold
    force: float  # mN, total plate reaction with the inclusion (full probe)
    force_ref: float  # mN, same for the reference solve
    delta: float  # mm, indentation actually applied
    image: np.ndarray
    image_raw: np.ndarray
    pixel: float
    ndofs: int
    ncells: int
    newton_iterations: int  # active-set / Newton iterations summed over both solves (1 per linear solve)
    seconds: float
    timings: dict[str, float]
    peak_memory_mb: float
    interface: dict[str, float] = field(default_factory=dict)  # interface diagnostics (tension check)

    def features(self) -> dict[str, float]:
        return {"O1": self.O1, "O2": self.O2, "O3": self.O3, "force": self.force}

    def summary(self) -> dict:
        """JSON-ready summary (no arrays)."""
        inc = self.params.inclusion
        out = {
            "d": inc.d,
            "h": inc.h,
            "E": inc.E,
            "O1": self.O1,
            "O2": self.O2,
            "O3": self.O3,
            "force": self.force,
            "force_ref": self.force_ref,
            "delta": self.delta,
            "ndofs": self.ndofs,
            "ncells": self.ncells,
            "newton_iterations": self.newton_iterations,
            "seconds": self.seconds,
            "peak_memory_mb": self.peak_memory_mb,
            "mesh": self.params.disc.mesh,
            "interface": self.params.disc.interface,
            "symmetry": self.params.disc.symmetry,
            "pixel": self.pixel,
            "image_shape": list(self.image.shape),
            "timings": self.timings,
            "interface_check": self.interface,
        }
        import numpy as np

        return {k: (float(v) if isinstance(v, (np.floating,)) else v) for k, v in out.items()}


def finite(x: float) -> bool:
    return math.isfinite(x)
