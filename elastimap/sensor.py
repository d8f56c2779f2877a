"""The sensor description: one plain-data record of a lab's sensor that every stage reads.

A sensor is what stays the same from one lesion to the next: the probe (its PDMS layers and
footprint), the tissue slab it presses, how it presses (plate travel or force), the probe-tissue
interface, and the camera below the glass plate.  The lesion (d, h, E) and the discretisation
(mesh level, element degree, symmetry, image pixel) are not part of it.

The paper's sensor (Lee et al. 2014) is the default: ``Sensor()``.  A lab writes a small TOML
file (docs/howto/your-own-sensor.md, "Describe the sensor"); fields it leaves out take the
paper's values::

    name = "lab-A probe 2"

    [probe]
    footprint = 20.0                 # mm, side of the square footprint
    nu = 0.49
    layers = [                       # from the tissue side up: thickness mm, modulus kPa
      { thickness = 2.0, E = 200.0 },
      { thickness = 3.0, E = 150.0 },
      { thickness = 5.0, E = 50.0 },
    ]

    [tissue]                         # the slab: modulus kPa, Poisson ratio, thickness mm
    E = 5.0
    thickness = 20.0

    [loading]                        # plate travel delta (mm); a total force (mN), if given, wins
    delta = 3.0

    [interface]
    model = "tied"                   # tied | contact | bonded

    [camera]                         # every field of elastimap.camera.optics.SensorModel
    window_native = 800

Units: mm, kPa, mN; angles in rad.  The camera's footprint is the probe's (``probe.footprint``,
one value).  :func:`load` reads and checks a file, :func:`dumps` writes one back (all fields),
:meth:`Sensor.hash` is a short canonical hash of the physics (the ``name`` is left out), recorded
with the description in every output.  Nothing here imports a room: the solver turns a
description into solve parameters (:func:`elastimap.solver.params.from_sensor`), the camera
into its model.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import numbers
import os
import tomllib
from dataclasses import dataclass, field
from typing import Any

from .constraints import Interval, Options, check_range, validate_params
from .errors import UserError

#: version of the description's layout (written into every file)
SCHEMA = 1
#: most a camera's ``noise_scale`` may multiply its shot + read noise (beyond it a frame holds noise only)
MAX_NOISE_SCALE = 100.0
#: probe-tissue interface models (solver/interface.py)
INTERFACES = ("tied", "contact", "bonded")
#: mm/kPa, the softest chest wall (``tissue.wall_compliance``; k_w = 0.1 kPa/mm): under the nominal
#: 3 mm press the slab's bottom carries about 1 kPa (docs/forward-model.md, 'Chest wall'), so a softer
#: wall would move more than the plate and the slab float on springs alone (a nearly singular press)
WALL_COMPLIANCE_MAX = 10.0

_POSITIVE_MM = Interval(float, 0, None, closed="neither", unit="mm")
_POSITIVE_KPA = Interval(float, 0, None, closed="neither", unit="kPa")
_POISSON = Interval(float, -1, 0.5, closed="neither")


def _as_floats(obj) -> None:
    """Store the integers given for float fields as floats (``E = 300`` and ``E = 300.0`` are one
    sensor, with one hash); called by the dataclasses' ``__post_init__``."""
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if str(f.type) in ("float", "float | None") and isinstance(v, int) and not isinstance(v, bool):
            object.__setattr__(obj, f.name, float(v))
        elif f.name == "led_power" and isinstance(v, (tuple, list)):
            object.__setattr__(
                obj, f.name, tuple(float(x) if isinstance(x, int) and not isinstance(x, bool) else x for x in v)
            )


@dataclass(frozen=True)
class Layer:
    """One PDMS layer of the probe: thickness (mm) and Young's modulus (kPa)."""

    thickness: float
    E: float

    def __post_init__(self):
        _as_floats(self)


@dataclass(frozen=True)
class ProbeSpec:
    """The soft probe: square footprint (mm), Poisson ratio of its PDMS, layers from the tissue side up.

    One Poisson ratio holds for all layers (the solver's material model takes one for the probe).
    """

    footprint: float = 25.0
    nu: float = 0.49
    layers: tuple[Layer, ...] = (Layer(2.0, 300.0), Layer(3.0, 150.0), Layer(5.0, 50.0))

    def __post_init__(self):
        _as_floats(self)
        object.__setattr__(self, "layers", tuple(self.layers))

    @property
    def height(self) -> float:
        """mm, the probe's total thickness."""
        return float(sum(l.thickness for l in self.layers))


