"""``dataset plot``: PNG figures of a sample dataset (matplotlib, Agg backend).

* ``scatter3d.png``  the paper's Fig. 5 style: one 3-D panel per feature, a circle at
  (d, h, E) for every ok sample, area and colour from the feature rescaled to 0-255
* ``features_vs_params.png``  each of O1, O2, O3, force against each of d, h, E
  (colour: log10 E in the d and h panels, d in the E panels)
* ``images.png``  a grid of example difference elasticity images, chosen across the O1 range
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from elastimap.errors import UserError

from . import io
from .phantoms import is_phantom
from .schema import COLUMNS, FEATURES, TARGETS


def _rescale255(x: np.ndarray) -> np.ndarray:
    lo, hi = np.nanmin(x), np.nanmax(x)
    if not np.isfinite(lo) or hi <= lo:
        return np.full_like(x, 128.0, dtype=float)
    return 255.0 * (x - lo) / (hi - lo)


def _label(c: str) -> str:
    u = COLUMNS[c][1]
    return f"{c} [{u}]" if u else c


def _log_axis(ax, x) -> None:
    """Log x axis with plain numbers at 1-2-5 steps (matplotlib's default labels collide)."""
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    ax.set_xscale("log")
    lo, hi = np.nanmin(x), np.nanmax(x)
    ticks = [m * 10.0**k for k in range(-3, 6) for m in (1, 2, 5) if lo <= m * 10.0**k <= hi]
    if len(ticks) >= 2:
        ax.set_xticks(ticks)
    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_formatter(NullFormatter())


def plot_all(path, out_dir, n_images: int = 12) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from elastimap.outputs import check_out_dir

    if n_images < 1:
        raise UserError("n_images", f"must be >= 1 (got {n_images})")
    out = check_out_dir(out_dir, "out_dir", allow_existing=True)  # before reading and plotting
    df = io.read_samples(path, status="ok")
    if len(df) == 0:
        raise UserError("path", f"{path} has no ok samples to plot")
    out.mkdir(parents=True, exist_ok=True)
    files = []
    d, h, E = (df[c].to_numpy(dtype=float) for c in TARGETS)
    phantom = is_phantom(df["tag"])

    # 1. paper-style 3-D scatter
    fig = plt.figure(figsize=(15, 5))
    for i, feat in enumerate(FEATURES):
        ax = fig.add_subplot(1, 3, i + 1, projection="3d")
        v = _rescale255(df[feat].to_numpy(dtype=float))
        sc = ax.scatter(
            d, h, E, s=5 + v * 0.6, c=v, cmap="jet", vmin=0, vmax=255, alpha=0.75, edgecolors="k", linewidths=0.2
        )
        if phantom.any():
            ax.scatter(d[phantom], h[phantom], E[phantom], s=60, marker="x", c="k", label="phantoms")
            ax.legend(loc="upper left", fontsize=7)
        ax.set_xlabel(_label("d"))
        ax.set_ylabel(_label("h"))
        ax.set_zlabel(_label("E"))
        ax.set_title(f"{feat} rescaled to 0-255")
        fig.colorbar(sc, ax=ax, shrink=0.6, pad=0.1)
    fig.suptitle(f"{len(df)} samples: marker area and colour = feature (0-255)")
    fig.tight_layout()
    files.append(out / "scatter3d.png")
    fig.savefig(files[-1], dpi=110)
    plt.close(fig)

    # 2. each feature against each parameter
    feats = (*FEATURES, "force")
    fig, axes = plt.subplots(len(feats), 3, figsize=(12, 3 * len(feats)), squeeze=False)
    for i, feat in enumerate(feats):
        y = df[feat].to_numpy(dtype=float)
        for j, par in enumerate(TARGETS):
            ax = axes[i, j]
            x = df[par].to_numpy(dtype=float)
            colour, clabel = (np.log10(E), "colour: log10 E [kPa]") if par != "E" else (d, f"colour: {_label('d')}")
            sc = ax.scatter(x, y, c=colour, s=8, cmap="viridis")
            if par == "E":
                _log_axis(ax, x)
            ax.set_xlabel(_label(par))
            ax.set_ylabel(_label(feat))
            if i == 0:
                fig.colorbar(sc, ax=ax, label=clabel)
    fig.tight_layout()
    files.append(out / "features_vs_params.png")
    fig.savefig(files[-1], dpi=100)
    plt.close(fig)

    # 3. example images across the O1 range
    shape, pixel = io.read_image_meta(path)
    order = np.argsort(df["O1"].to_numpy(dtype=float))
    k = min(n_images, len(df))
    pick = order[np.unique(np.linspace(0, len(df) - 1, k).round().astype(int))]
    imgs = io.stack_images(df.iloc[pick], shape)
    ncol = min(4, len(pick))
    nrow = int(np.ceil(len(pick) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.2 * ncol, 3.0 * nrow), squeeze=False)
    vmax = float(np.nanmax(imgs)) if np.isfinite(np.nanmax(imgs)) else 1.0
    half = shape[1] * pixel / 2
    for ax in axes.flat:
        ax.axis("off")
    for ax, img, (_, r) in zip(axes.flat, imgs, df.iloc[pick].iterrows()):
        im = ax.imshow(img, origin="lower", extent=(-half, half, -half, half), cmap="magma", vmin=0, vmax=vmax)
        ax.set_title(f"d={r.d:.3g} h={r.h:.3g} E={r.E:.3g}\nO1={r.O1:.3g} mm", fontsize=8)
        ax.axis("on")
        ax.tick_params(labelsize=6)
    fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.8, label="difference image [mm]")
    fig.suptitle(f"example elasticity images ({shape[0]}x{shape[1]} px, {pixel:g} mm), ordered by O1")
    files.append(out / "images.png")
    fig.savefig(files[-1], dpi=100)
    plt.close(fig)
    return files
