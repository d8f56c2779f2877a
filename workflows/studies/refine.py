"""Held-out study of the FEM refinement: the numbers behind :data:`elastimap.identify.refine.INTERVAL_SCALE`.

    elastimap study refine --pred runs/img-loocv/pred-scg-lnE-loocv.npz [--data data/sweep512]

Takes the held-out image-network estimates of ``elastimap study image_model``
(LOOCV with image noise), rebuilds each row's noisy image exactly as that study drew it, refines
the ensemble's estimate with :func:`elastimap.identify.refine.fit` through the cached FEM solves
(:func:`elastimap.identify.refine.fem_model`) and reports the MRE of the network and of the refined
estimate and the coverage of the CRB and reported intervals (docs/identifiability.md).
"""

from __future__ import annotations

import click
import numpy as np

from elastimap.cli_util import CONTEXT_SETTINGS, jobs_option, mesh_option, run
from elastimap.errors import UserError
from elastimap.identify.refine import INTERVAL_SCALE, METHODS, fem_model, fit, interval


def _refine_row(args):
    image, sigma, theta0, mesh, cache, max_iter, method = args
    return fit(image, sigma, theta0, fem_model(mesh, cache), method, max_iter)


def study(
    pred_path: str,
    data_path: str,
    *,
    rows: str = "identifiable",
    threshold: float = 0.10,
    image_noise: float | None = None,
    seed: int | None = None,
    mesh: str = "default",
    cache: str | None = None,
    jobs: int = 2,
    max_iter: int = 12,
    limit: int = 0,
    progress: bool = True,
    method: str = "rsm",
) -> dict:
    """Refine the held-out ensemble estimates of ``pred_path`` (elastimap study image_model) with the FEM.

    The measured image of each row is rebuilt exactly as the image_model study drew the *shared* noisy image
    (``add_image_noise(images, image_noise, default_rng([seed, 9]))``); the start is the mean over
    the repeats' networks of their prediction from it (``pred_shared_noise``), as inference reports it."""
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from elastimap.identify.measure import add_image_noise, load
    from elastimap.identify.region import IdentifiabilityMap

    z = np.load(pred_path, allow_pickle=False)
    if "pred_shared_noise" not in z.files:
        raise UserError(
            "--pred",
            f"{pred_path} has no pred_shared_noise (run elastimap study image_model with --image-noise > 0)",
        )
    level = float(z["image_noise"]) if image_noise is None and "image_noise" in z.files else image_noise
    sd = int(z["seed"]) if seed is None and "seed" in z.files else seed
    if level is None or sd is None:
        raise UserError(
            "--image-noise", f"{pred_path} does not record its noise level and seed; give --image-noise and --seed"
        )
    data = load(data_path)
    ids = np.asarray(z["ids"]).astype(str)
    if list(ids) != list(np.asarray(data.ids).astype(str)):
        raise UserError("--data", f"{data_path} does not hold the rows of {pred_path} in the same order")
    theta = np.asarray(z["theta"], float)
    start = np.nanmean(z["pred_shared_noise"], axis=0)
    noisy = add_image_noise(data.images, level, np.random.default_rng([sd, 9]))
    sigma = level * np.abs(noisy).max(axis=1)
    crb, _ = IdentifiabilityMap.load(None).bound(theta, "image")
    if rows == "identifiable":
        sel = np.flatnonzero(crb[:, 2] <= threshold)
    elif rows == "all":
        sel = np.arange(len(ids))
    else:
        want = [s.strip() for s in rows.split(",") if s.strip()]
        missing = [w for w in want if w not in set(ids)]
        if missing:
            raise UserError("--rows", f"unknown sample id(s): {', '.join(missing[:5])}")
        sel = np.array([int(np.flatnonzero(ids == w)[0]) for w in want])
    if limit:
        sel = sel[:limit]
    args = [(noisy[i], sigma[i], start[i], mesh, cache, max_iter, method) for i in sel]
    out = [None] * len(sel)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(sel), desc="refine", unit="row")
    if jobs > 1:
        import multiprocessing as mp
        import os

        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # inherited by the
            os.environ.setdefault(var, "1")  # spawned workers

        with ProcessPoolExecutor(jobs, mp_context=mp.get_context("spawn")) as ex:
            futs = {ex.submit(_refine_row, a): k for k, a in enumerate(args)}
            for f in as_completed(futs):
                out[futs[f]] = f.result()
                if bar:
                    bar.update()
    else:
        for k, a in enumerate(args):
            out[k] = _refine_row(a)
            if bar:
                bar.update()
    if bar:
        bar.close()
    return {
        "ids": ids[sel],
        "theta": theta[sel],
        "start": start[sel],
        "crb_map": crb[sel],
        "refined": np.array([r.theta for r in out]),
        "relstd": np.array([r.relstd for r in out]),
        "chi2_red": np.array([r.chi2_red for r in out]),
        "chi2_red_start": np.array([r.chi2_red0 for r in out]),
        "n_solves": np.array([r.n_solves for r in out]),
        "status": np.array([r.status for r in out]),
        "image_noise": level,
        "seed": sd,
        "rows": rows,
        "threshold": threshold,
        "method": method,
    }


