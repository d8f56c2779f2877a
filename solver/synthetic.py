"""A SYNTHETIC analytic stand-in for the forward model — for fast tests only, *not* physics.

It answers like :func:`elastimap.solver.solve` (a :class:`~elastimap.solver.params.SolveResult`
from :class:`~elastimap.solver.params.SolveParams`) in about a millisecond, so the sweep, the
solve store, the camera chain and the gap logic can be tested without DOLFINx.  It is passed in
explicitly wherever solves run (``solver=`` of the sweep, ``backend="toy"``/``solver=`` of
:class:`elastimap.gap.simulate.Simulator`); rows it produces are labelled ``synthetic`` in the
sample table's ``solver`` column.  Never use it for results.

The difference image is a radial bump on the pixel grid of the probe footprint,

    w(r) = A · exp(-(r / W)^p),        r = |(x, y) - (offset_x, offset_y)|   (mm)

    A = 0.03 (δ/3) (d/8)^2.2 (8/h)^1.6 (max(E - E_t, 0)/45)^0.6 · s_A      (mm)
    W = 0.35 d (1 - 0.2 ln(E/50)) + 0.25 h · s_W                           (mm)
    p = (1 + 0.12 h) (1 + 0.1 f)

with d, h in mm, E and the tissue modulus E_t in kPa and δ the indentation in mm: height, width
and profile sharpness depend on (d, h, E) differently, so the three features identify the three
parameters.  The factors s_A, s_W and f react to every effect switch of ``SolveParams``
(finite strain, interface stiffness k_t, a skin layer, the aspect ratio, the probe's first-layer
modulus, the chest wall's compliance c_w: s_A = e^(−c_w (0.3 + 0.03 h)), s_W = 1 + 0.12 c_w, the force
÷ (1 + 0.35 c_w), c_w in mm/kPa) so that the gap diagnosis can tell them apart.  The raw image adds a flat-punch-like
probe compression with edge peaks; the force (mN) grows with √E_t.  Displacement loading only
(``loading.force`` is ignored).

:class:`SyntheticSolver` adds fault injection for the sweep's crash tests: a chosen inclusion
diameter makes the process segfault, hang or raise :class:`SyntheticSolverError`.
"""

from __future__ import annotations

import ctypes
import os
import time
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from elastimap.errors import UserError

from .image import features, pixel_centres
from .params import ImageSpec, SolveParams, SolveResult

#: the label of this stand-in's rows in the sample table's ``solver`` column
SOLVER_NAME = "synthetic"


class SyntheticSolverError(RuntimeError):
    """The failure :class:`SyntheticSolver` raises on purpose (``fail_d``)."""


def synthetic_solve(p: SolveParams) -> SolveResult:
    """The SYNTHETIC analytic model of the module docstring (no validation, no faults)."""
    t0 = time.perf_counter()
    inc, t, probe = p.inclusion, p.tissue, p.probe
    pixel, size, delta = p.image.pixel, probe.size, p.loading.delta
    x = pixel_centres(size, pixel)
    X, Y = np.meshgrid(x, x)
    a = size / 2
    kprobe = probe.layers[0][1] / 300.0
    edge = np.exp(-(a - np.abs(X))) + np.exp(-(a - np.abs(Y)))
    base = 0.08 * (delta / 3.0) * (1.0 + 0.8 * edge) * (1 - 0.2 * (X**2 + Y**2) / (2 * a * a)) / kprobe**0.5
    beta, kt = t.nonlinearity, p.disc.friction_kt
    fk = kt / (kt + 0.3)
    skin = np.log(t.skin_E / t.E) if t.skin_thickness > 0 else 0.0
    amp = 0.03 * (delta / 3.0) * (inc.d / 8.0) ** 2.2 * (8.0 / inc.h) ** 1.6 * (max(inc.E - t.E, 0.0) / 45.0) ** 0.6
    amp *= (1 + 0.5 * beta * inc.d / 8.0) * (1 + 0.06 * fk) * np.exp(-0.12 * skin * 8.0 / inc.h)
    amp *= inc.aspect**0.9 * kprobe**-0.35
    cw = t.wall_compliance  # mm/kPa: a soft chest wall takes part of the press, more so under deep inclusions
    amp *= np.exp(-cw * (0.3 + 0.03 * inc.h))
    width = 0.35 * inc.d * (1.0 - 0.2 * np.log(inc.E / 50.0)) + 0.25 * inc.h
    width *= (1 - 0.04 * beta) * (1 + 0.2 * fk) * (1 + 0.1 * skin) * inc.aspect**0.25 * kprobe**0.3
    width *= 1 + 0.12 * cw
    prof = (1.0 + 0.12 * inc.h) * (1 + 0.1 * fk)
    R = np.sqrt((X - inc.offset_x) ** 2 + (Y - inc.offset_y) ** 2)
    diff = amp * np.exp(-((R / width) ** prof))
    o1, o2, o3 = features(diff, pixel, p.image.threshold, p.image.supersample)
    force = 1400.0 * (t.E / 5.0) ** 0.5 * (1 + 0.2 * beta) * (1 + 0.1 * fk) / (1 + 0.35 * cw)
    return SolveResult(
        params=p,
        O1=o1,
        O2=o2,
        O3=o3,
        force=force,
        force_ref=force,
        delta=delta,
        image=diff,
        image_raw=base + diff,
        pixel=pixel,
        ndofs=0,
        ncells=0,
        newton_iterations=0,
        seconds=time.perf_counter() - t0,
        timings={},
        peak_memory_mb=0.0,
    )


