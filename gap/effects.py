"""The effects library: unmodelled effects as documented switches with one magnitude each,
and multi-parameter families composed from them.

Every effect is a switch of the solver (:mod:`elastimap.solver.params`) or of the camera model
(:class:`elastimap.camera.optics.SensorModel`), so the same switch generates SYNTHETIC "measured" data
and serves as the correction.  Each has a nominal magnitude (the baseline model), a grid of
magnitudes for the fitting sweep and a "blind" range the self-test draws true magnitudes from
(chosen so that the features move by well over 3x the camera noise floor).

| name | stage | switch | magnitude (unit) | nominal |
|---|---|---|---|---|
| nonlinearity | mechanics | ``Tissue.nonlinearity`` | β, neo-Hookean fraction (-) | 0 |
| friction | mechanics | ``Discretisation.friction_kt`` | k_t (kPa/mm) | 0 |
| skin | mechanics | ``Tissue.skin_thickness`` = 1 mm, ``Tissue.skin_E`` | skin modulus (kPa) | none (5) |
| aspect | mechanics | ``Inclusion.aspect`` | vertical/horizontal axis ratio (-) | 1 |
| offaxis | mechanics | ``Inclusion.offset_x`` (full model, ~10x cost) | offset (mm) | 0 |
| probe_moduli | mechanics | ``Probe.layers`` moduli x factor | factor (-) | 1 |
| background_E | mechanics | ``Tissue.E`` | tissue modulus (kPa) | 5 |
| probe_E1, probe_E2, probe_E3 | mechanics | ``Probe.layers[i]`` modulus | layer modulus (kPa) | 300, 150, 50 |
| probe_t1, probe_t2, probe_t3 | mechanics | ``Probe.layers[i]`` thickness | layer thickness (mm) | 2, 3, 5 |
| slab_thickness | mechanics | ``Tissue.thickness`` | slab thickness (mm) | 20 |
| tissue_nu | mechanics | ``Tissue.nu`` | tissue Poisson ratio (-) | 0.49 |
| chest_wall | mechanics | ``Tissue.wall_compliance`` | chest-wall compliance c_w = 1/k_w (mm/kPa) | 0 (rigid) |
| tilt | mechanics | ``Loading.tilt`` (full model, ~10x cost) | plate angle (deg) | 0 |
| indentation | mechanics | ``Loading.delta`` = 3 mm + offset | plate-travel offset (mm) | 0 |
| saturation | optics | ``SensorModel.w_sat`` | saturation deflection (mm) | 0.5 |
| vignetting | optics | ``SensorModel.vignetting`` | corner fall-off (-) | 0.15 |
| blur | optics | ``SensorModel.blur_mm`` | point-spread sigma (mm) | 0 |
| gamma | optics | ``SensorModel.gamma`` | response exponent (-) | 1 |
| led_imbalance | optics | ``SensorModel.led_power[0]`` | left LED power (-) | 1 |
| stray_light | optics | ``SensorModel.stray`` | stray light (fraction of full well) | 0.02 |
| lens_distortion | optics | ``SensorModel.lens_k1`` | radial displacement at the footprint corner, k1 (-) | 0 |

**Outside-only effects** (:data:`OUTSIDE_ONLY`): they make SYNTHETIC data (``gap synth --effect``,
``gap selftest --outside``) for the out-of-library checks and are never diagnosis candidates (the
library holds no correction for them; :func:`parse_list` refuses them as candidates):

| name | stage | switch | magnitude (unit) | nominal |
|---|---|---|---|---|
| core_shell | mechanics | ``Inclusion.core`` = 0.6, ``Inclusion.core_ratio`` | core modulus / shell modulus (-) | 1 |
| mislabel_d, mislabel_h, mislabel_E | label | one phantom's table entry x (1 + m) | relative error (-) | 0 |

A **label** effect changes no solve and no camera: the data are those of the true phantom, and
the table written beside them records that phantom's d, h or E (1 + m) times its true value (a
phantom-labelling error; :meth:`Effect.apply_label`).  It acts on one phantom, the synthesizer's
``label_phantom`` (``gap synth --label-phantom``, default the first; the self-test draws it).

Multi-parameter **families** (:data:`FAMILIES`) combine single effects whose physics has several
parameters: ``probe_layers_E`` (the three layer moduli, k = 3) and ``probe_layers_t`` (the three
layer thicknesses, k = 3).  Their prediction is composed from the members' sweeps to first order,
f(m_1, m_2, m_3) = y_0 + sum_l (f_l(m_l) - y_0), and model selection charges k parameters.
``probe_moduli`` is nested in ``probe_layers_E`` (all three moduli times one factor:
``Family.common``).

``offaxis`` and ``tilt`` are in the library but not in the default candidate list (they break
the quarter symmetry: a full-model solve costs about ten quarter-model solves); pass them
explicitly with ``--effects``.  ``tilt`` rotates the rigid plate about the y axis by the angle
(degrees): the plate travel is δ + θ·x across the probe top (``Loading.tilt`` = θ in rad).

``indentation`` is exactly linear for the linear tied model: its sweep is then the baseline solve
scaled by (3 + offset)/3 (no extra solves; ``scales_with_delta``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from elastimap.errors import UserError
from elastimap.sensor import WALL_COMPLIANCE_MAX

#: effects that change the geometry (or switch to the full model), so each magnitude has its own mesh
REMESHING = frozenset(
    {"skin", "aspect", "offaxis", "core_shell", "probe_t1", "probe_t2", "probe_t3", "slab_thickness", "tilt"}
)
#: effects whose discretisation error does not carry over from the baseline (``Effect.own_model_error``)
OWN_ERROR = REMESHING | {"tissue_nu"}
#: effects that only make SYNTHETIC data (out-of-library checks), never diagnosis candidates
OUTSIDE_ONLY = frozenset({"core_shell", "mislabel_d", "mislabel_h", "mislabel_E"})
#: the table column each label effect mislabels
LABEL_COLUMN = {"mislabel_d": 0, "mislabel_h": 1, "mislabel_E": 2}
SKIN_THICKNESS = 1.0  # mm, thickness of the skin layer switched on by the ``skin`` effect
CORE_FRACTION = 0.6  # core diameter / inclusion diameter of the ``core_shell`` effect


@dataclass(frozen=True)
class Effect:
    name: str
    stage: str  # "mechanics", "optics" or "label" (a phantom-labelling error, outside-only)
    unit: str
    nominal: float
    grid: tuple[float, ...]  # magnitudes of the fitting sweep (includes the nominal)
    blind: tuple[float, float]  # range of true magnitudes in the self-test
    description: str
    n_params: int = 1
    cost: float = 1.0  # relative solve cost
    scales_with_delta: bool = False  # the effect only changes the plate travel (linear models: scale)
    #: the range (None: unbounded) a diagnosis may extend the grid into when a fit sits at the
    #: grid's end (:meth:`beyond`): physical where physics gives one (β ≤ 1, ν < 0.5, blur ≥ 0),
    #: elsewhere a plausibility bound (chosen, not measured); real effects need not respect the grid
    limits: tuple[float | None, float | None] = (None, None)
    #: the sensitivity magnitude (:attr:`sensitivity`) when the grid's far end is a poor one
    sensitivity_at: float | None = None

    @property
    def lo(self) -> float:
        return min(self.grid)

    @property
    def hi(self) -> float:
        return max(self.grid)

    @property
    def sensitivity(self) -> float:
        """The one magnitude an adaptive diagnosis solves before it has a fit: ``sensitivity_at``
        if set, else the grid end farther from the nominal (relative to the nominal's size; the
        upper end on a tie).  Until refinement adds points, the fit interpolates linearly
        between the nominal and this magnitude."""
        if self.sensitivity_at is not None:
            return float(self.sensitivity_at)
        scale = max(abs(self.nominal), 1e-300) if self.nominal != 0 else 1.0
        lo, hi = abs(self.lo - self.nominal) / scale, abs(self.hi - self.nominal) / scale
        return self.hi if hi >= lo else self.lo

    def beyond(self, m: float, lo: float, hi: float, step: float = 0.5) -> float | None:
        """The magnitude to try next when a fit ``m`` sits at an end of the range [lo, hi] it was
        fitted over: that end moved out by ``step`` x the grid's width, held inside ``limits``;
        None when ``m`` is inside the range or the end is already the physical limit."""
        tol = 1e-6 * max(hi - lo, 1e-300)
        w = step * (self.hi - self.lo)
        a, b = self.limits
        if m >= hi - tol and (b is None or hi < b - tol):
            return hi + w if b is None else min(hi + w, b)
        if m <= lo + tol and (a is None or lo > a + tol):
            return lo - w if a is None else max(lo - w, a)
        return None

    @property
    def own_model_error(self) -> bool:
        """Whether the baseline's discretisation error does not carry over to this effect's
        magnitudes, so the diagnosis measures the model error at its refined magnitudes
        (:func:`elastimap.gap.adaptive.refine`): the effects that remesh, and the tissue's
        Poisson ratio (the error of nearly incompressible elements grows as ν → 0.5)."""
        return self.stage == "mechanics" and self.name in OWN_ERROR

    def is_nominal(self, m: float) -> bool:
        return abs(float(m) - self.nominal) <= 1e-12 * max(1.0, abs(self.nominal))

    # ---------------------------------------------------------------- switches
    def apply_params(self, p, m: float):
        """SolveParams with this effect at magnitude ``m`` (mechanics effects)."""
        if self.stage != "mechanics" or self.is_nominal(m):
            return p
        m = float(m)
        r = dataclasses.replace
        if self.name == "nonlinearity":
            return p.replace(tissue=r(p.tissue, nonlinearity=m))
        if self.name == "friction":
            return p.replace(disc=r(p.disc, friction_kt=m))
        if self.name == "skin":
            return p.replace(tissue=r(p.tissue, skin_thickness=SKIN_THICKNESS, skin_E=m))
        if self.name == "aspect":
            return p.with_inclusion(aspect=m)
        if self.name == "core_shell":
            return p.with_inclusion(core=CORE_FRACTION, core_ratio=m)
        if self.name == "offaxis":
            return p.with_inclusion(offset_x=m).replace(disc=r(p.disc, symmetry="full"))
        if self.name == "probe_moduli":
            return p.replace(probe=r(p.probe, layers=tuple((t, E * m) for t, E in p.probe.layers)))
        if self.name == "background_E":
            return p.replace(tissue=r(p.tissue, E=m))
        if self.name.startswith("probe_E") or self.name.startswith("probe_t"):
            i = int(self.name[-1]) - 1
            lay = [list(x) for x in p.probe.layers]
            lay[i][0 if self.name.startswith("probe_t") else 1] = m
            return p.replace(probe=r(p.probe, layers=tuple(tuple(x) for x in lay)))
        if self.name == "slab_thickness":
            return p.replace(tissue=r(p.tissue, thickness=m))
        if self.name == "tissue_nu":
            return p.replace(tissue=r(p.tissue, nu=m))
        if self.name == "chest_wall":
            return p.replace(tissue=r(p.tissue, wall_compliance=m))
        if self.name == "tilt":
            return p.replace(loading=r(p.loading, tilt=math.radians(m)), disc=r(p.disc, symmetry="full"))
        if self.name == "indentation":
            return p.replace(loading=r(p.loading, delta=p.loading.delta + m))
        raise AssertionError(self.name)

    def apply_sensor(self, s, m: float):
        """SensorModel with this effect at magnitude ``m`` (optics effects)."""
        if self.stage != "optics" or self.is_nominal(m):
            return s
        if self.name == "saturation":
            return s.replace(w_sat=float(m))
        if self.name == "vignetting":
            return s.replace(vignetting=float(m))
        if self.name == "blur":
            return s.replace(blur_mm=float(m))
        if self.name == "gamma":
            return s.replace(gamma=float(m))
        if self.name == "led_imbalance":
            return s.replace(led_power=(s.led_power[0] * float(m),) + tuple(s.led_power[1:]))
        if self.name == "stray_light":
            return s.replace(stray=float(m))
        if self.name == "lens_distortion":
            return s.replace(lens_k1=float(m))
        raise AssertionError(self.name)

    def apply_label(self, dhe, m: float, i: int):
        """The phantom table (n, 3: d mm, h mm, E kPa) as a labelling error ``m`` records it (label
        effects): phantom ``i``'s d, h or E times (1 + m), every other entry as given (a copy)."""
        import numpy as np

        out = np.array(dhe, dtype=float, copy=True)
        if self.stage != "label" or self.is_nominal(m):
            return out
        out[i, LABEL_COLUMN[self.name]] *= 1.0 + float(m)
        return out

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["grid"], d["blind"], d["limits"] = list(self.grid), list(self.blind), list(self.limits)
        return d


