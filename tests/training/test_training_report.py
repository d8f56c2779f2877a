"""Training-curve figures name what each curve is measured on (the test set by how it was chosen)."""

from __future__ import annotations

import torch

from elastimap.training.data import prepare, synthetic_table
from elastimap.training.experiment import TrainConfig, run_validation
from elastimap.training.net import parse_hidden
from elastimap.training.report import curve_names, plot_curves


def _res(validate, **kw):
    s = prepare(synthetic_table(30, seed=2), source="SYNTHETIC toy table (n=30)")
    cfg = TrainConfig(hidden=parse_hidden("3"), epochs=3, progress=False, dtype=torch.float64, **kw).validate()
    return run_validation(s, "scg", validate, 2, cfg, seed=0)


def test_curves_name_the_test_set_and_are_drawn(tmp_path):
    hov = _res("hov", val_fraction=0.2)
    names = curve_names(hov)
    assert names["test"] == "test: 9 calibration-phantom rows"
    assert names["val"].startswith("validation rows")
    loo = _res("loocv")
    assert curve_names(loo)["test"] == "test: each network's left-out row (30 folds)"
    f = plot_curves(hov, str(tmp_path / "c.png"), label=", SYNTHETIC toy table (n=30)")
    assert (tmp_path / "c.png").read_bytes()[:4] == b"\x89PNG" and f.endswith("c.png")
