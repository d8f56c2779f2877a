"""Outside-only effects (docs/gap.md, 'Effects library'): the core/shell inclusion and the
phantom-labelling errors make SYNTHETIC data for the out-of-library checks and are never
candidates (the lens distortion, once outside-only, is a candidate: tests/gap/test_gap_lens.py).
TOY backend (not physics): it only exercises the data and the selftest's draws."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from elastimap.camera.optics import SensorModel
from elastimap.errors import UserError
from elastimap.gap import effects as fx
from elastimap.gap import selftest, synth
from elastimap.gap.settings import Settings
from elastimap.gap.simulate import Simulator

ROOT = Path(__file__).resolve().parents[2]
NEW = ("core_shell", "mislabel_d", "mislabel_h", "mislabel_E")


@pytest.fixture(scope="module")
def dhe():
    return synth.phantom_design(6, 0)


def test_outside_only_effects_are_never_candidates():
    assert set(NEW) == fx.OUTSIDE_ONLY and not fx.OUTSIDE_ONLY & set(fx.DEFAULT_CANDIDATES)
    assert fx.OUTSIDE_ONLY <= set(fx.EFFECTS)
    for n in NEW:
        with pytest.raises(UserError, match="not a candidate"):
            fx.parse_list(f"friction,{n}")
    assert sorted(e.name for e in fx.parse_list(",".join(NEW), outside_only=True)) == sorted(NEW)
    assert not fx.OUTSIDE_ONLY & {e.name for e in selftest.default_candidates()}
    ((e, m),) = fx.parse_spec("lens_distortion=0.2")
    assert e.apply_sensor(SensorModel(), m).lens_k1 == 0.2
    assert e.apply_sensor(SensorModel(), 0.0) == SensorModel()
    for bad in ("lens_distortion=0.9", "mislabel_d=-0.9"):
        with pytest.raises(UserError):
            fx.parse_spec(bad)


def test_apply_label_changes_one_entry():
    t = np.array([[8.0, 9.0, 50.0], [6.0, 7.0, 100.0]])
    for name, col in (("mislabel_d", 0), ("mislabel_h", 1), ("mislabel_E", 2)):
        out = fx.get(name).apply_label(t, 0.15, 1)
        want = t.copy()
        want[1, col] *= 1.15
        np.testing.assert_array_equal(out, want)
    assert fx.get("friction").apply_label(t, 0.3, 0) is not t  # other stages: a copy, unchanged
    np.testing.assert_array_equal(fx.get("mislabel_d").apply_label(t, 0.0, 0), t)


def test_mislabelled_phantom_keeps_the_true_data(toy, dhe):
    """The data (features, images) are the true phantoms'; only the table entry is wrong."""
    ref, _ = synth.synthesize(dhe, [], toy, frames=3, seed=4)
    meas, truth = synth.synthesize(dhe, [(fx.get("mislabel_h"), -0.2)], toy, frames=3, seed=4, label_phantom=2)
    np.testing.assert_array_equal(meas.y, ref.y)
    np.testing.assert_array_equal(meas.difference[2], ref.difference[2])
    want = np.array(dhe, float)
    want[2, 1] *= 0.8
    np.testing.assert_array_equal(meas.dhe, want)
    assert truth["label_phantom"] == "P03" and truth["true_dhe"] == [float(x) for x in dhe[2]]
    with pytest.raises(UserError, match="label-phantom"):
        synth.synthesize(dhe, [(fx.get("mislabel_h"), -0.2)], toy, frames=3, label_phantom=6)
    deep = int(np.argmax(dhe[:, 1]))  # a table no diagnosis would accept is refused before any solve
    with pytest.raises(UserError, match="no valid phantom"):
        synth.synthesize(dhe, [(fx.get("mislabel_h"), 0.45)], toy, frames=3, label_phantom=deep)


