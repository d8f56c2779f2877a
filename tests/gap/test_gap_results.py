"""What a diagnosis's result carries: the solve seconds by effect travel in the result (no state
kept between diagnoses in one process), and the residual map's pixel size.  TOY backend (not
physics: it only exercises the gap logic)."""

from elastimap.gap import effects as fx
from elastimap.gap import synth
from elastimap.gap.diagnose import diagnose
from elastimap.gap.settings import Settings
from elastimap.gap.simulate import Simulator


def test_solve_seconds_travel_in_each_result_and_nothing_carries_over():
    sim = Simulator(None, "tiny", "toy")
    dhe = synth.phantom_design(6, 3)
    meas, _ = synth.synthesize(dhe, [(fx.get("friction"), 0.4)], sim, frames=4, seed=1)
    st = Settings(inverse=False, bootstrap=10)
    a = diagnose(meas, fx.parse_list("friction,background_E,saturation"), sim, st, Simulator(None, "coarse", "toy"))
    b = diagnose(meas, fx.parse_list("tissue_nu,blur"), sim, st)
    # solved effects (mechanics) and the baseline have entries; optics costs no solves
    assert set(a["solve_seconds_by_effect"]) == {"baseline", "friction", "background_E", "error_mesh"}
    # the second diagnosis reports its own solves only: nothing of the first one's
    assert set(b["solve_seconds_by_effect"]) == {"baseline", "tissue_nu"}
    for res in (a, b):
        assert all(v >= 0 for v in res["solve_seconds_by_effect"].values())
        assert set(res["timing"]) == {"candidates", "model_error", "refine", "evaluate", "rest"}
    assert a["where"]["image"]["pixel_mm"] == meas.sensor_model().pixel_mm
