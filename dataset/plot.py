"""``dataset plot``: PNG figures of a sample dataset (matplotlib, Agg backend).

* ``scatter3d.png``  the paper's Fig. 5 style: one 3-D panel per feature, a circle at
  (d, h, E) for every ok sample; colour (viridis) is the feature in its unit (colour bar), marker
  area grows with it; calibration phantoms are marked x
* ``features_vs_params.png``  each of O1, O2, O3, force against each of d, h, E
  (colour: log10 E in the d and h panels, d in the E panels)
* ``images.png``  a grid of example difference elasticity images chosen across the O1 range,
  x and y in mm, each panel on its own colour scale with its colour bar in mm (one common scale
  left the small-O1 panels black: O1 spans two decades)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from elastimap.errors import UserError

from . import io
from .phantoms import is_phantom
from .schema import COLUMNS, FEATURES, TARGETS


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

    files.append(_scatter3d(plt, df, phantom, out / "scatter3d.png"))

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

    files.append(_images(plt, df, path, n_images, out / "images.png"))
    return files


def _scatter3d(plt, df, phantom: np.ndarray, path: Path) -> Path:
    """One 3-D panel per feature: a circle at (d, h, E) per sample, coloured by the feature (viridis,
    colour bar in the feature's unit), marker area from 6 to 120 pt^2 across the feature's range."""
    d, h, E = (df[c].to_numpy(dtype=float) for c in TARGETS)
    fig = plt.figure(figsize=(15, 5.2))
    for i, feat in enumerate(FEATURES):
        ax = fig.add_subplot(1, 3, i + 1, projection="3d")
        v = df[feat].to_numpy(dtype=float)
        lo, hi = np.nanmin(v), np.nanmax(v)
        area = 6 + 114 * ((v - lo) / (hi - lo) if hi > lo else np.full_like(v, 0.5))
        sc = ax.scatter(d, h, E, s=area, c=v, cmap="viridis", alpha=0.85, edgecolors="k", linewidths=0.2)
        if phantom.any():
            ax.scatter(d[phantom], h[phantom], E[phantom], s=60, marker="x", c="r", label="calibration phantoms")
            ax.legend(loc="upper left", fontsize=7)
        ax.set_xlabel(_label("d"))
        ax.set_ylabel(_label("h"))
        ax.set_zlabel(_label("E"))
        ax.set_title(f"{feat}: {COLUMNS[feat][2]}", fontsize=9)
        fig.colorbar(sc, ax=ax, shrink=0.6, pad=0.12, label=_label(feat))
    fig.suptitle(f"{len(df)} solved samples: colour and marker area = the feature (h: depth of the inclusion centre)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _images(plt, df, path, n_images: int, out: Path) -> Path:
    """Example difference images across the O1 range, each on its own colour scale (colour bar in mm)."""
    shape, pixel = io.read_image_meta(path)
    order = np.argsort(df["O1"].to_numpy(dtype=float))
    k = min(n_images, len(df))
    pick = order[np.unique(np.linspace(0, len(df) - 1, k).round().astype(int))]
    imgs = io.stack_images(df.iloc[pick], shape)
    ncol = min(4, len(pick))
    nrow = int(np.ceil(len(pick) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.6 * ncol, 3.1 * nrow), squeeze=False)
    half_x, half_y = shape[1] * pixel / 2, shape[0] * pixel / 2
    for ax in axes.flat:
        ax.axis("off")
    for n, (ax, img, (_, r)) in enumerate(zip(axes.flat, imgs, df.iloc[pick].iterrows())):
        finite = img[np.isfinite(img)]
        vmax = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
        vmin = min(0.0, float(finite.min())) if finite.size else 0.0
        extent = (-half_x, half_x, -half_y, half_y)
        im = ax.imshow(img, origin="lower", extent=extent, cmap="magma", vmin=vmin, vmax=vmax)
        ax.set_title(f"d={r.d:.3g} mm h={r.h:.3g} mm E={r.E:.3g} kPa\nO1={r.O1:.3g} mm", fontsize=8)
        ax.axis("on")
        ax.tick_params(labelsize=6)
        if n % ncol == 0:
            ax.set_ylabel("y [mm]", fontsize=7)
        if n >= len(pick) - ncol:
            ax.set_xlabel("x [mm]", fontsize=7)
        cb = fig.colorbar(im, ax=ax, shrink=0.85, pad=0.03)
        cb.ax.tick_params(labelsize=6)
        cb.set_label("mm", fontsize=7)
    fig.suptitle(
        f"example difference elasticity images ({shape[0]}x{shape[1]} px, {pixel:g} mm), ordered by O1; "
        "each panel on its own colour scale"
    )
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
