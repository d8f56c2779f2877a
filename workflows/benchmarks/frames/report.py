"""The benchmark's ``report`` stage: errors inside the identifiable region, coverage, what each
estimator reports as a number; ``OUT/benchmark.md``, ``.json`` and ``.png``."""

from __future__ import annotations

import os

import click
import numpy as np

from elastimap.identify.fit import STILL_MOVING

from .lesions import REGION_SETS, drawn_note, identifiable_at


def summarise(recs: list[dict], region_set: str = "frames") -> dict:
    """Per estimator: MRE where identifiable, coverage inside/outside, seconds; from the lesion records."""
    truth = np.array([r["truth"] for r in recs])
    reg = identifiable_at(truth, region_set)
    sig = np.array(["no_signal" not in r["network"]["flags"] for r in recs])
    conv = np.array([STILL_MOVING not in r.get("fit_message", "") for r in recs])
    out = {"n": len(recs), "identifiable": {q: int(reg[:, j].sum()) for j, q in enumerate("dhE")}}
    for name in ("network", "fit"):
        est = np.array([[r[name][q] for q in "dhE"] for r in recs])
        lo = np.array([[r[name][f"{q}_lo"] for q in "dhE"] for r in recs])
        hi = np.array([[r[name][f"{q}_hi"] for q in "dhE"] for r in recs])
        rel = np.abs(est - truth) / truth
        cov = (lo <= truth) & (truth <= hi)
        row = {}
        for j, q in enumerate("dhE"):
            i_in, i_out = reg[:, j], ~reg[:, j]
            i_err = i_in & sig  # no_signal lesions report nothing: left out of the errors, kept in coverage
            row[q] = {
                "mre_identifiable": float(rel[i_err, j].mean()) if i_err.any() else None,
                "median_re_identifiable": float(np.median(rel[i_err, j])) if i_err.any() else None,
                "n_error": int(i_err.sum()),
                "mre_all": float(rel[:, j].mean()),
                "coverage_inside": float(cov[i_in, j].mean()) if i_in.any() else None,
                "coverage_outside": float(cov[i_out, j].mean()) if i_out.any() else None,
                "n_inside": int(i_in.sum()),
                "n_outside": int(i_out.sum()),
            }
            # where the estimator itself prints q as a number (identifiable by its own sd, possible,
            # a signal): what a user is told to trust, decided from the frames, not from the truth
            rep = np.array([bool(r[name].get(f"{q}_reportable", False)) for r in recs])
            row[q].update(
                mre_reported=float(rel[rep, j].mean()) if rep.any() else None,
                median_re_reported=float(np.median(rel[rep, j])) if rep.any() else None,
                coverage_reported=float(cov[rep, j].mean()) if rep.any() else None,
                n_reported=int(rep.sum()),
            )
            if name == "fit":  # the fits among them whose last pass settled (FitResult.converged)
                rc = rep & conv
                row[q].update(
                    mre_reported_converged=float(rel[rc, j].mean()) if rc.any() else None,
                    n_reported_converged=int(rc.sum()),
                )
        out[name] = row
    sec = np.array([r["seconds_fit"] for r in recs])
    out["seconds_fit"] = {"mean": float(sec.mean()), "median": float(np.median(sec)), "max": float(sec.max())}
    # the fit's cost over the lesions a fit ran for (a lesion without a signal costs none)
    ran = [r for r in recs if r.get("n_fit_level_solves", 0) > 0] or recs
    cpu = np.array([r.get("cpu_seconds_fit", np.nan) for r in ran])
    out["cpu_seconds_fit"] = {
        "mean": float(np.nanmean(cpu)),
        "median": float(np.nanmedian(cpu)),
        "p90": float(np.nanpercentile(cpu, 90)),
        "n": len(ran),
    }
    out["seconds_network"] = float(np.mean([r["seconds_camera_and_network"] for r in recs]))
    for key in ("seconds_fit_level_solves", "seconds_alt_level_solves", "n_fit_level_solves", "n_alt_level_solves"):
        out[key] = float(np.mean([r[key] for r in ran]))
    for key in ("seconds_fine_level_solves", "n_fine_level_solves"):  # fits that correct by a finer level
        out[key] = float(np.mean([r.get(key, 0.0) for r in ran]))
    if all("fit_interval_gauss" in r for r in recs):  # records since 3bfcd81: the Gauss–Newton interval too
        # None where no fit ran (no signal): the reported interval, the network's, stands for both
        gauss = [
            r["fit_interval_gauss"] or {k: [r["fit"][f"{q}_{k}"] for q in "dhE"] for k in ("lo", "hi")} for r in recs
        ]
        glo, ghi = np.array([g["lo"] for g in gauss]), np.array([g["hi"] for g in gauss])
        gcov = (glo <= truth) & (truth <= ghi)
        out["fit_gauss_coverage"] = {
            q: {
                "inside": float(gcov[reg[:, j], j].mean()) if reg[:, j].any() else None,
                "outside": float(gcov[~reg[:, j], j].mean()) if (~reg[:, j]).any() else None,
            }
            for j, q in enumerate("dhE")
        }
    out["not_converged"] = int((~conv).sum())
    out["no_signal"] = int(sum("no_signal" in r["fit"]["flags"] for r in recs))
    out["model_mismatch"] = int(sum("model_mismatch" in r["fit"]["flags"] for r in recs))
    out["chi2_red_median"] = float(np.nanmedian([r["fit"].get("fit_chi2_red", np.nan) for r in recs]))
    return out


