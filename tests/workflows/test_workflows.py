"""The reproducible pipelines in ``workflows/`` run end to end on a tiny problem (the way scikit-fem
runs its examples as regression tests): a pipeline that no longer runs fails here, not in a user's
three-hour job.  Tiny mesh, few samples, two hidden neurons: only that it runs and writes its
table is checked, not the numbers."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[2]


def test_paper_table_pipeline_runs_on_tiny_mesh(tmp_path):
    out = tmp_path / "paper"
    cmd = [
        sys.executable,
        str(ROOT / "workflows" / "paper_table.py"),
        "--out",
        str(out),
        "--n",
        "8",
        "--mesh",
        "tiny",
        "--jobs",
        "2",
        "--repeats",
        "1",
        "--hidden",
        "2",
        "--epochs",
        "5",
        "--noise",
        "0",
    ]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    table = pd.read_csv(out / "paper_table.csv")
    # every algorithm x validation cell, one row each, with finite errors
    assert sorted(zip(table["algo"], table["validate"])) == [
        ("lm", "hov"),
        ("lm", "loocv"),
        ("scg", "hov"),
        ("scg", "loocv"),
    ]
    assert table[["mse100_d_mean", "mse100_h_mean", "mse100_E_mean"]].notna().all().all()
    md = (out / "paper_table.md").read_text()
    assert "paper (SCG, LOOCV, best)" in md and "tiny mesh" in md
    # a second run resumes: every stage is skipped, nothing is recomputed
    r2 = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r2.returncode == 0, r2.stderr[-2000:]
    assert r2.stdout.count("(done)") == 4