def summary_table(res: dict) -> str:
    """Markdown: MRE (%) of the start and the refined estimate, and 95 % interval coverage."""
    T, S, R, rs = res["theta"], res["start"], res["refined"], res["relstd"]
    mre = lambda P: 100 * np.mean(np.abs(P - T) / T, axis=0)  # noqa: E731
    med = lambda P: 100 * np.median(np.abs(P - T) / T, axis=0)  # noqa: E731

    def cover(scale):
        lo, hi = interval(R, rs, scale)
        return 100 * ((lo <= T) & (T <= hi)).mean(axis=0)

    cov1, cov = cover(1.0), cover(INTERVAL_SCALE)
    a, b, ma, mb = mre(S), mre(R), med(S), med(R)
    lines = [
        "| output | network ensemble MRE (%) | refined MRE (%) | network median (%) | refined median (%) "
        f"| coverage: CRB 95 % interval (%) | coverage: reported interval, x{INTERVAL_SCALE:g} (%) "
        "| median CRB at estimate (%) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for j, k in enumerate(("d", "h", "E")):
        lines.append(
            f"| {k} | {a[j]:.3g} | {b[j]:.3g} | {ma[j]:.3g} | {mb[j]:.3g} | {cov1[j]:.3g} | {cov[j]:.3g} "
            f"| {100 * np.median(rs[:, j]):.3g} |"
        )
    lines.append("")
    lines.append(
        f"{len(T)} rows; forward solves per row: median {np.median(res['n_solves']):.0f}, "
        f"max {np.max(res['n_solves'])}; reduced chi² at the refined estimate: median "
        f"{np.median(res['chi2_red']):.3g} (start {np.median(res['chi2_red_start']):.3g})."
    )
    return "\n".join(lines)


def plot(res: dict, path: str) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    T, S, R = res["theta"], res["start"], res["refined"]
    fig, axes = plt.subplots(1, 3, figsize=(12, 4))
    for j, (k, u) in enumerate((("d", "mm"), ("h", "mm"), ("E", "kPa"))):
        ax = axes[j]
        ax.plot(T[:, j], S[:, j], "o", mfc="none", color="0.5", label="image network (ensemble mean)")
        ax.plot(T[:, j], R[:, j], ".", color="C3", label="refined with the FEM")
        lim = [min(T[:, j].min(), S[:, j].min(), R[:, j].min()), max(T[:, j].max(), S[:, j].max(), R[:, j].max())]
        ax.plot(lim, lim, "k-", lw=0.8)
        if k == "E":
            ax.set_xscale("log")
            ax.set_yscale("log")
        ax.set_xlabel(f"true {k} ({u})")
        ax.set_ylabel(f"estimated {k} ({u})")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Held-out rows ({res['rows']}), {100 * res['image_noise']:g} % image noise")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


@click.command(context_settings=CONTEXT_SETTINGS)
@click.option(
    "--pred",
    "pred_path",
    required=True,
    help="pred-<algo>-loocv.npz of elastimap study image_model (with image noise).",
)
@click.option("--data", "data_path", default="data/sweep512", show_default=True, help="The sweep it was made from.")
@click.option(
    "--rows",
    default="identifiable",
    show_default=True,
    help="'identifiable' (E's map CRB <= --crb-limit at the true values), 'all', or sample ids a,b,c.",
)
@click.option(
    "--crb-limit",
    "threshold",
    default=0.10,
    show_default=True,
    type=float,
    help="Cramér–Rao relative std above which an output is non-identifiable.",
)
@click.option(
    "--image-noise", default=None, type=float, help="Noise level of the prediction file (default: the one it records)."
)
@click.option("--seed", default=None, type=int, help="Its seed (default: the one it records).")
@mesh_option(help="Must be the sweep's mesh.")
@jobs_option(default=2, help="Rows refined in parallel.")
@click.option(
    "--max-iter",
    default=12,
    show_default=True,
    type=int,
    help="trf only: trial points per row (each accepted one costs 6 more solves for the central-difference Jacobian).",
)
@click.option(
    "--method",
    default="rsm",
    show_default=True,
    help="rsm: response surface over two 15-solve stencils (averages the remeshing jitter); "
    "trf: trust-region least squares with a central-difference Jacobian.",
)
@click.option("--limit", default=0, type=int, help="Only the first N selected rows (0 = all).")
@click.option("--out", default="runs/refine", show_default=True, help="Output folder of the study's tables.")
def main(pred_path, data_path, rows, threshold, image_noise, seed, mesh, jobs, max_iter, method, limit, out):
    """Refine held-out image-network estimates by a maximum-likelihood fit of the FEM image.

    Prints the MRE of the network ensemble and of the refined estimate over the selected rows,
    writes refine.npz, refine.csv, results.md and refine.png to --out.
    """
    import os
    import time

    import pandas as pd

    if not os.path.isfile(pred_path):
        raise UserError("--pred", f"no such file: {pred_path}")
    if not 0 < threshold < 10:
        raise UserError("--crb-limit", f"must be in (0, 10) (got {threshold:g})")
    if image_noise is not None and not 0 < image_noise < 1:
        raise UserError("--image-noise", f"must be in (0, 1) (got {image_noise:g})")
    if jobs < 1:
        raise UserError("--jobs", f"must be >= 1 (got {jobs})")
    if method not in METHODS:
        raise UserError("--method", f"must be one of {', '.join(METHODS)} (got {method!r})")
    if max_iter < 1:
        raise UserError("--max-iter", f"must be >= 1 (got {max_iter})")
    t0 = time.perf_counter()
    res = study(
        pred_path,
        data_path,
        rows=rows,
        threshold=threshold,
        image_noise=image_noise,
        seed=seed,
        mesh=mesh,
        jobs=jobs,
        max_iter=max_iter,
        limit=limit,
        method=method,
    )
    wall = time.perf_counter() - t0
    os.makedirs(out, exist_ok=True)
    np.savez(os.path.join(out, "refine.npz"), **{k: np.asarray(v) for k, v in res.items()})
    df = pd.DataFrame({"sample_id": res["ids"]})
    for j, k in enumerate(("d", "h", "E")):
        df[f"{k}_true"] = res["theta"][:, j]
        df[f"{k}_start"] = res["start"][:, j]
        df[f"{k}_refined"] = res["refined"][:, j]
        df[f"{k}_crb_rel"] = res["relstd"][:, j]
    df["chi2_red"] = res["chi2_red"]
    df["n_solves"] = res["n_solves"]
    df.to_csv(os.path.join(out, "refine.csv"), index=False)
    md = (
        f"FEM refinement ({method}) of {pred_path} ({data_path}, mesh {mesh}, {100 * res['image_noise']:g} % image noise, "
        f"seed {res['seed']}), rows: {rows}; {wall:.0f} s wall with {jobs} job(s).\n\n" + summary_table(res) + "\n"
    )
    with open(os.path.join(out, "results.md"), "w") as f:
        f.write(md)
    plot(res, os.path.join(out, "refine.png"))
    click.echo(md)
    return 0


if __name__ == "__main__":
    run(main, prog_name="elastimap study refine")
