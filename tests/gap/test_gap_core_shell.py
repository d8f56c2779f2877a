"""The ``core_shell`` effect: a lesion's own effect kept outside the default candidates to test the
library's reach (docs/gap.md, 'Effects library')."""

from elastimap.gap import adopt
from elastimap.gap import effects as fx
from elastimap.sensor import Sensor
from elastimap.solver.params import SolveParams


def test_core_shell_is_an_outside_effect_of_the_lesion():
    e = fx.get("core_shell")
    assert e.stage == "mechanics" and "core_shell" in fx.OUTSIDE_ONLY and "core_shell" not in fx.DEFAULT_CANDIDATES
    assert "core_shell" in fx.REMESHING and e.own_model_error  # a new mesh (the core's surface) each
    p = SolveParams()
    assert e.apply_params(p, e.nominal) == p
    q = e.apply_params(p, 3.0)
    assert (q.inclusion.core, q.inclusion.core_ratio) == (fx.CORE_FRACTION, 3.0)
    assert q.validate().with_inclusion(core=0.0, core_ratio=1.0) == p
    # a property of the phantoms, not of the sensor: reported, never adopted
    assert adopt.apply_effect(Sensor(), fx.for_sensor(Sensor())["core_shell"], 3.0) is None
    assert fx.parse_spec("core_shell=2.5")[0][1] == 2.5