EFFECTS: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect(
            "nonlinearity",
            "mechanics",
            "-",
            0.0,
            (0.0, 0.125, 0.25, 0.375, 0.5, 0.75, 1.0),
            (0.3, 1.0),
            "tissue nonlinearity: compressible neo-Hookean finite strain (blend fraction β)",
            cost=5.0,
            limits=(0.0, 1.0),
            # the response is far from linear in β: on coarse (phantom 0 of the bench, d/h/E
            # 5.3/11.4/37.5) O1 rises 0.0200 → 0.0281 → 0.0318 mm at β = 0, 0.3, 0.53, peaks
            # near 0.8 (0.0336) and falls to 0.0327 at 1, the force drops 5 % from 0.94 to 1;
            # the secant 0 → 1 put a β = 0.325 fit at 0.53 (docs/history/gap.md,
            # 'Blind benchmark, seed 7'), 0 → 0.5 is closer
            sensitivity_at=0.5,
        ),
        Effect(
            "friction",
            "mechanics",
            "kPa/mm",
            0.0,
            (0.0, 0.025, 0.05, 0.1, 0.15, 0.275, 0.4, 0.7, 1.0),
            (0.1, 1.0),
            "probe-tissue friction: tangential interface stiffness k_t (0 = frictionless, inf = bonded)",
            limits=(0.0, None),
        ),
        Effect(
            "skin",
            "mechanics",
            "kPa",
            5.0,
            (5.0, 7.5, 10.0, 15.0, 20.0, 30.0, 40.0, 60.0, 80.0),
            (15.0, 80.0),
            f"stiffer skin layer ({SKIN_THICKNESS:g} mm) on the tissue surface: its modulus",
            limits=(1.0, None),
        ),
        Effect(
            "aspect",
            "mechanics",
            "-",
            1.0,
            (0.6, 0.7, 0.8, 0.9, 1.0, 1.125, 1.25),
            (0.6, 0.8),
            "non-spherical inclusion: ellipsoid, vertical semi-axis = aspect * d/2",
            limits=(0.3, 2.0),
        ),
        Effect(
            "offaxis",
            "mechanics",
            "mm",
            0.0,
            (0.0, 1.5, 3.0),
            (1.5, 3.0),
            "inclusion off the probe axis by offset_x (full model)",
            cost=10.0,
            limits=(0.0, None),
        ),
        Effect(
            "probe_moduli",
            "mechanics",
            "-",
            1.0,
            (0.6, 0.7, 0.8, 0.9, 1.0, 1.125, 1.25, 1.375, 1.5),
            (0.6, 0.75),
            "probe PDMS moduli x factor (cure / temperature)",
            limits=(0.3, None),
        ),
        Effect(
            "background_E",
            "mechanics",
            "kPa",
            5.0,
            (3.5, 3.875, 4.25, 4.625, 5.0, 5.5, 6.0, 6.5, 7.0),
            (6.0, 7.0),
            "background tissue modulus different from nominal",
            limits=(1.0, None),
        ),
        Effect(
            "probe_E1",
            "mechanics",
            "kPa",
            300.0,
            (180.0, 225.0, 270.0, 300.0, 345.0, 400.0, 450.0),
            (180.0, 230.0),
            "probe layer 1 (tissue side) modulus",
            limits=(60.0, None),
        ),
        Effect(
            "probe_E2",
            "mechanics",
            "kPa",
            150.0,
            (90.0, 112.5, 135.0, 150.0, 172.5, 200.0, 225.0),
            (90.0, 115.0),
            "probe layer 2 (middle) modulus",
            limits=(30.0, None),
        ),
        Effect(
            "probe_E3",
            "mechanics",
            "kPa",
            50.0,
            (30.0, 37.5, 45.0, 50.0, 57.5, 66.0, 75.0),
            (30.0, 38.0),
            "probe layer 3 (glass side) modulus",
            limits=(10.0, None),
        ),
        Effect(
            "probe_t1",
            "mechanics",
            "mm",
            2.0,
            (1.2, 1.6, 2.0, 2.5, 3.0),
            (1.2, 1.5),
            "probe layer 1 (tissue side) thickness",
            limits=(0.5, None),
        ),
        Effect(
            "probe_t2",
            "mechanics",
            "mm",
            3.0,
            (2.0, 2.5, 3.0, 3.5, 4.0),
            (3.6, 4.0),
            "probe layer 2 (middle) thickness",
            limits=(0.5, None),
        ),
        Effect(
            "probe_t3",
            "mechanics",
            "mm",
            5.0,
            (3.5, 4.25, 5.0, 5.75, 6.5),
            (3.5, 4.0),
            "probe layer 3 (glass side) thickness",
            limits=(1.0, None),
        ),
        Effect(
            "slab_thickness",
            "mechanics",
            "mm",
            20.0,
            (20.0, 21.0, 22.5, 24.0, 26.0),
            (23.0, 26.0),
            "tissue slab thickness (thinner slabs would not hold the deepest design phantoms)",
            limits=(15.0, None),
        ),
        Effect(
            "tissue_nu",
            "mechanics",
            "-",
            0.49,
            (0.45, 0.465, 0.48, 0.49, 0.495),
            (0.45, 0.47),
            "tissue Poisson ratio (compressibility)",
            limits=(0.3, 0.499),
        ),
        Effect(
            "chest_wall",
            "mechanics",
            "mm/kPa",
            0.0,
            (0.0, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0),
            (0.2, 0.8),
            "soft chest wall: the slab's bottom on a Winkler foundation, traction -u / c_w (compliance c_w)",
            limits=(0.0, WALL_COMPLIANCE_MAX),
            # the bottom face carries about 1.1 kPa under the nominal 3 mm press, so c_w moves it by
            # about 1.1 c_w mm: 0.2-0.9 mm over the blind range (a soft muscle layer over the ribs,
            # k_w ~ E_w / H_w = 1-5 kPa/mm); the response saturates (O1 -24 % at 0.5, -57 % at 2 on
            # tiny), so the secant runs to the middle of the blind range (docs/gap.md, 'Effects')
            sensitivity_at=0.5,
        ),
        Effect(
            "tilt",
            "mechanics",
            "deg",
            0.0,
            (0.0, 0.25, 0.5, 1.0, 1.5),
            (0.5, 1.5),
            "probe tilt: the plate rotated about the y axis, travel -(delta + tan(angle) x) across "
            "the probe top (full model)",
            cost=10.0,
            limits=(0.0, None),
        ),
        Effect(
            "indentation",
            "mechanics",
            "mm",
            0.0,
            (-0.6, -0.4, -0.2, 0.0, 0.2, 0.4, 0.6),
            (0.3, 0.6),
            "plate-travel offset: indentation 3 mm + offset (zero point of the stage)",
            scales_with_delta=True,
            limits=(-2.5, None),
        ),
        Effect(
            "saturation",
            "optics",
            "mm",
            0.5,
            (0.15, 0.2, 0.25, 0.3, 0.35, 0.425, 0.5, 0.6, 0.7),
            (0.15, 0.3),
            "optical response: scattering saturates at a different deflection w_sat (gamma/saturation)",
            limits=(0.05, None),
        ),
        Effect(
            "vignetting",
            "optics",
            "-",
            0.15,
            (0.0, 0.075, 0.15, 0.225, 0.3, 0.375, 0.45, 0.525, 0.6),
            (0.35, 0.6),
            "non-uniform illumination: lens/LED fall-off towards the window corners",
            limits=(0.0, 0.95),
        ),
        Effect(
            "blur",
            "optics",
            "mm",
            0.0,
            (0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.3),
            (0.5, 1.2),
            "optical point-spread: Gaussian blur of the light image, sigma (mm on the probe)",
            limits=(0.0, None),
        ),
        Effect(
            "gamma",
            "optics",
            "-",
            1.0,
            (0.7, 0.8, 0.9, 1.0, 1.1, 1.25, 1.4),
            (0.7, 0.85),
            "camera response gamma: DN = FS (charge / full well)^gamma",
            limits=(0.3, None),
        ),
        Effect(
            "led_imbalance",
            "optics",
            "-",
            1.0,
            (0.5, 0.7, 0.85, 1.0, 1.2, 1.5),
            (0.4, 0.6),
            "left LED power x factor (illumination imbalance)",
            limits=(0.1, None),
        ),
        Effect(
            "stray_light",
            "optics",
            "-",
            0.02,
            (0.0, 0.02, 0.05, 0.1, 0.15),
            (0.08, 0.15),
            "stray light reaching the camera without deformation (fraction of full well)",
            limits=(0.0, 0.5),
        ),
        Effect(
            "lens_distortion",
            "optics",
            "-",
            0.0,
            (-0.2, -0.15, -0.1, -0.05, 0.0, 0.05, 0.1, 0.15, 0.2, 0.3),
            (-0.2, -0.1),
            "radial lens distortion (Brown-Conrady k1): fractional radial displacement at the "
            "footprint corner (> 0 pincushion, < 0 barrel)",
            # the footprint's corner lies at 0.81 of the sensor's half-diagonal (707 of 869 pixels),
            # so k1 = 0.66 x a lens's corner distortion: machine-vision lenses (0.1-2 %) give |k1| <
            # 0.015, below what the diagnosis resolves (|k1| 0.05 is "no gap"); short-throw wide-angle
            # board lenses are barrel, 5-30 % (k1 -0.03 to -0.2); the blind range is the resolvable
            # barrel part; below -0.22 the default frame folds (SensorModel.validate)
            # (docs/gap.md, 'Effects library')
            limits=(-0.2, 0.5),
        ),
        # ---- outside-only (OUTSIDE_ONLY): SYNTHETIC data for the out-of-library checks
        Effect(
            "core_shell",
            "mechanics",
            "-",
            1.0,
            (0.2, 0.5, 1.0, 2.0, 4.0, 10.0),
            (2.0, 4.0),
            f"core/shell inclusion: a concentric core of {CORE_FRACTION:g} d whose modulus is this factor "
            "times the shell's (the phantom's E); outside-only",
            limits=(0.05, None),
        ),
        *(
            Effect(
                f"mislabel_{q}",
                "label",
                "-",
                0.0,
                (-0.3, -0.15, 0.0, 0.15, 0.3),
                (0.1, 0.25),
                f"phantom-labelling error: one phantom's table {q} is (1 + m) times the true one, its "
                "data the true phantom's; outside-only",
                limits=(-0.5, None),
            )
            for q in ("d", "h", "E")
        ),
    )
}


