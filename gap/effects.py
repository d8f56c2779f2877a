"""The effects library: unmodelled effects as documented switches with one magnitude each.

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
| saturation | optics | ``SensorModel.w_sat`` | saturation deflection (mm) | 0.5 |
| vignetting | optics | ``SensorModel.vignetting`` | corner fall-off (-) | 0.15 |

``offaxis`` is in the library but not in the default candidate list (a full-model solve costs
about ten quarter-model solves); pass it explicitly with ``--effects``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from elastimap.errors import UserError

SKIN_THICKNESS = 1.0  # mm, thickness of the skin layer switched on by the ``skin`` effect


@dataclass(frozen=True)
class Effect:
    name: str
    stage: str                       # "mechanics" or "optics"
    unit: str
    nominal: float
    grid: tuple[float, ...]          # magnitudes of the fitting sweep (includes the nominal)
    blind: tuple[float, float]       # range of true magnitudes in the self-test
    description: str
    n_params: int = 1
    cost: float = 1.0                # relative solve cost

    @property
    def lo(self) -> float:
        return min(self.grid)

    @property
    def hi(self) -> float:
        return max(self.grid)

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
        if self.name == "offaxis":
            return p.with_inclusion(offset_x=m).replace(disc=r(p.disc, symmetry="full"))
        if self.name == "probe_moduli":
            return p.replace(probe=r(p.probe, layers=tuple((t, E * m) for t, E in p.probe.layers)))
        if self.name == "background_E":
            return p.replace(tissue=r(p.tissue, E=m))
        raise AssertionError(self.name)

    def apply_sensor(self, s, m: float):
        """SensorModel with this effect at magnitude ``m`` (optics effects)."""
        if self.stage != "optics" or self.is_nominal(m):
            return s
        if self.name == "saturation":
            return s.replace(w_sat=float(m))
        if self.name == "vignetting":
            return s.replace(vignetting=float(m))
        raise AssertionError(self.name)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["grid"], d["blind"] = list(self.grid), list(self.blind)
        return d


EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect("nonlinearity", "mechanics", "-", 0.0, (0.0, 0.125, 0.25, 0.375, 0.5, 0.75, 1.0), (0.3, 1.0),
           "tissue nonlinearity: compressible neo-Hookean finite strain (blend fraction β)", cost=5.0),
    Effect("friction", "mechanics", "kPa/mm", 0.0, (0.0, 0.025, 0.05, 0.1, 0.15, 0.275, 0.4, 0.7, 1.0), (0.1, 1.0),
           "probe-tissue friction: tangential interface stiffness k_t (0 = frictionless, inf = bonded)"),
    Effect("skin", "mechanics", "kPa", 5.0, (5.0, 7.5, 10.0, 15.0, 20.0, 30.0, 40.0, 60.0, 80.0), (15.0, 80.0),
           f"stiffer skin layer ({SKIN_THICKNESS:g} mm) on the tissue surface: its modulus"),
    Effect("aspect", "mechanics", "-", 1.0, (0.6, 0.7, 0.8, 0.9, 1.0, 1.125, 1.25), (0.6, 0.8),
           "non-spherical inclusion: ellipsoid, vertical semi-axis = aspect * d/2"),
    Effect("offaxis", "mechanics", "mm", 0.0, (0.0, 1.5, 3.0), (1.5, 3.0),
           "inclusion off the probe axis by offset_x (full model)", cost=10.0),
    Effect("probe_moduli", "mechanics", "-", 1.0, (0.6, 0.7, 0.8, 0.9, 1.0, 1.125, 1.25, 1.375, 1.5), (0.6, 0.75),
           "probe PDMS moduli x factor (cure / temperature)"),
    Effect("background_E", "mechanics", "kPa", 5.0, (3.5, 3.875, 4.25, 4.625, 5.0, 5.5, 6.0, 6.5, 7.0), (6.0, 7.0),
           "background tissue modulus different from nominal"),
    Effect("saturation", "optics", "mm", 0.5, (0.15, 0.2, 0.25, 0.3, 0.35, 0.425, 0.5, 0.6, 0.7), (0.15, 0.3),
           "optical response: scattering saturates at a different deflection w_sat (gamma/saturation)"),
    Effect("vignetting", "optics", "-", 0.15, (0.0, 0.075, 0.15, 0.225, 0.3, 0.375, 0.45, 0.525, 0.6), (0.35, 0.6),
           "non-uniform illumination: lens/LED fall-off towards the window corners"),
)}

DEFAULT_CANDIDATES = tuple(n for n in EFFECTS if n != "offaxis")


def get(name: str) -> Effect:
    if name not in EFFECTS:
        raise UserError("effect", f"unknown effect {name!r}; known: {', '.join(EFFECTS)}")
    return EFFECTS[name]


def parse_list(text: str | None, default=DEFAULT_CANDIDATES) -> list[Effect]:
    if text is None or text.strip() == "":
        return [EFFECTS[n] for n in default]
    names = [t.strip() for t in text.split(",") if t.strip()]
    if len(set(names)) != len(names):
        raise UserError("effects", "names an effect twice")
    return [get(n) for n in names]


def parse_spec(text: str) -> list[tuple[Effect, float]]:
    """``"friction=0.3,skin=40"`` -> [(Effect, magnitude), ...]."""
    out = []
    for part in [t.strip() for t in text.split(",") if t.strip()]:
        if "=" not in part:
            raise UserError("effect", f"{part!r}: use NAME=MAGNITUDE (e.g. friction=0.3)")
        name, val = part.split("=", 1)
        e = get(name.strip())
        try:
            m = float(val)
        except ValueError:
            raise UserError("effect", f"{part!r}: magnitude must be a number") from None
        if not (min(e.lo, e.nominal) - 1e-12 <= m <= max(e.hi, e.nominal) * 1.5 + 1e-12) or m < 0:
            raise UserError("effect", f"{e.name}={m:g} is outside the supported range "
                                      f"[{e.lo:g}, {1.5 * e.hi:g}] {e.unit}")
        out.append((e, m))
    if len({e.name for e, _ in out}) != len(out):
        raise UserError("effect", "names an effect twice")
    return out