def test_distorted_camera_changes_the_data_and_an_optics_effect_applies_once(toy, dhe):
    ref, _ = synth.synthesize(dhe, [], toy, frames=3, seed=4, noise_scale=0.0)
    dist, truth = synth.synthesize(dhe, [(fx.get("lens_distortion"), 0.3)], toy, frames=3, seed=4, noise_scale=0.0)
    assert not np.allclose(dist.y, ref.y) and truth["effects"][0]["name"] == "lens_distortion"
    assert dist.sensor == ref.sensor  # the sidecar records the nominal camera: the effect is the data's
    # an optics effect acts once, whatever the number of phantoms (led_imbalance scales a power)
    led, _ = synth.synthesize(dhe, [(fx.get("led_imbalance"), 0.5)], toy, frames=3, seed=4, noise_scale=0.0)
    s = SensorModel()
    by_hand, _ = synth.synthesize(
        dhe, [], toy, sensor=s.replace(led_power=(0.5,) + s.led_power[1:]), frames=3, seed=4, noise_scale=0.0
    )
    np.testing.assert_array_equal(led.y, by_hand.y)


def test_selftest_draws_a_labelling_error(dhe):
    cands = fx.parse_list("background_E,saturation")
    outside = fx.parse_list("mislabel_d", outside_only=True)
    res = selftest.run(
        3, Simulator(None, "tiny", "toy"), Simulator(None, "coarse", "toy"), cands, outside,
        n_phantoms=6, frames=3, seed=2, st=Settings(inverse=False, bootstrap=10), log=None,
    )  # fmt: skip
    (out,) = [r for r in res["trials"] if r["kind"] == "out"]
    assert out["true_effect"] == "mislabel_d" and out["label_phantom"] in [f"P{i:02d}" for i in range(1, 7)]
    assert "confident_wrong" in out


def test_cli_refuses_outside_only_candidates_and_a_stray_label_phantom(tmp_path):
    py = [sys.executable, "-m", "elastimap.gap.cli"]
    m = tmp_path / "m"
    r = subprocess.run(
        py + ["synth", "--out", str(m), "--backend", "toy", "--n", "5", "--effect", "mislabel_E=0.2"]
        + ["--label-phantom", "P04", "--frames", "2", "--cache", "none", "--no-progress"],
        capture_output=True, text=True, cwd=ROOT,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert synth.unseal(m)["label_phantom"] == "P04"
    for args, word in (
        (["synth", "--out", str(tmp_path / "a"), "--backend", "toy", "--label-phantom", "P01"], "label effect"),
        (
            ["synth", "--out", str(tmp_path / "b"), "--effect", "mislabel_d=0.1", "--label-phantom", "X"],
            "not a phantom",
        ),
        (["diagnose", "--measured", str(m), "--out", str(tmp_path / "d"), "--effects", "core_shell"], "candidate"),
    ):
        r = subprocess.run(py + args, capture_output=True, text=True, cwd=ROOT)
        assert r.returncode == 2 and word in r.stderr and r.stderr.count("\n") == 1, r.stderr
        assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_a_fit_pinned_by_the_bounded_search_is_at_the_end_of_its_range():
    """The bounded Brent search stops short of a bound it is pinned against by about its tolerance
    (1e-7 of the range): a family's probe_E1 ended at 180.000024 for its grid end 180 on the
    lens-distortion world L3 (docs/gap.md, 'Out-of-library checks'), which the end test of
    before (1e-9 absolute) missed."""
    from elastimap.gap.fit_models import END_RTOL, at_end

    assert at_end(180.00002413380372, 180.0, 450.0) and at_end(450.0 - 1e-4, 180.0, 450.0)
    assert not at_end(180.0 + 2 * END_RTOL * 270.0, 180.0, 450.0) and not at_end(300.0, 180.0, 450.0)
    assert at_end(0.0, 0.0, 1.0) and not at_end(0.01, 0.0, 1.0)