@dataclass(frozen=True)
class Family:
    """A multi-parameter effect composed (to first order) from single-effect sweeps."""

    name: str
    members: tuple[str, ...]
    description: str
    #: the single effect that moves every member by one common factor (nested in the family)
    common: str | None = None

    @property
    def n_params(self) -> int:
        return len(self.members)

    @property
    def stage(self) -> str:
        return EFFECTS[self.members[0]].stage


FAMILIES: dict[str, Family] = {
    f.name: f
    for f in (
        Family(
            "probe_layers_E",
            ("probe_E1", "probe_E2", "probe_E3"),
            "the three probe layer moduli together",
            common="probe_moduli",
        ),
        Family("probe_layers_t", ("probe_t1", "probe_t2", "probe_t3"), "the three probe layer thicknesses together"),
    )
}

#: every effect but those that need the full model (about ten quarter-model solves each)
DEFAULT_CANDIDATES = tuple(n for n in EFFECTS if n not in ("offaxis", "tilt") and n not in OUTSIDE_ONLY)
DEFAULT_FAMILIES = tuple(FAMILIES)


def get(name: str) -> Effect:
    if name not in EFFECTS:
        raise UserError("effect", f"unknown effect {name!r}; known: {', '.join(EFFECTS)}")
    return EFFECTS[name]


