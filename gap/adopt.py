"""Adopting what a diagnosis found: the sensor description with the identified effect(s) at their
fitted magnitude (``adopted-sensor.toml``), so the loop closes with the ordinary commands
(docs/howto/your-own-sensor.md, "Adopt and repeat").

Each effect is applied by its own switch (:meth:`elastimap.gap.effects.Effect.apply_params` on the
sensor's solve parameters, :meth:`~elastimap.gap.effects.Effect.apply_sensor` on its camera) and
read back into the description (:func:`elastimap.solver.params.to_sensor`), so an effect means
the same thing in the diagnosis and in the adopted sensor.  An effect that changes the lesion
rather than the sensor (an inclusion's aspect ratio or its offset from the probe axis: a
phantom-making error) is reported, not adopted.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from elastimap.sensor import Sensor
from elastimap.solver.params import from_sensor, to_sensor

from . import effects as fx

#: the file ``gap diagnose`` writes into its ``--out`` (one of ``gap.report.REPORT_FILES``)
ADOPTED = "adopted-sensor.toml"


@dataclass
class Adoption:
    """The adopted description and, per effect, what was done with it."""

    sensor: Sensor
    rows: list[dict] = field(default_factory=list)  # {effect, magnitude, unit, adopted, why}

    @property
    def adopted(self) -> list[str]:
        return [r["effect"] for r in self.rows if r["adopted"]]

    @property
    def reported_only(self) -> list[str]:
        return [r["effect"] for r in self.rows if not r["adopted"]]


def apply_effect(sensor: Sensor, e: fx.Effect, m: float) -> Sensor | None:
    """``sensor`` with effect ``e`` at magnitude ``m``; None when ``e`` is not a sensor property.

    ``e`` must be the effect about ``sensor`` (:func:`elastimap.gap.effects.for_sensor`): its
    nominal is the sensor's own value, which leaves the sensor as it is.
    """
    if e.stage == "optics":
        from elastimap.camera.optics import SensorModel

        return sensor.replace(camera=e.apply_sensor(SensorModel.of(sensor), m).spec())
    p = from_sensor(sensor)
    q = e.apply_params(p, m)
    if q.inclusion != p.inclusion:
        return None
    return to_sensor(q, sensor)


def adopt(sensor: Sensor, found: dict[str, list[float]], name: str | None = None) -> Adoption:
    """The description ``sensor`` with every effect of ``found`` (effect name -> fitted magnitudes,
    one per member of a family, as a diagnosis reports them) at its magnitude.

    Effects are applied in the order given; the result is named ``name`` (default: the sensor's
    name with ``+adopted``) and validated.
    """
    table = fx.for_sensor(sensor)
    out = sensor
    rows = []
    for effect, mags in found.items():
        members = list(fx.FAMILIES[effect].members) if effect in fx.FAMILIES else [effect]
        if len(members) != len(mags):
            raise ValueError(f"{effect}: {len(mags)} magnitudes for {len(members)} parameters")
        for member, m in zip(members, mags):
            e = table.get(member)
            new = None if e is None else apply_effect(out, e, float(m))
            row = {"effect": member, "magnitude": float(m), "unit": fx.get(member).unit, "adopted": new is not None}
            if effect != member:
                row["via"] = effect
            if e is None:
                row["why"] = "does not apply to this sensor"
            elif new is None:
                row["why"] = "a property of the lesion or phantom, not of the sensor: reported, not adopted"
            else:
                row["nominal"] = e.nominal
                out = new
            rows.append(row)
    if any(r["adopted"] for r in rows):
        out = out.replace(name=name or f"{sensor.name}+adopted")
    return Adoption(out.validate(), rows)


def from_diagnosis(res: dict, sensor: Sensor) -> tuple[Adoption, str]:
    """What a diagnosis ``res`` (:func:`elastimap.gap.diagnose.diagnose`) adopts into ``sensor``, and
    a one-line note: only an explained gap is adopted (its winner at the fitted magnitudes); an
    ambiguous one names the candidates and adopts nothing, as does no significant gap."""
    ev = res["evaluation"]
    outcome = ev["outcome"]
    if outcome != "explained":
        why = {
            "no significant gap": "no gap beyond the model-form level: nothing to adopt"
            if ev.get("model_form")
            else "no significant gap: nothing to adopt",
            "ambiguous": "ambiguous (" + ", ".join(ev.get("ambiguous_set", [])) + "): nothing adopted; "
            "the report says which measurement separates them",
            "unexplained": "unexplained by the candidates: nothing to adopt",
        }.get(outcome, f"{outcome}: nothing adopted")
        return Adoption(sensor), why
    winner = ev["winner"]
    row = ev["reported"][winner]
    if row["_row"].get("pair"):  # two effects at once: each at its fitted magnitude
        spec = {n: [float(m)] for n, m in zip(row["members"], row["magnitude"])}
    else:
        name = winner if winner in fx.FAMILIES and len(row["magnitude"]) > 1 else row["members"][0]
        spec = {name: [float(m) for m in row["magnitude"]]}
    a = adopt(sensor, spec)
    for r in a.rows:
        ci = row["magnitude_ci"][row["members"].index(r["effect"])] if r["effect"] in row["members"] else None
        r["magnitude_ci"] = ci
    done = ", ".join(f"{r['effect']} = {r['magnitude']:.4g} {r['unit']}" for r in a.rows if r["adopted"])
    kept = ", ".join(f"{r['effect']} ({r['why']})" for r in a.rows if not r["adopted"])
    note = (f"adopted {done}" if done else "nothing adopted") + (f"; reported, not adopted: {kept}" if kept else "")
    return a, note


def record(a: Adoption, note: str, before: Sensor) -> dict:
    """The ``adoption`` entry of ``diagnosis.json``."""
    return {
        "note": note,
        "rows": a.rows,
        "file": ADOPTED if a.adopted else None,
        "from": before.record(),
        "adopted": a.sensor.record() if a.adopted else None,
    }
