"""Convergence over d and smoothness in (d, h) of the forward model; prints Markdown tables.

    python -m elastimap.solver.verify_morph                              # every check (long)
    python -m elastimap.solver.verify_morph --checks smoothness --points 8:7
    python -m elastimap.solver.verify_morph --checks convergence --levels coarse,default,fine
    python -m elastimap.solver.verify_morph --checks calculix --calculix independent-fem/calculix.csv

Checks:

``convergence``
    O1, O2, O3 and the image for d = 2 … 15 mm at the depth h = d/2 + 3 mm (3 mm of cover)
    on each mesh level, and the change from each level to the next (``--sizing``).
``smoothness``
    central differences of O1, O2 and the image in d and in h with the steps ``--steps``,
    remeshed vs morphed (the morphed map pinned to the reference of the point), the spread
    of each derivative over the steps, and the seconds per sample of each method.
``edges``
    the jump at a bin edge: one (d, h) on an edge solved on the references of both sides.
``calculix``
    O1, O2 and the plate forces of the phantoms of an independent model's table (``--calculix``,
    e.g. the ``calculix.csv`` of the independent FEM's development data: columns d_mm, h_mm,
    E_kPa, O1_mm, O2_mm, plate_force_mN, plate_force_ref_mN) by the remeshed, fixed-sizing path
    (what the sweep runs by default) and by the morphed, sized-by-d one on ``--mesh``, each one's
    relative deviation from the table and which is closer; not run unless named.

Figures belong in docs/forward-model.md together with the command that produced them.
"""

from __future__ import annotations

import sys
import time

import click
import numpy as np
from tqdm import tqdm

from elastimap.cli_util import mesh_option, run

from .params import MESH_LEVELS, SIZINGS, Discretisation, SolveParams

CHECKS = ("convergence", "smoothness", "edges", "calculix")
#: the checks run when ``--checks`` is not given (``calculix`` needs a table)
DEFAULT_CHECKS = CHECKS[:3]
#: the two forward-model paths ``calculix`` compares: (geometry, sizing)
PATHS = (("remesh", "fixed"), ("morph", "by_d"))
#: the table's columns and the SolveResult fields they are compared with
CALCULIX_COLUMNS = {"O1_mm": "O1", "O2_mm": "O2", "plate_force_mN": "force", "plate_force_ref_mN": "force_ref"}
DIAMETERS = (2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 15.0)
STEPS = (0.05, 0.1, 0.25, 0.5)
POINTS = ((8.0, 7.0), (3.0, 4.5), (12.0, 9.0))


def _row(cells):
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _table(head, rows):
    return "\n".join([_row(head), _row(["---"] * len(head))] + [_row(r) for r in rows])


def _pct(a: float, b: float) -> str:
    return f"{100 * (a / b - 1):+.2f} %"


