"""Detection study (paper 5.3) on SYNTHETIC scans: scores, ROC, AUC, bootstrap (toy forward model)."""

import numpy as np

from elastimap.camera.detection import (
    DETECTION_INCLUSIONS,
    DetectionSettings,
    auc,
    bootstrap_auc,
    plot_roc,
    roc_curve,
    run_detection,
)
from elastimap.camera.optics import SensorModel
from elastimap.solver.synthetic import solve_dhe as toy_solve  # SYNTHETIC stand-in, not physics


def test_auc_and_roc_basics():
    assert auc([3, 4], [1, 2]) == 1.0 and auc([1, 2], [3, 4]) == 0.0 and auc([1], [1]) == 0.5
    fpr, tpr, _ = roc_curve(np.array([3.0, 1.5]), np.array([1.0, 2.0]))
    assert fpr[0] == tpr[0] == 0 and fpr[-1] == tpr[-1] == 1
    lo, hi = bootstrap_auc([3, 4, 2.5, 5], [1, 2, 3, 0.5], n_boot=200)
    assert 0 <= lo <= hi <= 1


def test_detection_study_runs_and_separates(tmp_path):
    res = [toy_solve(d, h, E) for d, h, E in DETECTION_INCLUSIONS]
    easy = run_detection(res, SensorModel(), DetectionSettings(clutter_mm=0.0, n_boot=200, n_threshold=10))
    assert easy["n_pos"] == easy["n_neg"] == 8 and easy["synthetic"]
    assert easy["auc"] > 0.95 and easy["sensitivity"] >= 0.75
    hard = run_detection(
        res, SensorModel(noise_scale=30), DetectionSettings(clutter_mm=0.004, n_boot=200, n_threshold=10)
    )
    assert hard["auc"] < easy["auc"]
    assert hard["tp"] + hard["fn"] == 8 and hard["tn"] + hard["fp"] == 8
    lo, hi = hard["auc_ci95"]
    assert lo <= hard["auc"] <= hi
    png = tmp_path / "synthetic_roc.png"
    plot_roc(hard, png)
    assert png.stat().st_size > 5000
