"""Error tables (CSV, Markdown) and training-curve figures."""

from __future__ import annotations

import os
import textwrap

import numpy as np
import pandas as pd

from elastimap.outputs import write_text

from .data import TARGETS, UNITS
from .experiment import METRICS, ValidationResult

PAPER_BEST = {
    "algo": "scg",
    "validate": "loocv",
    "epochs": 100,
    "mse100": {"d": 0.58, "h": 1.12, "E": 0.51},
}  # paper section 5.2 (MSE x 100 %)


def table(results: list[ValidationResult]) -> pd.DataFrame:
    return pd.DataFrame([r.row for r in results])


def _cell(row, m, t, digits=3):
    mean, lo, hi = row[f"{m}_{t}_mean"], row[f"{m}_{t}_lo"], row[f"{m}_{t}_hi"]
    if row["repeats"] > 1:
        return f"{mean:.{digits}g} [{lo:.{digits}g}, {hi:.{digits}g}]"
    return f"{mean:.{digits}g}"


def write_tables(folder: str, df: pd.DataFrame, md: str) -> None:
    """A validation run's tables into ``folder``: ``results.csv`` and ``results.md`` (each written whole,
    :func:`elastimap.outputs.write_text`)."""
    write_text(os.path.join(folder, "results.csv"), df.to_csv(index=False), "out")
    write_text(os.path.join(folder, "results.md"), md, "out")


def markdown(df: pd.DataFrame, title: str | None = None) -> str:
    """One row per (algorithm, validation, repeats): mean [2.5 %, 97.5 %] across repeats."""
    heads = ["algo", "validation", "repeats", "n train"]
    for m, unit_fn in (("mse100", lambda t: "%"), ("mre", lambda t: "%"), ("rmse", lambda t: UNITS[t])):
        label = {"mse100": "MSE×100", "mre": "MRE", "rmse": "RMSE"}[m]
        heads += [f"{label} {t} ({unit_fn(t)})" for t in TARGETS]
    heads += ["wall s", "nets/s"]
    lines = []
    if title:
        lines += [title, ""]
    lines += ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
    for _, row in df.iterrows():
        cells = [row["algo"].upper(), row["validate"].upper(), str(row["repeats"]), str(row["n_train"])]
        for m in METRICS:
            cells += [_cell(row, m, t) for t in TARGETS]
        cells += [f"{row['wall_s']:.1f}", f"{row['trainings_per_s']:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def curve_names(res: ValidationResult) -> dict[str, str]:
    """What each curve of ``res`` is measured on, for the legend: the training rows, the early-stopping
    validation rows, and the test set named as the validation chose it (HOV: e.g. the calibration-phantom
    rows; LOOCV: each network's one left-out row)."""
    n_test = res.row.get("n_test_per_repeat")
    if res.validate == "loocv":
        test = f"test: each network's left-out row ({res.row.get('test_set', '')})"
    else:
        test = f"test: {res.row.get('test_set') or f'{n_test} held-out rows'}"
    return {"train": "training rows", "val": "validation rows (early stopping)", "test": test}


def plot_curves(res: ValidationResult, path: str, label: str = "") -> str:
    """Median (line) and 10–90 % band (shaded) over the networks of the MSE per epoch on the training
    rows, the validation rows (when any) and the test set, which the legend names; ``label`` is appended
    to the title (the data source, e.g. "SYNTHETIC toy table (n=60)")."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = curve_names(res)
    n_nets = res.curves["train"].shape[0]
    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=110)
    for name, color in (("train", "C0"), ("val", "C2"), ("test", "C3")):
        c = res.curves.get(name)
        if c is None or np.isnan(c).all():
            continue
        c = pd.DataFrame(c).ffill(axis=1).to_numpy()  # a stopped network keeps its last value
        with np.errstate(all="ignore"):
            med = np.nanmedian(c, axis=0)
            lo, hi = np.nanpercentile(c, 10, axis=0), np.nanpercentile(c, 90, axis=0)
        ep = np.arange(c.shape[1])
        ax.plot(ep, med, color=color, label=names[name])
        ax.fill_between(ep, lo, hi, color=color, alpha=0.2, lw=0)
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("MSE on [-1, 1]-scaled targets (d, h, E)")
    title = textwrap.fill(f"{res.algo.upper()} / {res.validate.upper()}, {n_nets} networks{label}", 80)
    ax.set_title(f"{title}\nline: median over the networks; shaded band: 10–90 % of the networks", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