@dataclass(frozen=True)
class SlabSpec:
    """The tissue slab on a rigid chest wall: modulus (kPa), Poisson ratio, thickness and side (mm).

    ``skin_thickness`` > 0 adds a bonded skin layer of modulus ``skin_E``; ``nonlinearity`` in
    [0, 1] blends in compressible neo-Hookean finite strain (0 = linear elastic);
    ``wall_compliance`` (mm/kPa) > 0 makes the chest wall a soft (Winkler) foundation
    (:class:`elastimap.solver.params.Tissue`; 0 = rigid, left out of the description and its hash).
    """

    E: float = 5.0
    nu: float = 0.49
    thickness: float = 20.0
    size: float = 120.0
    skin_thickness: float = 0.0
    skin_E: float = 5.0
    nonlinearity: float = 0.0
    wall_compliance: float = 0.0

    def __post_init__(self):
        _as_floats(self)


@dataclass(frozen=True)
class LoadingSpec:
    """How the plate presses: travel ``delta`` (mm, downward), or a total ``force`` (mN), which when
    given wins (the solver then finds the travel); ``tilt`` (rad) rotates the plate about the y axis
    (needs ``delta`` and the full model)."""

    delta: float = 3.0
    force: float | None = None
    tilt: float = 0.0

    def __post_init__(self):
        _as_floats(self)


@dataclass(frozen=True)
class InterfaceSpec:
    """Probe-tissue interface: ``model`` (tied, contact, bonded) and tangential stiffness
    ``friction_kt`` (kPa/mm; 0 = frictionless)."""

    model: str = "tied"
    friction_kt: float = 0.0

    def __post_init__(self):
        _as_floats(self)


@dataclass(frozen=True)
class CameraSpec:
    """The TIR camera's parameters (the optics model itself: :mod:`elastimap.camera.optics`)."""

    # camera (paper section 2.1)
    sensor_rows: int = 1042
    sensor_cols: int = 1392
    pixel_um: float = 4.65
    binning: int = 10  # software binning (downsampled default); 1 = full resolution
    window_native: int = 1000  # native pixels spanned by the probe footprint (centred)
    footprint_mm: float = 25.0
    # optics of the waveguide
    w_sat: float = 0.5  # mm of probe compression at which scattering reaches 63 % of its maximum
    level: float = 0.7  # full-scattering signal as a fraction of full well (unit illumination)
    stray: float = 0.02  # light reaching the camera with no deformation (fraction of full well)
    led_power: tuple[float, float, float, float] = (1.0, 0.85, 1.1, 0.95)  # left, right, bottom, top
    led_gap: float = 3.0  # mm from the footprint edge to each LED
    led_r0: float = 15.0  # mm, LED fall-off radius
    vignetting: float = 0.15  # relative fall-off at the window corner
    # effect switches (the nominal camera has neither): optical point-spread and response gamma
    blur_mm: float = 0.0  # sigma (mm on the probe) of a Gaussian point-spread of the light image
    gamma: float = 1.0  # response exponent: DN = FS * (electrons / (b^2 FW))^gamma
    lens_k1: float = 0.0  # radial lens distortion: fractional displacement of the footprint corner
    # sensor noise
    full_well_e: float = 9000.0  # electrons per native pixel at full scale
    read_noise_e: float = 10.0  # electrons rms per native pixel
    dark_e: float = 100.0  # offset electrons per native pixel
    bits: int = 16  # 8, 12 (frames in 16-bit files, full scale 4095) or 16
    noise_scale: float = 1.0  # multiplies shot + read noise; 0 = noise-free
    seed: int = 0

    def __post_init__(self):
        _as_floats(self)

    def validate(self):
        """Raise :class:`UserError` naming the first bad field; return self."""
        for name in ("sensor_rows", "sensor_cols", "binning", "window_native", "bits", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral):
                raise UserError(name, f"must be an integer (got {v!r})")
        if self.bits not in (8, 12, 16):
            raise UserError("bits", f"must be 8, 12 or 16 (got {self.bits})")
        if not (1 <= self.binning <= 64):
            raise UserError("binning", f"must be in [1, 64] (got {self.binning})")
        if not (8 <= self.window_native <= min(self.sensor_rows, self.sensor_cols)):
            raise UserError(
                "window_native",
                f"must be in [8, {min(self.sensor_rows, self.sensor_cols)}] native pixels (got {self.window_native})",
            )
        if self.window_native // self.binning < 4:
            raise UserError("binning", "leaves fewer than 4 pixels across the footprint")
        check_range("pixel_um", self.pixel_um, 0, lo_open=True, unit="um")
        check_range("footprint_mm", self.footprint_mm, 0, lo_open=True, unit="mm")
        check_range("w_sat", self.w_sat, 0, lo_open=True, unit="mm")
        check_range("level", self.level, 0, 1, lo_open=True)
        check_range("stray", self.stray, 0, 1)
        if (
            len(self.led_power) != 4
            or any(not math.isfinite(p) or p < 0 for p in self.led_power)
            or sum(self.led_power) <= 0
        ):
            raise UserError("led_power", "needs four non-negative powers (left, right, bottom, top), not all 0")
        check_range("led_gap", self.led_gap, 0, unit="mm")
        check_range("led_r0", self.led_r0, 0, lo_open=True, unit="mm")
        check_range("vignetting", self.vignetting, 0, 0.9)
        check_range("blur_mm", self.blur_mm, 0, 5, unit="mm")
        check_range("gamma", self.gamma, 0.3, 3)
        check_range("lens_k1", self.lens_k1, -0.2, 0.5)
        check_range("full_well_e", self.full_well_e, 1)
        check_range("read_noise_e", self.read_noise_e, 0)
        check_range("dark_e", self.dark_e, 0)
        check_range("noise_scale", self.noise_scale, 0, MAX_NOISE_SCALE)
        if self.seed < 0:
            raise UserError("seed", f"must be >= 0 (got {self.seed})")
        return self