def parse_list(
    text: str | None,
    default=DEFAULT_CANDIDATES,
    table: dict[str, Effect] | None = None,
    outside_only: bool = False,
    flag: str = "effects",
) -> list[Effect]:
    """The candidate effects named in ``text`` (default: ``default``), from ``table`` (the library
    about another sensor, :func:`for_sensor`; default :data:`EFFECTS`).  An outside-only effect
    (:data:`OUTSIDE_ONLY`) is refused unless ``outside_only`` (the self-test's out-of-library
    list); ``flag`` names the option in the error."""
    table = EFFECTS if table is None else table
    if text is None or text.strip() == "":
        return [table[n] for n in default if n in table]
    names = [t.strip() for t in text.split(",") if t.strip()]
    if len(set(names)) != len(names):
        raise UserError(flag, "names an effect twice")
    bad = [n for n in names if n in OUTSIDE_ONLY] if not outside_only else []
    if bad:
        raise UserError(
            flag, f"{bad[0]} makes SYNTHETIC data only (gap synth --effect, gap selftest --outside), not a candidate"
        )
    missing = [n for n in names if n in EFFECTS and n not in table]
    if missing:
        raise UserError("effects", f"{missing[0]} does not apply to this sensor (its probe has no such layer)")
    return [table[get(n).name] for n in names]