def _pct(v):
    return "—" if v is None else f"{100 * v:.1f} %"


def table(sm: dict) -> str:
    lines = [
        "| estimator | E MRE where identifiable (n) | d MRE where identifiable (n) | h MRE where identifiable (n) | "
        "95 % coverage inside d / h / E | 95 % coverage outside d / h / E (n) | s per lesion |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, label in (("network", "frames -> image network"), ("fit", "frames -> network -> ML fit")):
        r = sm[name]
        sec = (
            f"{sm['seconds_network']:.2f}"
            if name == "network"
            else f"{sm['seconds_fit']['mean']:.1f} (median {sm['seconds_fit']['median']:.1f}, max {sm['seconds_fit']['max']:.1f})"
        )
        lines.append(
            f"| {label} | {_pct(r['E']['mre_identifiable'])} ({r['E']['n_error']}) | "
            f"{_pct(r['d']['mre_identifiable'])} ({r['d']['n_error']}) | {_pct(r['h']['mre_identifiable'])} ({r['h']['n_error']}) | "
            + " / ".join(_pct(r[q]["coverage_inside"]) for q in "dhE")
            + " | "
            + " / ".join(_pct(r[q]["coverage_outside"]) for q in "dhE")
            + f" ({r['d']['n_outside']} / {r['h']['n_outside']} / {r['E']['n_outside']}) | {sec} |"
        )
    lines += [
        "",
        "Where the estimator itself reports the quantity as a number (its own interval within the "
        "identifiability threshold, possible, a signal; decided from the frames, not the truth):",
        "",
        "| estimator | E MRE / median (n) | coverage E | d MRE / median (n) | coverage d | h MRE / median (n) | coverage h |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, label in (("network", "frames -> image network"), ("fit", "frames -> network -> ML fit")):
        r = sm[name]
        lines.append(
            f"| {label} | "
            + " | ".join(
                f"{_pct(r[q]['mre_reported'])} / {_pct(r[q]['median_re_reported'])} ({r[q]['n_reported']}) | "
                f"{_pct(r[q]['coverage_reported'])}"
                for q in "Edh"
            )
            + " |"
        )
    r = sm["fit"]
    g = sm.get("fit_gauss_coverage")
    if g:
        lines += [
            "",
            "The fit's Gauss–Newton interval (θ̂ ± 1.96 sd clipped to the box), beside the reported one: coverage "
            "inside d / h / E "
            + " / ".join(_pct(g[q]["inside"]) for q in "dhE")
            + ", outside "
            + " / ".join(_pct(g[q]["outside"]) for q in "dhE")
            + ".",
        ]
    lines += [
        "",
        f"Fits that ended still moving (the passes ran out): {sm['not_converged']} of {sm['n']}.  Among the fit's "
        "reported quantities, those whose fit converged: "
        + ", ".join(f"{q} {_pct(r[q]['mre_reported_converged'])} ({r[q]['n_reported_converged']})" for q in "Edh")
        + ".",
    ]
    return "\n".join(lines)


def plot(recs: list[dict], path: str, region_set: str = "frames") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    truth = np.array([r["truth"] for r in recs])
    reg = identifiable_at(truth, region_set)
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.6))
    for j, (q, unit) in enumerate((("d", "mm"), ("h", "mm"), ("E", "kPa"))):
        ax = axes[j]
        net = np.array([r["network"][q] for r in recs])
        fit = np.array([r["fit"][q] for r in recs])
        lo = np.array([r["fit"][f"{q}_lo"] for r in recs])
        hi = np.array([r["fit"][f"{q}_hi"] for r in recs])
        ax.scatter(truth[:, j], net, s=10, c="0.7", label="image network")
        for m, c, lab in (
            (reg[:, j], "C0", f"fit, {q} identifiable"),
            (~reg[:, j], "C3", f"fit, {q} not identifiable"),
        ):
            ax.errorbar(
                truth[m, j],
                fit[m],
                yerr=[np.clip(fit[m] - lo[m], 0, None), np.clip(hi[m] - fit[m], 0, None)],
                fmt="o",
                ms=3,
                c=c,
                lw=0.6,
                label=lab,
            )
        a, b = truth[:, j].min(), truth[:, j].max()
        ax.plot([a, b], [a, b], "k--", lw=0.8)
        if q == "E":
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_ylim(5, 400)
        else:
            ax.set_ylim(0.5 * a, 1.3 * b)
        ax.set_xlabel(f"true {q} ({unit})")
        ax.set_ylabel(f"estimated {q} ({unit})")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    where = drawn_note(recs[0].get("design"))
    where = f" {where}" if where else ""
    fig.suptitle(f"SYNTHETIC camera frames, {len(recs)} held-out lesions{where}: estimate vs truth (95 % intervals)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


@click.command("report")
@click.option("--out", required=True, help="The benchmark folder.")
@click.option("--fits", "fits_name", default=None, help="The fits folder inside OUT (default: the only one).")
@click.option(
    "--region-set",
    type=click.Choice(REGION_SETS),
    default="frames",
    show_default=True,
    help="The map's set that decides where d, h, E are identifiable: frames = what inference from frames "
    "uses (the larger of camera and image), camera = the nominal camera's frames alone, "
    "image = 1 % of the peak per pixel (earlier tables).",
)
@click.option(
    "--common-with",
    "common",
    default=None,
    type=click.Path(exists=True, file_okay=False),
    help="Another fits folder (any benchmark folder): score only the lesions both hold, so that two fits "
    "are compared on the same lesions (files get '-common-<its name>').",
)
def report_cmd(out, fits_name, region_set, common):
    """Table (printed and OUT/benchmark.md), OUT/benchmark.json and OUT/benchmark.png (``-FITS`` and
    ``-SET`` added to the names when OUT holds several fits folders or the regions are not ``frames``)."""
    import glob
    import json

    from elastimap.errors import UserError

    names = sorted(os.path.basename(p) for p in glob.glob(os.path.join(out, "fits-*")))
    if fits_name is None:
        if len(names) != 1:
            raise UserError("--fits", f"{out} holds {len(names)} fits folders ({', '.join(names)}); name one")
        fits_name = names[0]
    files = sorted(glob.glob(os.path.join(out, fits_name, "lesion-*.json")))
    if not files:
        raise UserError("--out", f"{os.path.join(out, fits_name)}: no lesion fits yet (run the 'run' stage)")
    if common is not None:
        other = {os.path.basename(f) for f in glob.glob(os.path.join(common, "lesion-*.json"))}
        files = [f for f in files if os.path.basename(f) in other]
        if not files:
            raise UserError("--common-with", f"{common} holds none of the lesions of {os.path.join(out, fits_name)}")
    recs = [json.load(open(f)) for f in files]
    designs = {json.dumps(r.get("design"), sort_keys=True) for r in recs}
    if len(designs) != 1:
        raise UserError("--out", f"{os.path.join(out, fits_name)} mixes lesion designs ({', '.join(sorted(designs))})")
    design = recs[0].get("design") or {}
    sm = summarise(recs, region_set)
    sm["region_set"] = region_set
    sm["inside"] = design.get("inside")
    sm["outside"] = design.get("outside")
    r0 = recs[0]
    drawn = drawn_note(design)
    drawn = f"{drawn} (region-stratified, not a sample of the design)" if drawn else "over the whole design box"
    head = (
        f"SYNTHETIC camera frames ({r0['frames']} lesion + {r0['frames']} background frames per lesion; camera: "
        f"{'nominal' if r0.get('camera', 'nominal') == 'nominal' else 'LED powers and vignetting drawn per lesion'}), "
        f"{len(recs)} held-out lesions {drawn}; world: {r0['world']}; fit: {r0['fit_map']}; "
        f"regions: the map's {region_set!r} set at the truth (10 %)"
    )
    foot = (
        f"fit CPU time per fitted lesion ({sm['cpu_seconds_fit'].get('n', sm['n'])} of {sm['n']}; one core, process "
        f"time): mean {sm['cpu_seconds_fit']['mean']:.1f} s, median {sm['cpu_seconds_fit']['median']:.1f} s, "
        f"p90 {sm['cpu_seconds_fit'].get('p90', float('nan')):.1f} s (the table's seconds are wall time on the shared "
        "machine, over all lesions); "
        f"fit: {sm['n_fit_level_solves']:.1f} solves at the fit's level ({sm['seconds_fit_level_solves']:.1f} s) + "
        f"{sm['n_alt_level_solves']:.1f} at the model-error level ({sm['seconds_alt_level_solves']:.1f} s) "
        + (
            f"+ {sm['n_fine_level_solves']:.1f} at the correcting level ({sm['seconds_fine_level_solves']:.1f} s) "
            if sm.get("n_fine_level_solves")
            else ""
        )
        + "per lesion "
        f"on average; median reduced chi2 {sm['chi2_red_median']:.2f}; no_signal {sm['no_signal']} (left out of the "
        f"errors, kept in the coverage), "
        f"model_mismatch {sm['model_mismatch']}"
    )
    md = head + "\n\n" + table(sm) + "\n\n" + foot + "\n"
    # one fits folder: OUT/benchmark[-SET].*; several: the folder's name too, so that none overwrites another
    stem = (
        "benchmark"
        + ("" if len(names) == 1 else f"-{fits_name}")
        + ("" if region_set == "frames" else f"-{region_set}")
        + ("" if common is None else f"-common-{os.path.basename(os.path.normpath(common))}")
    )
    with open(os.path.join(out, f"{stem}.md"), "w") as fh:
        fh.write(md)
    with open(os.path.join(out, f"{stem}.json"), "w") as fh:
        json.dump({"synthetic": True, "summary": sm, "lesions": recs}, fh, indent=1)
    plot(recs, os.path.join(out, f"{stem}.png"), region_set)
    click.echo(md)
