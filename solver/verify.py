"""Verification and speed benchmark of the forward model; prints Markdown tables.

    python -m elastimap.solver.verify                      # every check (several minutes)
    python -m elastimap.solver.verify --checks hertz,speed # a subset

Checks: ``hertz`` (rigid sphere on a block vs Hertz), ``convergence`` (O1..O3 on
coarse/default/fine), ``symmetry`` (quarter vs full model), ``interface``
(tied vs contact vs bonded), ``speed`` (seconds per sample at the default mesh
and where the time goes).  Figures belong in docs/forward-model.md together
with the command that produced them.
"""

from __future__ import annotations

import platform
import sys
import time

import click
import numpy as np

from elastimap.cli_util import run

from .params import Discretisation, SolveParams

CHECKS = ("hertz", "convergence", "symmetry", "interface", "speed")


def _row(cells):
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _table(head, rows):
    out = [_row(head), _row(["---"] * len(head))] + [_row(r) for r in rows]
    return "\n".join(out)


def check_hertz() -> str:
    from .hertz import hertz

    r = hertz(level="verify")
    return (
        "### Hertz: rigid sphere R = 20 mm, δ = 0.2 mm, E = 10 kPa, ν = 0.3\n\n"
        + _table(
            ["quantity", "FEM", "Hertz", "error"],
            [
                ["force (mN)", f"{r.force:.4f}", f"{r.force_hertz:.4f}", f"{100 * r.force_error:+.2f} %"],
                ["contact radius (mm)", f"{r.radius:.4f}", f"{r.radius_hertz:.4f}", f"{100 * r.radius_error:+.2f} %"],
            ],
        )
        + f"\n\n{r.ndofs} dofs, {r.iterations} active-set iterations, {r.seconds:.1f} s\n"
    )


def _feat(r):
    return [f"{r.O1:.6f}", f"{r.O2:.5f}", f"{r.O3:.3f}", f"{r.force:.2f}"]


def check_convergence(d=8.0, h=7.0, E=50.0) -> str:
    from .api import solve

    rows, res = [], {}
    for lvl in ("coarse", "default", "fine"):
        r = solve(SolveParams(disc=Discretisation(mesh=lvl)).with_inclusion(d=d, h=h, E=E))
        res[lvl] = r
        rows.append([lvl, r.ndofs] + _feat(r) + [f"{r.seconds:.2f}"])
    a, b = res["default"], res["fine"]
    rows.append(
        ["change default→fine", ""]
        + [f"{100 * (getattr(b, k) / getattr(a, k) - 1):+.2f} %" for k in ("O1", "O2", "O3", "force")]
        + [""]
    )
    return (
        f"### Mesh convergence, d = {d:g} mm, h = {h:g} mm, E = {E:g} kPa (quarter model, tied)\n\n"
        + _table(["mesh", "dofs", "O1 (mm)", "O2 (mm)", "O3 (mm²)", "force (mN)", "s"], rows)
        + "\n"
    )


def check_symmetry(d=8.0, h=7.0, E=50.0, mesh="default") -> str:
    from .api import solve

    p = SolveParams(disc=Discretisation(mesh=mesh)).with_inclusion(d=d, h=h, E=E)
    q = solve(p)
    f = solve(p.replace(disc=Discretisation(mesh=mesh, symmetry="full")))
    rows = [
        ["quarter", q.ndofs] + _feat(q) + [f"{q.seconds:.1f}"],
        ["full", f.ndofs] + _feat(f) + [f"{f.seconds:.1f}"],
        ["full vs quarter", ""]
        + [f"{100 * (getattr(f, k) / getattr(q, k) - 1):+.2f} %" for k in ("O1", "O2", "O3", "force")]
        + [""],
    ]
    return (
        f"### Quarter vs full model ({mesh} mesh), d = {d:g}, h = {h:g}, E = {E:g}\n\n"
        + _table(["model", "dofs", "O1 (mm)", "O2 (mm)", "O3 (mm²)", "force (mN)", "s"], rows)
        + "\n"
    )