def families_for(cands: list[Effect], names=DEFAULT_FAMILIES) -> list[Family]:
    """The families whose members are all among the candidates."""
    have = {e.name for e in cands}
    return [FAMILIES[n] for n in names if set(FAMILIES[n].members) <= have]


def parse_spec(text: str, table: dict[str, Effect] | None = None) -> list[tuple[Effect, float]]:
    """``"friction=0.3,skin=40"`` -> [(Effect, magnitude), ...], from ``table`` (the library about
    another sensor, :func:`for_sensor`; default :data:`EFFECTS`)."""
    table = EFFECTS if table is None else table
    out = []
    for part in [t.strip() for t in text.split(",") if t.strip()]:
        if "=" not in part:
            raise UserError("effect", f"{part!r}: use NAME=MAGNITUDE (e.g. friction=0.3)")
        name, val = part.split("=", 1)
        e = get(name.strip())
        if e.name not in table:
            raise UserError("effect", f"{e.name} does not apply to this sensor (its probe has no such layer)")
        e = table[e.name]
        try:
            m = float(val)
        except ValueError:
            raise UserError("effect", f"{part!r}: magnitude must be a number") from None
        lo, hi = min(e.lo, e.nominal), max(e.hi, e.nominal)
        hi = hi + 0.5 * abs(hi)
        if not (lo - 1e-12 <= m <= hi + 1e-12):
            raise UserError("effect", f"{e.name}={m:g} is outside the supported range [{lo:g}, {hi:g}] {e.unit}")
        out.append((e, m))
    if len({e.name for e, _ in out}) != len(out):
        raise UserError("effect", "names an effect twice")
    return out


