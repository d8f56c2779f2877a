"""SYNTHETIC measured data: the baseline forward model plus unmodelled effects, through the
camera model with noise.  Everything it writes says SYNTHETIC.

``synthesize(phantoms, effects, sim, ...)``: for every phantom (d, h, E) the mechanics effects
switch the solver, the optics effects switch the camera (:class:`elastimap.camera.optics.SensorModel`),
``frames`` noisy lesion and background frames are rendered and the camera features (with their
standard errors from the frame scatter) and the denoised difference image are kept; a label effect
(a phantom-labelling error, :meth:`elastimap.gap.effects.Effect.apply_label`) leaves the data of the
true phantom and writes phantom ``label_phantom``'s d, h or E wrong in the table.  The true
effects are returned separately (and written to ``SEALED_truth.json``, never read by the
diagnosis).
"""

from __future__ import annotations

import base64
import dataclasses
import json
import os
from pathlib import Path

import numpy as np
from scipy.stats import qmc

from elastimap.camera.features import FeatureSettings
from elastimap.camera.optics import MAX_NOISE_SCALE, SensorModel, render_pair
from elastimap.constraints import Interval, validate_params
from elastimap.errors import UserError
from elastimap.outputs import check_out_dir, is_empty_dir
from elastimap.tables import check_name

from . import effects as fx
from .measured import SEALED, SIDECAR, TABLE_NAMES, Measured
from .simulate import Simulator, base_params
from .views import from_frames

DEFAULT_N = 12
MAX_PHANTOMS = 100_000  # phantoms of one synthetic set (each is a forward solve)
MAX_FRAMES = 10_000  # frames per phantom: a stack of this many is already gigabytes


def check_out(out: str | os.PathLike, overwrite: bool = False) -> Path:
    """Refuse an output folder a generator must not write into (checked before any solve).

    A folder that holds files is refused unless ``overwrite`` is given AND it holds a
    SYNTHETIC measured dataset (its ``measured.json`` says ``"synthetic": true``); real
    measured data (``"synthetic": false``, or no readable sidecar) and any other content are
    never replaced by a generator, with or without ``overwrite``."""
    p = Path(out)
    if p.is_dir() and not is_empty_dir(p):
        side = p / SIDECAR
        info = None
        if side.is_file():
            try:
                info = json.loads(side.read_text())
            except (OSError, ValueError):
                info = None
        if not isinstance(info, dict):
            raise UserError(
                "out",
                f"{p} holds files that are not a SYNTHETIC measured dataset; "
                "a generator never writes there (choose another folder)",
            )
        if info.get("synthetic") is not True:
            raise UserError(
                "out",
                f"{p} holds real (non-synthetic) measured data; a generator never overwrites "
                "it, not even with --overwrite (choose another folder)",
            )
        foreign = sorted(x.name for x in p.iterdir() if not _written_by_synth(x))
        if foreign:
            shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
            raise UserError(
                "out",
                f"{p} holds a SYNTHETIC measured dataset and files gap synth did not write ({shown}); "
                "a generator never replaces them, not even with --overwrite (move them, or choose another folder)",
            )
        if not overwrite:
            raise UserError("out", f"{p} already holds a SYNTHETIC measured dataset; give --overwrite to replace it")
    return check_out_dir(p, "out", overwrite=overwrite)


def _written_by_synth(x: Path) -> bool:
    """Whether ``x`` is a file of the kind :func:`elastimap.gap.measured.write` and :func:`seal` write
    for a SYNTHETIC dataset (its table, sidecar, sealed truth, ``synthetic_*.npy`` images)."""
    if not x.is_file() or x.is_symlink():
        return False
    return x.name in (*TABLE_NAMES, SIDECAR, SEALED) or (x.name.startswith("synthetic_") and x.suffix == ".npy")


def phantom_design(n: int = DEFAULT_N, seed: int = 0) -> np.ndarray:
    """(n, 3) phantom (d, h, E): LHS over d 5-12 mm, E 30-150 kPa (log), depth valid for every
    effect of the library (ellipsoid up to aspect 1.25, 1 mm skin layer)."""
    validate_params({"n": n, "seed": seed}, {"n": [Interval(int, 1, MAX_PHANTOMS)], **_parameter_constraints})
    u = qmc.LatinHypercube(d=3, rng=np.random.default_rng(seed)).random(n)
    d = 5.0 + 7.0 * u[:, 0]
    half = 1.25 * d / 2
    lo, hi = half + 1.6, np.minimum(14.0, 18.0 - half)
    h = lo + u[:, 1] * (hi - lo)
    E = np.exp(np.log(30.0) + u[:, 2] * np.log(150.0 / 30.0))
    return np.round(np.column_stack([d, h, E]), 3)


#: What each setting of :func:`synthesize` alone must be (checked before any solve).
_parameter_constraints = {
    "frames": [Interval(int, 1, MAX_FRAMES)],
    "seed": [Interval(int, 0, None)],
    "noise_scale": [Interval(float, 0, MAX_NOISE_SCALE)],
    "force_noise": [None, Interval(float, 0, 1, closed="right")],
}