synthetic_solve.solver_name = SOLVER_NAME


def solve_dhe(
    d: float, h: float, E: float, *, tissue_E: float = 5.0, delta: float = 3.0, supersample: int = 4
) -> SolveResult:
    """:func:`synthetic_solve` of the default setup with inclusion (d mm, h mm, E kPa), tissue modulus
    ``tissue_E`` kPa and indentation ``delta`` mm (the camera tests' shorthand)."""
    p = SolveParams(image=ImageSpec(supersample=supersample)).with_inclusion(d=float(d), h=float(h), E=float(E))
    p = p.replace(tissue=replace(p.tissue, E=float(tissue_E)), loading=replace(p.loading, delta=float(delta)))
    return synthetic_solve(p)


def _diameters(value) -> tuple[float, ...]:
    if isinstance(value, (int, float)):
        return (float(value),)
    return tuple(float(v) for v in value)


@dataclass(frozen=True)
class SyntheticSolver:
    """The stand-in as a solver: ``SyntheticSolver(...)(params) -> SolveResult``.

    ``seconds``: each solve sleeps this long.  ``crash_d`` / ``hang_d`` / ``fail_d``: inclusion
    diameters (mm) at which the process dies with SIGSEGV (as a crashing solver would), sleeps
    an hour (a hung solve) or raises :class:`SyntheticSolverError`; ``crash_E``: inclusion moduli
    (kPa) at which it dies (one sample of a geometry's group, ``sweep run --moduli-per-mesh``).  ``log``: a file that gets
    one line ``d h E pid`` per solve started.  Instances pickle by module path, so dask workers
    receive them as task arguments.
    """

    seconds: float = 0.0
    crash_d: tuple[float, ...] = ()
    hang_d: tuple[float, ...] = ()
    fail_d: tuple[float, ...] = ()
    crash_E: tuple[float, ...] = ()
    log: str | None = None

    solver_name: ClassVar[str] = SOLVER_NAME

    def __post_init__(self):
        for name in ("crash_d", "hang_d", "fail_d", "crash_E"):
            object.__setattr__(self, name, _diameters(getattr(self, name)))

    @classmethod
    def from_spec(cls, text: str) -> SyntheticSolver:
        """Parse ``synthetic[:KEY=VALUE,...]``, e.g. ``synthetic:seconds=0.1,crash_d=7.5,fail_d=4|5,log=/tmp/x``
        (diameter lists separated by ``|``)."""
        name, _, rest = text.partition(":")
        if name != SOLVER_NAME:
            raise UserError("solver", f"must be 'fem' or 'synthetic[:KEY=VALUE,...]' (got {text!r})")
        kw: dict = {}
        for item in filter(None, (s.strip() for s in rest.split(","))):
            key, eq, value = item.partition("=")
            if not eq or key not in ("seconds", "crash_d", "hang_d", "fail_d", "crash_E", "log"):
                raise UserError(
                    "solver",
                    f"unknown synthetic option {item!r} (known: seconds, crash_d, hang_d, fail_d, crash_E, log)",
                )
            try:
                kw[key] = (
                    value
                    if key == "log"
                    else float(value)
                    if key == "seconds"
                    else tuple(float(v) for v in value.split("|") if v)
                )
            except ValueError:
                raise UserError("solver", f"{key}: not a number ({value!r})") from None
        return cls(**kw)

    def warmup(self, params: SolveParams) -> None:
        """Nothing to compile (the sweep calls this before it fans out)."""

    def __call__(self, params: SolveParams) -> SolveResult:
        p = params.validate()
        d = p.inclusion.d
        if self.log:
            fd = os.open(self.log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            os.write(fd, f"{d:g} {p.inclusion.h:g} {p.inclusion.E:g} {os.getpid()}\n".encode())
            os.close(fd)
        t0 = time.perf_counter()
        time.sleep(self.seconds)
        if any(abs(d - v) < 1e-9 for v in self.crash_d) or any(abs(p.inclusion.E - v) < 1e-9 for v in self.crash_E):
            ctypes.string_at(0)  # SIGSEGV
        if any(abs(d - v) < 1e-9 for v in self.hang_d):
            time.sleep(3600)
        if any(abs(d - v) < 1e-9 for v in self.fail_d):
            raise SyntheticSolverError(
                f"synthetic divergence for d={d:g} mm, h={p.inclusion.h:g} mm, E={p.inclusion.E:g} kPa"
            )
        res = synthetic_solve(p)
        res.seconds = time.perf_counter() - t0
        return res


#: the stand-in without faults: ``solve(params) -> SolveResult``
solve = SyntheticSolver()