# ----------------------------------------------------------------------------- another sensor
#: effects whose magnitude is a positive physical size: re-centred on another sensor by scaling
#: (grid, blind range and limits times the sensor's value / the paper's); the others are shifted
SCALED = frozenset(
    {"skin", "background_E", "probe_E1", "probe_E2", "probe_E3", "probe_t1", "probe_t2", "probe_t3"}
    | {"slab_thickness", "saturation"}
)


def value_in(e: Effect, p, camera) -> float | None:
    """The magnitude of ``e`` that the solve parameters ``p`` and the camera ``camera`` (a
    :class:`elastimap.sensor.CameraSpec`) hold, the inverse of :meth:`Effect.apply_params` /
    :meth:`Effect.apply_sensor`; None when ``e`` does not apply (a probe without that layer).
    Relative effects (a factor or an offset) and the lesion's own (aspect, offaxis) are at their
    nominal."""
    n = e.name
    if n.startswith("probe_E") or n.startswith("probe_t"):
        i = int(n[-1]) - 1
        if i >= len(p.probe.layers):
            return None
        return float(p.probe.layers[i][0 if n.startswith("probe_t") else 1])
    values = {
        "nonlinearity": lambda: p.tissue.nonlinearity,
        "friction": lambda: p.disc.friction_kt,
        "skin": lambda: p.tissue.skin_E if p.tissue.skin_thickness > 0 else e.nominal,
        "background_E": lambda: p.tissue.E,
        "slab_thickness": lambda: p.tissue.thickness,
        "tissue_nu": lambda: p.tissue.nu,
        "chest_wall": lambda: p.tissue.wall_compliance,
        "tilt": lambda: math.degrees(p.loading.tilt),
        "saturation": lambda: camera.w_sat,
        "vignetting": lambda: camera.vignetting,
        "blur": lambda: camera.blur_mm,
        "gamma": lambda: camera.gamma,
        "lens_distortion": lambda: camera.lens_k1,
        "stray_light": lambda: camera.stray,
    }
    return float(values[n]()) if n in values else e.nominal