#: what each mechanical field alone must be, under its name in the description
FIELD_CONSTRAINTS = {
    "probe.footprint": [_POSITIVE_MM],
    "probe.nu": [_POISSON],
    "tissue.E": [_POSITIVE_KPA],
    "tissue.nu": [_POISSON],
    "tissue.thickness": [_POSITIVE_MM],
    "tissue.size": [_POSITIVE_MM],
    "tissue.skin_thickness": [Interval(float, 0, None, unit="mm")],
    "tissue.skin_E": [_POSITIVE_KPA],
    "tissue.nonlinearity": [Interval(float, 0, 1)],
    "tissue.wall_compliance": [Interval(float, 0, WALL_COMPLIANCE_MAX, unit="mm/kPa")],
    "loading.delta": [_POSITIVE_MM],
    "loading.force": [None, Interval(float, 0, None, closed="neither", unit="mN")],
    "loading.tilt": [Interval(float, -0.1, 0.1, unit="rad")],
    "interface.model": [Options(INTERFACES)],
    "interface.friction_kt": [Interval(float, 0, None, unit="kPa/mm")],
}


@dataclass(frozen=True)
class Sensor:
    """A whole sensor: probe, tissue slab, loading, interface and camera (the paper's by default)."""

    name: str = "paper"
    probe: ProbeSpec = field(default_factory=ProbeSpec)
    tissue: SlabSpec = field(default_factory=SlabSpec)
    loading: LoadingSpec = field(default_factory=LoadingSpec)
    interface: InterfaceSpec = field(default_factory=InterfaceSpec)
    camera: CameraSpec = field(default_factory=CameraSpec)

    # ------------------------------------------------------------------ checks
    def validate(self) -> Sensor:
        """Raise :class:`UserError` naming the first bad field (``probe.layers[2].E``, ``camera.bits``)."""
        p, t, ld = self.probe, self.tissue, self.loading
        values = {
            **{f"probe.{k}": getattr(p, k) for k in ("footprint", "nu")},
            **{f"tissue.{f.name}": getattr(t, f.name) for f in dataclasses.fields(t)},
            **{f"loading.{f.name}": getattr(ld, f.name) for f in dataclasses.fields(ld)},
            **{f"interface.{f.name}": getattr(self.interface, f.name) for f in dataclasses.fields(self.interface)},
        }
        validate_params(values, FIELD_CONSTRAINTS)
        if not p.layers:
            raise UserError("probe.layers", "at least one layer {thickness, E} is required")
        for i, layer in enumerate(p.layers, 1):
            validate_params(
                {f"probe.layers[{i}].thickness": layer.thickness, f"probe.layers[{i}].E": layer.E},
                {f"probe.layers[{i}].thickness": [_POSITIVE_MM], f"probe.layers[{i}].E": [_POSITIVE_KPA]},
            )
        # the sensor's own geometry (the rules that also involve the lesion stay with the solver)
        if p.footprint >= t.size:
            raise UserError("probe.footprint", f"must be < the slab size tissue.size = {t.size:g} mm")
        if t.thickness > t.size:
            raise UserError("tissue.thickness", f"must be <= the slab size tissue.size = {t.size:g} mm")
        if p.height > t.size / 2:
            raise UserError("probe.layers", f"add up to {p.height:g} mm; at most {t.size / 2:g} mm (tissue.size / 2)")
        if t.skin_thickness > t.thickness / 2:
            raise UserError("tissue.skin_thickness", f"must be <= half the slab thickness ({t.thickness / 2:g} mm)")
        limit = min(p.height, t.thickness) / 2
        if ld.force is None and ld.delta + abs(ld.tilt) * p.footprint / 2 > limit:
            raise UserError(
                "loading.delta",
                f"the plate travels up to {ld.delta + abs(ld.tilt) * p.footprint / 2:g} mm; at most {limit:g} mm "
                "(half the thinner of probe and slab)",
            )
        if ld.tilt != 0 and ld.force is not None:
            raise UserError("loading.tilt", "a tilted plate needs the plate travel delta, not the force")
        if self.camera.footprint_mm != p.footprint:
            raise UserError("camera.footprint_mm", "is the probe's footprint: set probe.footprint only")
        try:
            self.camera.validate()
        except UserError as exc:
            raise UserError(f"camera.{exc.param}", exc.message) from None
        return self

    # ------------------------------------------------------------ plain data
    def to_dict(self) -> dict:
        """Every field, as plain JSON/TOML data (``loading.force`` left out when None)."""
        d = dataclasses.asdict(self)
        d = {"schema": SCHEMA, **d}
        d["probe"]["layers"] = [dict(l) for l in d["probe"]["layers"]]
        d["camera"]["led_power"] = list(self.camera.led_power)
        del d["camera"]["footprint_mm"]  # one value: probe.footprint
        if d["camera"]["lens_k1"] == 0.0:  # no distortion: the descriptions (and hashes) of before
            del d["camera"]["lens_k1"]
        d["loading"] = {k: v for k, v in d["loading"].items() if v is not None}
        if d["tissue"]["wall_compliance"] == 0:  # the rigid chest wall: descriptions and hashes as before
            del d["tissue"]["wall_compliance"]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Sensor:
        """A checked description from plain data; missing fields take the paper's values."""
        return _from_dict(d).validate()

    def hash(self) -> str:
        """16 hex digits of the SHA-256 of the canonical JSON of every field but ``name``."""
        d = self.to_dict()
        del d["name"]
        text = json.dumps(d, sort_keys=True, separators=(",", ":"), allow_nan=False)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def record(self) -> dict:
        """What an output records: ``{"sensor": description, "sensor_hash": hash}``."""
        return {"sensor": self.to_dict(), "sensor_hash": self.hash()}

    @property
    def is_paper(self) -> bool:
        """True for the paper's sensor (whatever its name)."""
        return self.hash() == PAPER_HASH

    def replace(self, **changes) -> Sensor:
        return dataclasses.replace(self, **changes)