def synthesize(
    dhe: np.ndarray,
    effects: list[tuple[fx.Effect, float]],
    sim: Simulator,
    sensor=None,
    settings=None,
    frames: int = 10,
    seed: int = 0,
    ids: list[str] | None = None,
    noise_scale: float = 1.0,
    disc: dict | None = None,
    force_noise: float | None = None,
    description=None,
    label_phantom: int = 0,
) -> tuple[Measured, dict]:
    """``disc`` overrides fields of the solver's ``Discretisation`` (e.g. ``{"interface": "contact"}``)
    so that the data come from another formulation than the diagnosis; ``force_noise`` (relative
    standard error) adds a measured plate force.  ``description``: the lab's sensor
    (:class:`elastimap.sensor.Sensor`; default the paper's), whose camera is ``sensor`` unless
    given; ``effects`` come on top of it (take them from ``effects.for_sensor(description)``).
    ``label_phantom``: the index of the phantom whose table entry a label effect changes (the
    solves and frames are of the true ``dhe``)."""
    validate_params(
        {"frames": frames, "seed": seed, "noise_scale": noise_scale, "force_noise": force_noise},
        _parameter_constraints,
    )
    for id_ in ids or ():
        check_name(id_, "ids", "id")
    if not 0 <= label_phantom < len(dhe):
        raise UserError("label-phantom", f"must name one of the {len(dhe)} phantoms (got index {label_phantom})")
    if sensor is None and description is not None:
        sensor = SensorModel.of(description)
    sensor = (sensor or SensorModel()).validate()
    settings = settings or FeatureSettings()
    true_sensor = sensor.replace(noise_scale=noise_scale)
    plist = []
    for row in dhe:
        p = base_params(sim.mesh, *row, sensor=description)
        if disc:
            p = p.replace(disc=dataclasses.replace(p.disc, **disc))
        for e, m in effects:
            if e.stage == "mechanics":
                p = e.apply_params(p, m)
        plist.append(p)
    for e, m in effects:
        if e.stage == "optics":
            true_sensor = e.apply_sensor(true_sensor, m)
    table = _labelled(dhe, effects, label_phantom, sim.mesh, description)
    recs = sim.run(plist)
    rng = np.random.default_rng(seed)
    y, se, D, Dse = [], [], [], []
    bad = [i for i, r in enumerate(recs) if not np.isfinite(r.O1)]
    if bad:
        raise UserError("synth", f"the forward solve failed for phantom(s) {bad} with these effects")
    for r in recs:
        L, B = render_pair(true_sensor, r.image_raw, r.image, r.pixel, frames, rng)
        v = from_frames(L, B, true_sensor, settings)
        y.append(v["values"])
        se.append(v["se"])
        D.append(v["difference"])
        Dse.append(v["difference_se"])
    n = len(dhe)
    force = np.full(n, np.nan)
    force_se = np.zeros(n)
    if force_noise:
        F = np.array([r.force for r in recs])
        force_se = force_noise * F
        force = F + rng.normal(0.0, 1.0, n) * force_se
    ids = ids or [f"P{i + 1:02d}" for i in range(n)]
    label = ", ".join(f"{e.name}={m:g}" for e, m in effects) or "none"
    form = f"mesh {sim.mesh}" + "".join(f", {k} {v}" for k, v in (disc or {}).items())
    meas = Measured(
        ids,
        table,
        np.asarray(y),
        np.asarray(se),
        np.full(n, np.nan),
        D,
        sensor.to_dict(),
        settings.to_dict(),
        sim.mesh,
        True,
        f"SYNTHETIC measured data: forward model ({form}) + sealed unmodelled effect(s), {frames} frames, "
        f"noise_scale {noise_scale:g}, seed {seed}, backend {sim.backend}",
        "synthetic",
        Dse,
        force,
        force_se,
        description,
    )
    truth = {"effects": [{"name": e.name, "magnitude": float(m), "unit": e.unit} for e, m in effects], "label": label}
    if any(e.stage == "label" for e, _ in effects):
        truth["label_phantom"] = ids[label_phantom]
        truth["true_dhe"] = [float(x) for x in np.asarray(dhe, float)[label_phantom]]
    return meas, truth


def _labelled(dhe, effects, i: int, mesh: str, description) -> np.ndarray:
    """The table the data are written with: ``dhe`` with the label effects applied to phantom ``i``
    (checked to be a phantom a diagnosis accepts, before any solve)."""
    table = np.asarray(dhe, float)
    labels = [(e, m) for e, m in effects if e.stage == "label"]
    for e, m in labels:
        table = e.apply_label(table, m, i)
    if labels:
        try:
            base_params(mesh, *table[i], sensor=description).validate()
        except UserError as exc:
            raise UserError(
                "effect", f"the mislabelled phantom {i + 1} is no valid phantom ({exc.param}: {exc.message})"
            ) from None
    return table


def seal(truth: dict, folder: str | Path) -> Path:
    """Write the truth base64-wrapped (not secret, just not readable at a glance)."""
    p = Path(folder) / SEALED
    blob = base64.b64encode(json.dumps(truth).encode()).decode()
    p.write_text(json.dumps({"sealed": blob, "note": "SYNTHETIC truth; the diagnosis never reads this file"}) + "\n")
    return p


def unseal(folder: str | Path) -> dict:
    d = json.loads((Path(folder) / SEALED).read_text())
    return json.loads(base64.b64decode(d["sealed"]))