def recentred(e: Effect, v: float) -> Effect:
    """``e`` about the nominal ``v`` (another sensor's value): scaled (:data:`SCALED`) or shifted,
    grid points outside the effect's limits dropped, ``v`` itself always on the grid."""
    if e.is_nominal(v):
        return e
    if e.name in SCALED:
        f = v / e.nominal
        move = lambda x: x * f
        limits = tuple(None if b is None else b * f for b in e.limits)
    else:
        move = lambda x: x + (v - e.nominal)
        limits = e.limits
    lo, hi = (-math.inf if limits[0] is None else limits[0]), (math.inf if limits[1] is None else limits[1])
    grid = sorted({round(move(g), 12) for g in e.grid if lo <= move(g) <= hi} | {v})
    blind = tuple(min(max(move(b), lo), hi) for b in e.blind)
    at = None if e.sensitivity_at is None else min(max(move(e.sensitivity_at), lo), hi)
    return dataclasses.replace(e, nominal=float(v), grid=tuple(grid), blind=blind, limits=limits, sensitivity_at=at)


def for_sensor(sensor) -> dict[str, Effect]:
    """The effects library about the sensor ``sensor`` (:class:`elastimap.sensor.Sensor`): each
    effect's nominal is the sensor's value (:func:`value_in`), its grid moved with it
    (:func:`recentred`); effects that do not apply (a layer the probe lacks) are left out.  The
    paper's sensor gives :data:`EFFECTS` itself."""
    from elastimap.solver.params import from_sensor

    p = from_sensor(sensor)
    out = {}
    for name, e in EFFECTS.items():
        v = value_in(e, p, sensor.camera)
        if v is not None:
            out[name] = recentred(e, v)
    return out
