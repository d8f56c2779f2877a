"""Global identifiability evidence: cross-validated error of a strong regressor per measurement set.

    elastimap study global_cv --data data/sweep512 [--noise 0.01]

Measurement sets: (a) the paper's features O1, O2, O3; (b) the whole difference image (PCA);
(c) image + plate-force difference (force − force_ref).  Regressor: scikit-learn
HistGradientBoosting on log-features / PCA scores, targets d, h, log E, 10-fold CV on the design
rows.  Prints the mean relative error (%) per output.  ``--noise`` adds relative Gaussian noise to
the features and to every image pixel (relative to the image's max), drawn once with a fixed seed.
"""

from __future__ import annotations

import sys

import click
import numpy as np

from elastimap.cli_util import run


def evaluate(df, noise: float = 0.0, seed: int = 0, folds: int = 10) -> dict[str, np.ndarray]:
    from sklearn.decomposition import PCA
    from sklearn.ensemble import HistGradientBoostingRegressor
    from sklearn.model_selection import KFold, cross_val_predict
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    rng = np.random.default_rng(seed)
    T = df[["d", "h", "E"]].to_numpy(float)
    F = df[["O1", "O2", "O3"]].to_numpy(float)
    img = np.stack(df["image"].to_numpy()).astype(float)
    dforce = (df["force"] - df["force_ref"]).to_numpy(float)
    if noise:
        F = F * (1 + noise * rng.standard_normal(F.shape))
        img = img + noise * np.abs(img).max(axis=1, keepdims=True) * rng.standard_normal(img.shape)
        dforce = dforce * (1 + noise * rng.standard_normal(dforce.shape))
    feats = np.column_stack([np.log(np.abs(F[:, 0]) + 1e-9), np.log(np.abs(F[:, 1]) + 1e-9), F[:, 2]])
    sets = {"(a) O1, O2, O3": feats, "(b) image (PCA 20)": img, "(c) image + force": np.column_stack([img, dforce])}
    y = np.column_stack([T[:, 0], T[:, 1], np.log(T[:, 2])])
    cv = KFold(folds, shuffle=True, random_state=seed)
    out = {}
    for name, X in sets.items():
        steps = [StandardScaler()]
        if X.shape[1] > 10:
            steps.append(PCA(20, random_state=seed))
        preds = []
        for j in range(3):
            model = make_pipeline(
                *steps, HistGradientBoostingRegressor(max_iter=400, learning_rate=0.05, random_state=seed)
            )
            preds.append(cross_val_predict(model, X, y[:, j], cv=cv))
        P = np.column_stack([preds[0], preds[1], np.exp(preds[2])])
        out[name] = 100 * np.mean(np.abs(P - T) / T, axis=0)
    return out


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--data", required=True, help="Sweep dataset with images.")
@click.option(
    "--noise", type=float, default=0.0, show_default=True, help="Relative noise on features and image pixels."
)
def main(data, noise):
    """Cross-validated mean relative error of d, h, E per measurement set."""
    from elastimap.dataset.io import read_samples

    df = read_samples(data)
    df = df[df["tag"] == "design"].reset_index(drop=True)
    res = evaluate(df, noise)
    click.echo(f"{len(df)} design samples from {data}, noise {noise:g}; 10-fold CV, gradient boosting")
    click.echo("| measurement | MRE d (%) | MRE h (%) | MRE E (%) |\n|---|---|---|---|")
    for k, v in res.items():
        click.echo(f"| {k} | {v[0]:.1f} | {v[1]:.1f} | {v[2]:.1f} |")


if __name__ == "__main__":
    run(main, sys.argv[1:], prog_name="elastimap study global_cv")
