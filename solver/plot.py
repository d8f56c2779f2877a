"""PNG figure of an elasticity image (matplotlib, no display needed)."""

from __future__ import annotations

import numpy as np


def save_image_png(
    path: str,
    img: np.ndarray,
    pixel: float,
    title: str,
    label: str = "deflection difference (mm)",
    raw: np.ndarray | None = None,
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = 2 if raw is not None else 1
    fig, axes = plt.subplots(1, n, figsize=(5.2 * n, 4.4), squeeze=False)
    half = img.shape[1] * pixel / 2
    ext = (-half, half, -half, half)
    panels = [(img, title, label)] + ([(raw, "raw probe deflection u_z + δ", "mm")] if raw is not None else [])
    for ax, (a, t, lab) in zip(axes[0], panels):
        im = ax.imshow(a, origin="lower", extent=ext, cmap="viridis")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title(t, fontsize=9)
        fig.colorbar(im, ax=ax, label=lab)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