def _image_change(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


# ------------------------------------------------------------------ convergence over d
def check_convergence(levels, diameters=DIAMETERS, sizing="by_d", E=50.0, max_seconds=600.0) -> str:
    """One remeshed solve per (d, level); a level is skipped for the larger d once one of its
    solves took more than ``max_seconds``."""
    from .api import solve

    rows = []
    skip: set[str] = set()
    bar = tqdm(total=len(levels) * len(diameters), desc="convergence", file=sys.stderr)
    for d in diameters:
        h = d / 2 + 3.0
        prev = None
        for lvl in levels:
            bar.update()
            if lvl in skip:
                rows.append([f"{d:g}", f"{h:g}", lvl, f"skipped (> {max_seconds:g} s)"] + [""] * 7)
                prev = None
                continue
            p = SolveParams(disc=Discretisation(mesh=lvl, sizing=sizing)).with_inclusion(d=d, h=h, E=E)
            r = solve(p)
            if r.seconds > max_seconds:
                skip.add(lvl)
            ch = (
                ["", "", ""]
                if prev is None
                else [
                    _pct(r.O1, prev.O1),
                    _pct(r.O2, prev.O2),
                    f"{100 * _image_change(r.image, prev.image):.2f} %",
                ]
            )
            rows.append(
                [f"{d:g}", f"{h:g}", lvl, r.ndofs, f"{r.O1:.6g}", f"{r.O2:.6g}", f"{r.O3:.5g}"]
                + ch
                + [f"{r.seconds:.1f}"]
            )
            prev = r
    bar.close()
    return (
        f"### Mesh convergence over d (h = d/2 + 3 mm, E = {E:g} kPa, sizing = {sizing}, remeshed)\n\n"
        "Changes are from the level on the row above (same d); the image change is "
        "‖I − I_prev‖ / ‖I_prev‖.\n\n"
        + _table(
            ["d (mm)", "h (mm)", "mesh", "dofs", "O1 (mm)", "O2 (mm)", "O3 (mm²)", "ΔO1", "ΔO2", "Δimage", "s"],
            rows,
        )
        + "\n"
    )


# ------------------------------------------------------------------ smoothness in (d, h)
def _spread(values) -> float:
    v = np.asarray(values, dtype=float)
    return float((v.max() - v.min()) / abs(v.mean()))


def _s2_residual(steps, values) -> float:
    """Largest deviation of the central differences from the smooth truncation law D(s) = D₀ + c s²,
    relative to |D₀| (what is left is jitter, not curvature)."""
    s = np.asarray(steps, dtype=float)
    v = np.asarray(values, dtype=float)
    A = np.column_stack([np.ones_like(s), s**2])
    coef, *_ = np.linalg.lstsq(A, v, rcond=None)
    return float(np.max(np.abs(A @ coef - v)) / abs(coef[0]))


def _image_spread(derivs) -> float:
    mean = np.mean(derivs, axis=0)
    return max(float(np.linalg.norm(a - b) / np.linalg.norm(mean)) for a in derivs for b in derivs)


def check_smoothness(points=POINTS, steps=STEPS, mesh="default", sizing="by_d", E=50.0) -> str:
    from .api import solve
    from .morph import MorphedForward

    base = SolveParams(disc=Discretisation(mesh=mesh, sizing=sizing))
    rows = []
    cost = {"remesh": [], "morph": []}
    bar = tqdm(total=len(points) * 2 * 2 * len(steps) * 2, desc="smoothness", file=sys.stderr)
    with MorphedForward(base) as fwd:
        for d0, h0 in points:
            ref = fwd.reference_for(d0, h0)
            fwd.solve(d0, h0, E, reference=ref)  # builds the reference mesh (not counted in the cost)

            def remesh(d, h, base=base):
                return solve(base.with_inclusion(d=d, h=h, E=E))

            def morph(d, h, ref=ref):
                return fwd.solve(d, h, E, reference=ref)

            for var in ("d", "h"):
                for name, f in (("remesh", remesh), ("morph", morph)):
                    dO1, dO2, dI = [], [], []
                    for s in steps:
                        lo = (d0 - s, h0) if var == "d" else (d0, h0 - s)
                        hi = (d0 + s, h0) if var == "d" else (d0, h0 + s)
                        a, b = f(*lo), f(*hi)
                        bar.update(2)
                        cost[name] += [a.seconds, b.seconds]
                        dO1.append((b.O1 - a.O1) / (2 * s))
                        dO2.append((b.O2 - a.O2) / (2 * s))
                        dI.append((b.image.astype(float) - a.image) / (2 * s))
                    rows.append(
                        [f"{d0:g}, {h0:g}", var, name]
                        + [f"{v:.5g}" for v in dO2]
                        + [
                            f"{100 * _spread(dO1):.2f} %",
                            f"{100 * _spread(dO2):.2f} %",
                            f"{100 * _image_spread(dI):.2f} %",
                            f"{100 * _s2_residual(steps, dO2):.2f} %",
                        ]
                    )
    bar.close()
    steps_txt = ", ".join(f"{s:g}" for s in steps)
    rm, mm = np.mean(cost["remesh"]), np.mean(cost["morph"])
    return (
        f"### Derivative smoothness ({mesh} mesh, sizing = {sizing}, E = {E:g} kPa)\n\n"
        f"Central differences at steps {steps_txt} mm; spread = (max − min) / |mean| over the steps "
        "(image: largest ‖D_a − D_b‖ / ‖mean D‖); the last column is what is left after fitting the smooth "
        "truncation law D(s) = D₀ + c s² to dO2 (jitter, not curvature). The morphed map is pinned to the "
        "reference of the point.\n\n"
        + _table(
            ["(d, h) mm", "in", "geometry"]
            + [f"dO2 step {s:g}" for s in steps]
            + ["O1 spread", "O2 spread", "image spread", "O2 off D₀ + c s²"],
            rows,
        )
        + f"\n\nseconds per sample (two solves), same mesh level, one process: remesh {rm:.2f} s, "
        f"morph {mm:.2f} s (reference mesh already built)\n"
    )


# ------------------------------------------------------------------ bin edges
def check_edges(mesh="default", sizing="by_d", E=50.0) -> str:
    from .morph import D_ANCHOR, D_RATIO, S_ANCHOR, S_WIDTH, MorphedForward

    base = SolveParams(disc=Discretisation(mesh=mesh, sizing=sizing))
    T = base.tissue.thickness
    d_edge = D_ANCHOR * D_RATIO**-0.5  # between the bins of 5.66 and 8 mm
    ratio = np.exp(S_ANCHOR + 0.5 * S_WIDTH)  # g / b on the edge above the d = 8, h = 7 bin
    g = (T - 8.0) * ratio / (1 + ratio)
    cases = [("d", d_edge, 7.0), ("h", 8.0, g + 4.0)]
    rows = []
    with MorphedForward(base) as fwd:
        for var, d, h in tqdm(cases, desc="edges", file=sys.stderr):
            eps = 1e-3
            lo = fwd.reference_for(d - eps, h) if var == "d" else fwd.reference_for(d, h - eps)
            hi = fwd.reference_for(d + eps, h) if var == "d" else fwd.reference_for(d, h + eps)
            a = fwd.solve(d, h, E, reference=lo)
            b = fwd.solve(d, h, E, reference=hi)
            rows.append(
                [
                    var,
                    f"{d:.3f}, {h:.3f}",
                    f"({lo.d0:.3g}, {lo.h0:.3g}) → ({hi.d0:.3g}, {hi.h0:.3g})",
                    _pct(b.O1, a.O1),
                    _pct(b.O2, a.O2),
                    f"{100 * _image_change(b.image, a.image):.2f} %",
                ]
            )
    return (
        f"### Jump at a bin edge ({mesh} mesh, sizing = {sizing}, E = {E:g} kPa)\n\n"
        + _table(["edge in", "(d, h) mm", "references (d0, h0)", "ΔO1", "ΔO2", "Δimage"], rows)
        + "\n"
    )


# ------------------------------------------------------------------ an independent model's phantoms
def check_calculix(path, mesh="default") -> str:
    """Each phantom of the table at ``path`` solved by each of :data:`PATHS` on ``mesh`` (the
    morphed path on the reference of its own bin); per phantom and quantity the relative
    deviation (elastimap / table − 1) and which path is closer, then the mean |deviation| per
    path and quantity over the phantoms."""
    import pandas as pd

    from .api import solve

    table = pd.read_csv(path)
    dev = {pth: {q: [] for q in CALCULIX_COLUMNS} for pth in PATHS}
    rows, secs = [], {pth: 0.0 for pth in PATHS}
    for r in table.itertuples(index=False):
        res = {}
        for geometry, sizing in PATHS:
            disc = Discretisation(mesh=mesh, geometry=geometry, sizing=sizing)
            p = SolveParams(disc=disc).with_inclusion(d=r.d_mm, h=r.h_mm, E=r.E_kPa)
            t0 = time.perf_counter()
            res[(geometry, sizing)] = solve(p)
            secs[(geometry, sizing)] += time.perf_counter() - t0
        for col, field in CALCULIX_COLUMNS.items():
            ref = float(getattr(r, col))
            e = {pth: getattr(res[pth], field) / ref - 1 for pth in PATHS}
            for pth in PATHS:
                dev[pth][col].append(abs(e[pth]))
            a, b = (abs(e[pth]) for pth in PATHS)
            closer = "/".join(PATHS[0]) if a < b else "/".join(PATHS[1]) if b < a else "tie"
            rows.append(
                [f"{r.d_mm:g}", f"{r.h_mm:g}", f"{r.E_kPa:g}", field, f"{ref:.6g}"]
                + [f"{100 * e[pth]:+.2f} %" for pth in PATHS]
                + [closer]
            )
    names = ["/".join(pth) for pth in PATHS]
    out = [f"### Against {path} (mesh {mesh})\n"]
    out.append(_table(["d", "h", "E", "quantity", "table"] + names + ["closer"], rows))
    out.append("\nMean |deviation| over the phantoms:\n")
    out.append(
        _table(
            ["quantity"] + names,
            [[CALCULIX_COLUMNS[c]] + [f"{100 * np.mean(dev[pth][c]):.2f} %" for pth in PATHS] for c in CALCULIX_COLUMNS]
            + [["O1 and O2"] + [f"{100 * np.mean(dev[pth]['O1_mm'] + dev[pth]['O2_mm']):.2f} %" for pth in PATHS]],
        )
    )
    out.append(
        "\nSeconds per phantom (this process): "
        + ", ".join(f"{n} {secs[pth] / len(table):.1f}" for n, pth in zip(names, PATHS, strict=True))
        + "\n"
    )
    return "\n".join(out)


def _csv(text: str, name: str, cast=float) -> tuple:
    from elastimap.errors import UserError

    try:
        return tuple(cast(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise UserError(name, f"must be a comma-separated list (got {text!r})") from None


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option(
    "--checks",
    default=",".join(DEFAULT_CHECKS),
    show_default=True,
    help=f"Comma-separated subset of {', '.join(CHECKS)}.",
)
@click.option(
    "--calculix",
    "calculix",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    help="calculix check: the independent model's table (e.g. independent-fem/calculix.csv)",
)
@click.option("--levels", default="coarse,default,fine,finer", show_default=True, help="mesh levels (convergence)")
@click.option("--diameters", default=",".join(f"{d:g}" for d in DIAMETERS), show_default=True, help="d (mm)")
@click.option(
    "--sizing",
    type=click.Choice(SIZINGS),
    default="by_d",
    show_default=True,
    help="Element size near the inclusion: fixed or by_d (scaled with d).",
)
@mesh_option(help="smoothness, edges")
@click.option(
    "--points", default=",".join(f"{d:g}:{h:g}" for d, h in POINTS), show_default=True, help="d:h pairs (smoothness)"
)
@click.option("--steps", default=",".join(f"{s:g}" for s in STEPS), show_default=True, help="steps (mm)")
@click.option(
    "--max-seconds",
    type=float,
    default=120.0,
    show_default=True,
    help="convergence: skip a level for the larger d once one of its solves took longer",
)
def command(checks, calculix, levels, diameters, sizing, mesh, points, steps, max_seconds):
    """Convergence over d, derivative smoothness (remesh vs morph) and bin-edge jumps, as Markdown."""
    from elastimap.errors import UserError

    chosen = [c.strip() for c in checks.split(",") if c.strip()]
    bad = [c for c in chosen if c not in CHECKS]
    if bad:
        raise UserError("--checks", f"unknown check(s) {', '.join(bad)}; choose from {', '.join(CHECKS)}")
    if "calculix" in chosen and calculix is None:
        raise UserError("--calculix", "the calculix check needs the table's path")
    lv = _csv(levels, "--levels", str)
    if not lv or any(v not in MESH_LEVELS for v in lv):
        raise UserError("--levels", f"choose from {', '.join(MESH_LEVELS)} (got {levels!r})")
    ds = _csv(diameters, "--diameters")
    st = _csv(steps, "--steps")
    if not st or min(st) <= 0:
        raise UserError("--steps", "must be positive (mm)")
    try:
        pts = tuple(tuple(float(v) for v in pair.split(":")) for pair in points.split(",") if pair.strip())
        if any(len(pt) != 2 for pt in pts):
            raise ValueError
    except ValueError:
        raise UserError("--points", f"must be d:h pairs like 8:7,3:4.5 (got {points!r})") from None
    for d, h in pts:
        for s in (0.0, max(st)):
            SolveParams().with_inclusion(d=d + s, h=h + s).validate()
            SolveParams().with_inclusion(d=d - s, h=h - s).validate()
    for d in ds:
        SolveParams().with_inclusion(d=d, h=d / 2 + 3).validate()
    t0 = time.perf_counter()
    click.echo(f"_{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}_\n")
    for c in chosen:
        if c == "convergence":
            text = check_convergence(lv, ds, sizing, max_seconds=max_seconds)
        elif c == "smoothness":
            text = check_smoothness(pts, st, mesh, sizing)
        elif c == "calculix":
            text = check_calculix(calculix, mesh)
        else:
            text = check_edges(mesh, sizing)
        click.echo(text)
        sys.stdout.flush()
    click.echo(f"_verification wall time {time.perf_counter() - t0:.0f} s_")


def main(argv=None):
    run(command, argv, prog_name="python -m elastimap.solver.verify_morph")


if __name__ == "__main__":
    main(sys.argv[1:])