def check_interface(mesh="default") -> str:
    from .api import solve

    cases = [(8.0, 7.0, 50.0), (15.0, 8.5, 200.0), (3.0, 3.0, 200.0)]
    rows = []
    for d, h, E in cases:
        p = SolveParams(disc=Discretisation(mesh=mesh)).with_inclusion(d=d, h=h, E=E)
        out = {m: solve(p.replace(disc=Discretisation(mesh=mesh, interface=m))) for m in ("tied", "contact", "bonded")}
        t = out["tied"]
        for m, r in out.items():
            dev = (
                max(abs(getattr(r, k) / getattr(t, k) - 1) for k in ("O1", "O2", "O3", "force")) if m != "tied" else 0.0
            )
            rows.append(
                [f"{d:g}/{h:g}/{E:g}", m]
                + _feat(r)
                + [
                    f"{100 * dev:.3f} %",
                    r.newton_iterations,
                    f"{r.interface['open_pair_fraction']:.3f}",
                    f"{r.seconds:.2f}",
                ]
            )
    return (
        f"### Interface models ({mesh} mesh)\n\n"
        + _table(
            ["d/h/E", "interface", "O1", "O2", "O3", "force", "max dev. vs tied", "iterations", "open pairs", "s"], rows
        )
        + "\n"
    )


def check_speed(n: int = 6, seed: int = 1) -> str:
    from .api import solve, warmup
    from .params import DESIGN_BOX, depth_range

    warmup()
    rng = np.random.default_rng(seed)
    rows, secs = [], []
    tsum: dict[str, float] = {}
    for _ in range(n):
        d = float(rng.uniform(*DESIGN_BOX["d"]))
        lo, hi = depth_range(d)
        h = float(rng.uniform(lo, hi))
        E = float(np.exp(rng.uniform(*np.log(DESIGN_BOX["E"]))))
        r = solve(SolveParams().with_inclusion(d=d, h=h, E=E))
        secs.append(r.seconds)
        for k, v in r.timings.items():
            tsum[k] = tsum.get(k, 0.0) + v
        rows.append([f"{d:.2f}", f"{h:.2f}", f"{E:.1f}", r.ndofs, f"{r.seconds:.2f}", f"{r.peak_memory_mb:.0f}"])
    total = sum(tsum.values())
    where = ", ".join(f"{k} {100 * v / total:.0f} %" for k, v in sorted(tsum.items(), key=lambda kv: -kv[1]))
    return (
        f"### Speed, default mesh, one core ({platform.processor() or platform.machine()})\n\n"
        + _table(["d", "h", "E", "dofs", "s/sample", "peak MiB"], rows)
        + f"\n\nmean {np.mean(secs):.2f} s/sample (two solves: inclusion + reference), median {np.median(secs):.2f} s; "
        f"time split: {where}\n"
    )


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--checks", default=",".join(CHECKS), show_default=True, help="Comma-separated subset of checks.")
@click.option(
    "--speed-samples",
    type=click.IntRange(1, 100),
    default=6,
    show_default=True,
    help="Samples (drawn over the design box) the speed check times.",
)
def command(checks, speed_samples):
    """Run the forward-model verification checks and print Markdown tables."""
    from elastimap.errors import UserError

    chosen = [c.strip() for c in checks.split(",") if c.strip()]
    bad = [c for c in chosen if c not in CHECKS]
    if bad:
        raise UserError("--checks", f"unknown check(s) {', '.join(bad)}; choose from {', '.join(CHECKS)}")
    t0 = time.perf_counter()
    for c in chosen:
        text = check_speed(speed_samples) if c == "speed" else globals()[f"check_{c}"]()
        click.echo(text)
        sys.stdout.flush()
    click.echo(f"_verification wall time {time.perf_counter() - t0:.0f} s_")


def main(argv=None):
    run(command, argv, prog_name="python -m elastimap.solver.verify")


if __name__ == "__main__":
    main(sys.argv[1:])