# ----------------------------------------------------------------------------- reading and writing
_SECTIONS = {"probe": ProbeSpec, "tissue": SlabSpec, "loading": LoadingSpec, "interface": InterfaceSpec}


def _number(where: str, v: Any, kind: type) -> Any:
    """``v`` as ``kind`` (int or float); a string, a bool or a float given for an int is refused."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise UserError(where, f"must be a number (got {v!r})")
    if kind is int:
        if isinstance(v, float) and not v.is_integer():
            raise UserError(where, f"must be an integer (got {v!r})")
        return int(v)
    return float(v)


def _table(where: str, v: Any) -> dict:
    if not isinstance(v, dict):
        raise UserError(where, f"must be a table of fields (got {v!r})")
    return v


def _fields_of(cls, where: str, given: dict, skip: tuple[str, ...] = ()) -> dict:
    """Check the keys of one section against the dataclass ``cls`` and coerce the numbers."""
    types = {f.name: f.type for f in dataclasses.fields(cls) if f.name not in skip}
    unknown = sorted(set(given) - set(types))
    if unknown:
        raise UserError(f"{where}.{unknown[0]}", f"unknown field (known: {', '.join(types)})")
    out = {}
    for k, v in given.items():
        t = str(types[k])
        if t in ("float", "float | None"):
            out[k] = _number(f"{where}.{k}", v, float)
        elif t == "int":
            out[k] = _number(f"{where}.{k}", v, int)
        elif t == "str":
            if not isinstance(v, str):
                raise UserError(f"{where}.{k}", f"must be a string (got {v!r})")
            out[k] = v
        else:
            out[k] = v  # structured fields are checked by their section
    return out


def _from_dict(d: dict) -> Sensor:
    d = _table("sensor", d)
    known = {"schema", "name", "camera", *_SECTIONS}
    unknown = sorted(set(d) - known)
    if unknown:
        raise UserError(unknown[0], f"unknown section or field (known: {', '.join(sorted(known))})")
    if d.get("schema", SCHEMA) != SCHEMA:
        raise UserError("schema", f"this elastimap reads sensor descriptions of schema {SCHEMA} (got {d['schema']!r})")
    name = d.get("name", "unnamed")
    if not isinstance(name, str) or not name.strip():
        raise UserError("name", f"must be a non-empty string (got {name!r})")
    parts: dict[str, Any] = {}
    for sec, cls in _SECTIONS.items():
        given = _fields_of(cls, sec, _table(sec, d.get(sec, {})))
        if sec == "probe" and "layers" in given:
            given["layers"] = _layers(given["layers"])
        parts[sec] = cls(**given)
    cam = dict(_table("camera", d.get("camera", {})))
    if "footprint_mm" in cam:
        raise UserError("camera.footprint_mm", "is the probe's footprint: set probe.footprint instead")
    cam = _fields_of(CameraSpec, "camera", cam, skip=("footprint_mm",))
    if "led_power" in cam:
        lp = cam["led_power"]
        if not isinstance(lp, list) or len(lp) != 4:
            raise UserError("camera.led_power", f"must be a list of four powers (got {lp!r})")
        cam["led_power"] = tuple(_number(f"camera.led_power[{i}]", v, float) for i, v in enumerate(lp, 1))
    camera = CameraSpec(footprint_mm=parts["probe"].footprint, **cam)
    return Sensor(name=name, camera=camera, **parts)


def _layers(v: Any) -> tuple[Layer, ...]:
    if not isinstance(v, list):
        raise UserError("probe.layers", f"must be a list of {{thickness, E}} tables (got {v!r})")
    out = []
    for i, item in enumerate(v, 1):
        given = _fields_of(Layer, f"probe.layers[{i}]", _table(f"probe.layers[{i}]", item))
        missing = [k for k in ("thickness", "E") if k not in given]
        if missing:
            raise UserError(f"probe.layers[{i}].{missing[0]}", "is required (thickness in mm, E in kPa)")
        out.append(Layer(**given))
    return tuple(out)


def load(path: str | os.PathLike, param: str = "sensor") -> Sensor:
    """Read and check a sensor description (TOML, or the JSON an output recorded); without a
    ``name`` it is named after the file.

    Every problem is one :class:`UserError` under ``param`` (the CLI's ``--sensor``) naming the
    file and the field: ``--sensor: lab.toml: probe.layers[2].E: must be > 0 kPa (got -5)``.
    """
    p = str(path)
    if not os.path.isfile(p):
        raise UserError(param, f"{p}: no such file" if not os.path.exists(p) else f"{p}: not a file")
    try:
        with open(p, "rb") as fh:
            raw = fh.read()
        text = raw.decode("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(param, f"{p}: cannot read ({exc})") from None
    try:
        if p.lower().endswith(".json"):
            data = json.loads(text)
            if isinstance(data, dict) and "sensor" in data and "sensor_hash" in data:
                data = data["sensor"]  # an output's record
        else:
            data = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise UserError(param, f"{p}: not valid {'JSON' if p.lower().endswith('.json') else 'TOML'} ({exc})") from None
    if isinstance(data, dict) and "name" not in data:
        data = {"name": os.path.splitext(os.path.basename(p))[0], **data}  # a file's sensor is named after it
    try:
        return Sensor.from_dict(data)
    except UserError as exc:
        raise UserError(param, f"{p}: {exc.param}: {exc.message}") from None


def dumps(sensor: Sensor, comment: str = "") -> str:
    """The description as TOML text (every field), headed by ``comment`` lines and its hash."""
    import tomli_w

    head = [f"# {line}" if line else "#" for line in comment.splitlines()]
    head += [
        "# elastimap sensor description (docs/howto/your-own-sensor.md); units mm, kPa, mN, rad",
        f"# hash {sensor.hash()}",
    ]
    return "\n".join(head) + "\n\n" + tomli_w.dumps(sensor.to_dict())


PAPER_HASH = Sensor().hash()
