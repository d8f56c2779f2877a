"""End-to-end pipeline for the paper's error table, resumable stage by stage.

    python workflows/paper_table.py --out runs/paper            # 512 samples, 10 repeats
    python workflows/paper_table.py --out runs/small --n 32 --repeats 2 --mesh coarse   # a quick check

Stages (a finished stage is skipped when the command is run again):

1. ``sweep run --n N --jobs J --phantoms`` into OUT/data (the sweep itself resumes sample by sample);
2. ``train`` for every algorithm × validation × feature noise (0 and 1 %), each into
   OUT/train/<algo>-<validation>-noise<pct>; a run counts as finished when its results.csv exists;
3. OUT/paper_table.md and .csv: every row together, next to the paper's numbers.

LM with LOOCV is the costly cell (one 393×393 Cholesky per network and epoch);
``--lm-loocv-repeats`` lowers its repeats on its own and the table says so.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time

import click

PAPER = ("paper (SCG, LOOCV, best)", "0.58", "1.12", "0.51")


def _run(argv: list[str]) -> None:
    bindir = os.path.dirname(sys.executable)
    exe = shutil.which(argv[0], path=bindir + os.pathsep + os.environ.get("PATH", ""))
    if exe is None:
        raise click.ClickException(f"{argv[0]} not found next to {sys.executable}")
    click.secho("$ " + " ".join(argv), bold=True)
    t0 = time.perf_counter()
    r = subprocess.run([exe, *argv[1:]])
    if r.returncode:
        raise click.ClickException(f"{argv[0]} failed with exit code {r.returncode}")
    click.echo(f"-- {time.perf_counter() - t0:.0f} s")


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--out", default="runs/paper", show_default=True)
@click.option("--n", type=click.IntRange(8), default=512, show_default=True, help="Design samples.")
@click.option("--jobs", type=click.IntRange(1), default=2, show_default=True)
@click.option("--mesh", default="default", show_default=True)
@click.option("--repeats", type=click.IntRange(1), default=10, show_default=True)
@click.option("--lm-loocv-repeats", type=click.IntRange(1), default=None, help="Repeats of the LM+LOOCV cell only.")
@click.option(
    "--lm-loocv-float32",
    is_flag=True,
    help="Train the LM+LOOCV cell in single precision (about 2x faster; the table says so).",
)
@click.option(
    "--workers",
    type=click.IntRange(0),
    default=0,
    show_default=True,
    help="Training processes per cell (0 = one per core).",
)
@click.option("--epochs", type=click.IntRange(1), default=100, show_default=True)
@click.option("--hidden", default="25,10", show_default=True, help="Hidden layers (smaller for tiny test runs).")
@click.option("--noise", "noises", default="0,0.01", show_default=True, help="Feature-noise levels (relative).")
def main(out, n, jobs, mesh, repeats, lm_loocv_repeats, lm_loocv_float32, workers, epochs, hidden, noises):
    """Sweep → train every algorithm × validation × noise → one table next to the paper's."""
    import pandas as pd

    data = os.path.join(out, "data")
    _run(["sweep", "run", "--n", str(n), "--jobs", str(jobs), "--mesh", mesh, "--phantoms", "--out", data])
    rows = []
    for noise in [float(x) for x in noises.split(",")]:
        for validate in ("hov", "loocv"):
            for algo in ("scg", "lm"):
                lm_loocv = algo == "lm" and validate == "loocv"
                reps = lm_loocv_repeats if (lm_loocv and lm_loocv_repeats) else repeats
                run_dir = os.path.join(out, "train", f"{algo}-{validate}-noise{100 * noise:g}")
                res = os.path.join(run_dir, "results.csv")
                if not os.path.exists(res):
                    _run(
                        [
                            "train",
                            "--algo",
                            algo,
                            "--validate",
                            validate,
                            "--repeats",
                            str(reps),
                            "--epochs",
                            str(epochs),
                            "--feature-noise",
                            str(noise),
                            "--hidden",
                            hidden,
                            "--data",
                            data,
                            "--out",
                            run_dir,
                            "--no-progress",
                            "--no-model",
                            "--workers",
                            str(workers),
                        ]
                        + (["--float32"] if (lm_loocv and lm_loocv_float32) else [])
                    )
                else:
                    click.echo(f"skip {run_dir} (done)")
                rows.append(pd.read_csv(res))
    table = pd.concat(rows, ignore_index=True)
    table.to_csv(os.path.join(out, "paper_table.csv"), index=False)
    lines = [
        "| algorithm | validation | repeats | feature noise | MSE×100 d (%) | MSE×100 h (%) | MSE×100 E (%) | "
        "MRE d (%) | MRE h (%) | MRE E (%) | precision | wall s |",
        "|" + "---|" * 12,
    ]
    for _, r in table.iterrows():

        def ci(k, r=r):
            return f"{r[k + '_mean']:.3g} [{r[k + '_lo']:.3g}, {r[k + '_hi']:.3g}]"

        lines.append(
            f"| {r['algo'].upper()} | {r['validate'].upper()} | {r['repeats']} | {100 * r['feature_noise']:g} % | "
            f"{ci('mse100_d')} | {ci('mse100_h')} | {ci('mse100_E')} | {ci('mre_d')} | {ci('mre_h')} | "
            f"{ci('mre_E')} | {r.get('dtype', 'float64') if isinstance(r.get('dtype'), str) else 'float64'} | "
            f"{r['wall_s']:.0f} |"
        )
    lines.append(f"| {PAPER[0]} | | 10/50/100 | (measured) | {PAPER[1]} | {PAPER[2]} | {PAPER[3]} | | | | | |")
    text = (
        "Error table, mean [2.5 %, 97.5 %] over repeats; MSE×100 is paper eq. (1) on [-1, 1]-scaled targets; "
        f"data {data} ({n} design samples + 9 phantoms, {mesh} mesh).\n\n" + "\n".join(lines) + "\n"
    )
    with open(os.path.join(out, "paper_table.md"), "w") as fh:
        fh.write(text)
    click.echo(text)


if __name__ == "__main__":
    from elastimap.cli_util import run

    run(main, sys.argv[1:], prog_name="workflows/paper_table.py")
