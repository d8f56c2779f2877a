"""Write a diagnosis as Markdown (``report.md``), a self-contained HTML page (``report.html``,
figures embedded), PNG figures and JSON (``diagnosis.json``)."""

from __future__ import annotations

import base64
import html
import json
import math
import re
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from .measured import FEATURES
from .views import EDGES


def _jsonable(o):
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items() if not str(k).startswith("_")}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return o.tolist() if o.ndim <= 2 and o.size <= 400 else f"<array {o.shape}>"
    if isinstance(o, (np.floating, float)):
        return None if not math.isfinite(float(o)) else float(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


def _mag(r: dict) -> str:
    s = "; ".join(
        f"{n} {m:.4g} {u} [{c[0]:.4g}, {c[1]:.4g}]"
        for n, m, u, c in zip(r["members"], r["magnitude"], r["units"], r["magnitude_ci"])
    )
    via = r.get("via")
    if not via:
        return s
    if r.get("via_kind") == "common factor":
        return s + f" (the family {via} fitted every member off by one common factor)"
    return s + f" (fitted by the family {via}, whose other members hold their nominal values)"


def summary(res: dict) -> dict:
    """The small JSON-ready verdict of a diagnosis."""
    ev = res["evaluation"]
    top = ev["ranking"][0] if ev["ranking"] else None
    out = {
        "outcome": ev["outcome"],
        "verdict": ev.get("verdict", ev["outcome"]),
        "verdict_line": verdict_line(res),
        "model_form": ev.get("model_form_note"),
        "residual_level": ev.get("residual_level"),
        "winner": ev["winner"],
        "ambiguous_set": ev["ambiguous_set"],
        "best_candidate": ev["best"],
        "runner_up": ev["runner_up"],
        "gap_significant": ev["significant"],
        "chi2_baseline": ev["chi2_baseline"],
        "chi2_threshold": ev["chi2_threshold"],
        "n_terms": ev["n_terms"],
        "reduced_chi2_baseline": ev["reduced_chi2_baseline"],
        "views": ev["views"],
        "model_error": res["model_error"]["kind"],
    }
    if top:
        out.update(
            magnitude=top["magnitude"],
            magnitude_ci=top["magnitude_ci"],
            unit=top["unit"],
            explained_fraction_cv=top["explained_fraction"],
            reduced_chi2_cv=top["reduced_chi2_cv"],
        )
    rep = ev.get("reported", {})
    out["set_magnitudes"] = {
        n: {
            "magnitude": rep[n]["magnitude"],
            "ci": rep[n]["magnitude_ci"],
            "members": rep[n]["members"],
            "via": rep[n]["via"],
            "via_kind": rep[n].get("via_kind"),
        }
        for n in ev["ambiguous_set"]
    }
    if res.get("proposal"):
        out["proposal"] = res["proposal"]["recommendation"]
    if res.get("shrink_features"):
        out["gap_shrink_withheld"] = res["shrink_features"]["shrink"]
    if res.get("shrink_inverse"):
        out["dhe_error_shrink_withheld"] = res["shrink_inverse"]["shrink"]
    return out


def _level(ev: dict) -> str:
    """What the best candidate leaves, in model-form units (the residual's modes and where it is largest)."""
    lv = ev.get("residual_level")
    if not lv:
        return ""
    parts = ", ".join(
        f"{m} {100 * a:+.2g} ± {100 * b:.2g} %" for m, a, b in zip(lv["modes"], lv["beta_mean"], lv["beta_sd"])
    )
    where = lv.get("where", "")
    return f"residual {parts} (mean ± sd over the phantoms)" + (f", largest at {where}" if where else "")


def verdict_line(res: dict) -> str:
    """The one-line verdict: one of the three outcomes (docs/gap.md, 'The three outcomes')."""
    ev = res["evaluation"]
    rows = ev.get("reported", {})
    o = ev["outcome"]
    mf = ev.get("model_form", False)
    lvl = "the model-form level" if mf else "the model's own tolerance"
    if o == "no significant gap":
        return (
            f"outcome: no gap beyond {lvl} (χ² {ev['chi2_baseline']:.4g} ≤ "
            f"{ev['chi2_threshold']:.4g} at α = {ev['alpha']:g})"
        )
    leaves = f"; leaving a {_level(ev)} -- at {lvl}" if _level(ev) else ""
    if o == "explained":
        return f"outcome: explained by {ev['winner']}: {_mag(rows[ev['winner']])}{leaves}"
    if o == "ambiguous":
        s = "; ".join(f"{n}: {_mag(rows[n])}" for n in ev["ambiguous_set"])
        p = res.get("proposal") or {}
        rec = p.get("recommendation")
        tail = (
            f"; to separate them: {rec['measurement']} (≥ {rec['min_pair_separation_noise_units']:.3g} noise units)"
            if rec
            else ""
        )
        return f"outcome: explained, ambiguous -- cannot be told apart with these phantoms: {s}{leaves}{tail}"
    top = ev["ranking"][0]
    rank = ", ".join(r["effect"] for r in ev["ranking"][:3])
    if ev.get("shadowed_by"):
        held = "a family held at its" if len(ev["shadowed_by"]) == 1 else "families held at their"
        why = (
            f"not told apart from {', '.join(ev['shadowed_by'])}, {held} members' grid ends "
            "(the data may ask for more than the library holds)"
        )
    elif ev.get("second_effect"):
        s = ev["second_effect"]
        lo, hi = s["magnitude_ci_in_pair"]
        b_lo, b_hi = s["second_magnitude_ci"]
        held = "needed" if s["second_needed"] else "its interval holding its nominal"
        why = (
            f"{_mag(top)}, but a second effect may be present: {s['pair']} fits better by Δscore "
            f"{s['delta_score']:.3g} (charged for its parameter) with {s['effect']} at "
            f"{s['magnitude_in_pair']:.4g} [{lo:.4g}, {hi:.4g}], outside its own interval, and "
            f"{s['second']} {s['second_magnitude']:.4g} [{b_lo:.4g}, {b_hi:.4g}] ({held})"
        )
    elif ev.get("residual_level") and ev["residual_level"]["beyond"] and top["passes"]:
        why = f"its residual's {', '.join(ev['residual_level']['beyond'])} beyond 3 × the prior scale"
    elif top["passes"] and top["at_grid_edge"]:
        why = f"its fit pinned at the end of its range, held-out reduced χ² {top['reduced_chi2_cv']:.3g}"
    elif top["passes"] and ev.get("beyond_design"):
        span = ", ".join(f"[{a:.4g}, {b:.4g}]" for a, b in top["design_range"])
        why = f"{_mag(top)}: its 95 % interval wholly beyond the magnitudes the library was built for, {span}"
    elif top["passes"] and ev.get("model_form"):
        why = f"its 95 % interval holds its nominal (no effect), held-out reduced χ² {top['reduced_chi2_cv']:.3g}"
    else:
        why = f"held-out reduced χ² {top['reduced_chi2_cv']:.3g}"
    return f"outcome: unexplained: a residual beyond {lvl} remains (best {ev['best']}, {why}; ranking {rank})"


REPORT_FILES = ("diagnosis.json", "report.md", "report.html", "adopted-sensor.toml")  # the last: gap/adopt.py


def check_out(out: str | Path) -> None:
    """``gap diagnose --out`` is replaced whole by the new report: it may hold nothing but an
    earlier report (its files and PNG figures), so no file of the user's is ever deleted."""
    from elastimap.errors import UserError

    p = Path(out)
    if not p.is_dir():
        return
    foreign = sorted(
        x.name for x in p.iterdir() if not (x.is_file() and (x.name in REPORT_FILES or x.suffix == ".png"))
    )
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
        raise UserError(
            "out",
            f"{p} holds files that are not a gap report ({shown}); the report replaces the folder whole, "
            "so choose an empty or new folder",
        )


def write(res: dict, out: str | Path) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figs = _figures(res, out)
    doc = {"kind": "elastimap.gap.diagnosis", "version": 2, "summary": summary(res), **res, "figures": figs}
    (out / "diagnosis.json").write_text(json.dumps(_jsonable(doc), indent=2) + "\n")
    md = markdown(res, figs)
    (out / "report.md").write_text(md)
    (out / "report.html").write_text(to_html(md, out))
    return doc


def _pct(x) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{100 * x:+.2f} %"


def markdown(res: dict, figs: list[str]) -> str:
    ev, wh, m, me = res["evaluation"], res["where"], res["measured"], res["model_error"]
    syn = "SYNTHETIC " if m["synthetic"] else ""
    L = [f"# {syn}sim-to-real gap diagnosis", ""]
    if m["synthetic"]:
        L += [
            "> **SYNTHETIC measured data** — generated by `gap synth` from a forward model plus sealed "
            "effects; not laboratory measurements.",
            "",
        ]
    sm = res["simulator"]
    L += [
        f"Measured data: `{m['source']}` ({m['n']} phantoms; {m['description'] or 'no description'}).  "
        f"Forward model mesh `{m['mesh']}`, backend `{sm['backend']}`; {sm['solved_this_diagnosis']} solves run "
        f"on `{m['mesh']}`"
        + (f" and {sm['fine_solved']} on `{sm['fine_mesh']}`" if sm.get("fine_mesh") else "")
        + f", {sm['hits']} from the cache; {res['seconds']:.0f} s.",
        "",
        f"Views compared: **{' + '.join(ev['views'])}** (verdict); available: {', '.join(m['views_available'])}.  "
        f"Model error: **{me['kind']}** — {me['note']}.",
        "",
    ]
    L += ["## Verdict", "", f"**{verdict_line(res)}**", ""]
    if res.get("adoption"):
        a = res["adoption"]
        where = f" → `{a['file']}` (hash {a['adopted']['sensor_hash']})" if a.get("file") else ""
        L += [f"Sensor `{a['from']['sensor']['name']}` (hash {a['from']['sensor_hash']}): {a['note']}{where}.", ""]
    L.append(
        f"Baseline χ² = {ev['chi2_baseline']:.4g} over N = {ev['n_terms']} terms (reduced {ev['reduced_chi2_baseline']:.3g}, "
        f"p = {ev['p_value_baseline']:.3g}); the calibrated threshold χ²_N(1 − α) at α = {ev['alpha']:g} is "
        f"{ev['chi2_threshold']:.4g}.  A candidate passes when its held-out χ² is below the same threshold; "
        f"candidates within Δscore ≤ {res['settings']['ambiguity_margin']:g} of a passing best cannot be told apart, "
        f"nor (with the model-form level) a passing candidate whose deficit is within the noise of a χ² difference "
        f"between the two fitted predictions, z_(1−α) · 2 √D_ab (docs/gap.md, 'Look-alikes'); "
        f"a pair of effects leads only when "
        f"{'' if res['settings'].get('pair_beside_single') else 'no single effect passes, '}"
        f"both its effects are needed and it beats every single effect "
        f"by more than that, and a single best is no confident answer when a pair holding it beats it by "
        f"more than the margin with its magnitude outside its interval (docs/gap.md, 'Two effects at once').  "
        f"Error budget: noise, the measured discretisation error and the model-form level -- "
        f"{ev.get('model_form_note', 'none')}."
    )
    if ev["outcome"] == "ambiguous" and res.get("proposal"):
        L += _md_proposal(res["proposal"])
    L += _md_ranking(ev)
    L += _md_where(wh)
    L += _md_shrink(res)
    L += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figs]
    L += ["", "Method and equations: docs/gap.md, 'Method'.", ""]
    return "\n".join(L)


def _md_proposal(p: dict) -> list[str]:
    """The report's lines on what would separate an ambiguous set."""
    L: list[str] = []
    cols = (
        ["now (these phantoms)"]
        + (["plate force"] if p["force"] else [])
        + (["second depth"] if p["second_depth"] else [])
    )
    L += [
        "",
        "### Cannot be told apart with these phantoms — what would separate them",
        "",
        "Predicted separation of each pair in noise units, sqrt(Σ ((f_a − f_b)/S)²):",
        "",
        "| pair | " + " | ".join(cols) + " |",
        "|---" * (len(cols) + 1) + "|",
    ]
    for k, v in p["now"].items():
        vals = [v] + ([p["force"][k]] if p["force"] else []) + ([p["second_depth"][k]] if p["second_depth"] else [])
        L.append(f"| {k} | " + " | ".join(f"{x:.3g}" for x in vals) + " |")
    L += [""]
    if p.get("force_note") and p["force"]:
        L.append(f"* plate force: {p['force_note']}.")
    if p.get("second_depth_note"):
        L.append(f"* second depth: {p['second_depth_note']}.")
    for ph in p["phantoms"]:
        sv = ph.get("solved_pair_separation")
        L.append(
            f"* new phantom d {ph['d']:.3g} mm, h {ph['h']:.3g} mm, E {ph['E']:.3g} kPa: emulated min pair "
            f"separation {ph['predicted_min_pair_separation']:.3g}"
            + (f"; solved: {', '.join(f'{k} {v:.3g}' for k, v in sv.items())}" if sv else "")
        )
    L += [
        f"* ({p['phantoms_note']}.)",
        "",
        f"**Recommended next measurement: {p['recommendation']['measurement']}** "
        f"(smallest pair separation {p['recommendation']['min_pair_separation_noise_units']:.3g} noise units).",
    ]
    return L


def _vs_best(v: dict | None) -> str:
    """A ranking row against the best (:func:`elastimap.gap.selection.told_apart`): D_ab, the noise
    2 √D_ab of the χ² difference and whether the phantoms tell it apart ("—" when not compared)."""
    if not v:
        return "—"
    why = [w for k, w in (("margin", "margin"), ("within_noise", "within the noise")) if v[k]]
    verdict = "told apart" if v["told_apart"] else "not told apart (" + ", ".join(why) + ")"
    if v.get("shadow"):
        verdict += "; a family held at its grid ends within the noise: the best is not confident"
    return f"{v['separation']:.3g}, {v['noise']:.3g}: {verdict}"


def _md_ranking(ev: dict) -> list[str]:
    """The report's ranking table and its table of every view."""
    L: list[str] = []
    L += [
        "",
        "## Which effect (cross-validated ranking)",
        "",
        "| rank | effect | k | fitted magnitude [95 % interval] | held-out χ² | red. | passes | Δscore | explained | χ² by view (held-out) | vs the best: D_ab, 2 √D_ab |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for k, r in enumerate(ev["ranking"], 1):
        edge = " (end of its range)" if r["at_grid_edge"] else ""
        if r.get("extended_to"):  # a fit at the grid's end: the range was extended
            ex = "; ".join(f"{n} {', '.join(f'{x:.4g}' for x in v)}" for n, v in r["extended_to"].items())
            edge += f" (range extended to {ex})"
        if r.get("adaptive"):  # solved at a few magnitudes: say whether its fit was solved too
            sm = "; ".join(f"{n} {', '.join(f'{x:.4g}' for x in v)}" for n, v in r["solved_magnitudes"].items())
            edge += f" (solved at {sm}{'' if r['refined'] else '; emulated, not refined'})"
        byv = ", ".join(f"{a} {b:.3g}" for a, b in r["chi2_cv_by_view"].items())
        L.append(
            f"| {k} | {r['effect']} | {r['n_params']} | {_mag(r)}{edge} | {r['ssr_cv']:.4g} | {r['reduced_chi2_cv']:.3g} | "
            f"{'yes' if r['passes'] else 'no'} | {r['delta_score']:.3g} | {100 * r['explained_fraction']:.1f} % | {byv} | "
            f"{_vs_best(r.get('vs_best'))} |"
        )
    L += [
        "",
        "score = held-out χ² + k ln N; explained = 1 − held-out χ² / baseline χ² (descriptive only); "
        "D_ab: the fitted predictions' separation from the best's in error units, 2 √D_ab: the sd of a χ² "
        "difference between them from the error alone (docs/gap.md, 'Look-alikes').",
        "",
    ]
    L += [
        "## Every view",
        "",
        "| view | terms | χ² noise only | χ² noise + model error | threshold | significant | "
        "median model error (relative) | median noise (relative) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for k, b in ev["by_view"].items():
        L.append(
            f"| {k} | {b['n_terms']} | {b['chi2_noise_only']:.4g} | {b['chi2']:.4g} | {b['threshold']:.4g} | "
            f"{'yes' if b['significant'] else 'no'} | {', '.join(f'{100 * x:.2g} %' for x in b['model_error_relative_median'])} | "
            f"{', '.join(f'{100 * x:.2g} %' for x in b['noise_relative_median'])} |"
        )
    return L


def _md_where(wh: dict) -> list[str]:
    """The report's lines on where the gap lies (feature, region, stage, image)."""
    L: list[str] = []
    L += [
        "",
        "## Where the gap lies",
        "",
        "### By feature",
        "",
        "| feature | mean relative gap | 95 % CI | RMS (noise + model units) | noise (relative) | model error (relative) |",
        "|---|---|---|---|---|---|",
    ]
    for k in FEATURES:
        b = wh["by_feature"][k]
        L.append(
            f"| {k} | {_pct(b['relative_gap_mean'])} | {_pct(b['relative_gap_ci'][0])} – {_pct(b['relative_gap_ci'][1])} "
            f"| {b['noise_units_rms']:.3g} | {100 * b['noise_floor_relative']:.3g} % | {100 * b['model_error_relative']:.3g} % |"
        )
    L += [
        "",
        "### By region of (d, h, E)",
        "",
        "| parameter | range | n | RMS gap (noise units) | 95 % CI | rel. gap O1 / O2 / O3 |",
        "|---|---|---|---|---|---|",
    ]
    for q, bins in wh["by_region"].items():
        for b in bins:
            g = b["relative_gap_mean"]
            L.append(
                f"| {q} | {b['range'][0]:.3g} – {b['range'][1]:.3g} | {b['n']} | {b['rms_noise_units']:.3g} | "
                f"{b['rms_ci'][0]:.3g} – {b['rms_ci'][1]:.3g} | {_pct(g['O1'])} / {_pct(g['O2'])} / {_pct(g['O3'])} |"
            )
    st = wh["stage"]
    L += [
        "",
        "### By pipeline stage",
        "",
        f"* optics-like share (what a per-feature affine camera recalibration absorbs, held-out): "
        f"{100 * st['optics_like_affine_share']:.1f} %; mechanics-like remainder {100 * st['mechanics_like_share']:.1f} % "
        "(an upper bound for optics: a mechanical effect that scales a feature uniformly also looks affine).",
    ]
    if st.get("best_mechanics_candidate"):
        L.append(
            f"* best mechanics effect: `{st['best_mechanics_candidate'][0]}` ({100 * st['best_mechanics_candidate'][1]:.1f} % explained); "
            + (
                f"best optics effect: `{st['best_optics_candidate'][0]}` ({100 * st['best_optics_candidate'][1]:.1f} %)."
                if st.get("best_optics_candidate")
                else "no optics candidate tested."
            )
        )
    if st.get("inverse_own_error"):
        own, mea = st["inverse_own_error"], st["inverse_error_on_measured"]
        L.append(
            "* inverse stage (mean relative error on the withheld phantoms): own error on noise-free baseline "
            f"simulations d {100 * own['d']:.1f} %, h {100 * own['h']:.1f} %, E {100 * own['E']:.1f} %; on the measured "
            f"features d {100 * mea['d']:.1f} %, h {100 * mea['h']:.1f} %, E {100 * mea['E']:.1f} %."
        )
    if "image" in wh:
        L += _md_image(wh)
    return L


def _md_image(wh: dict) -> list[str]:
    """The report's lines on the image residual by annulus."""
    im = wh["image"]
    L: list[str] = []
    L += [
        "",
        "### By image region",
        "",
        f"Mean residual (measured − baseline) of the camera difference images over {im['n']} phantoms "
        f"(`residual_map.png`); noise band = noise of the mean ({im['noise_kind']}) and the model error per pixel; "
        f"largest |mean residual| = {im['max_abs_z']:.3g} × its band.",
        "",
        "| annulus (mm) | mean residual (FS) | band (FS) | noise units |" + (" after |" if "image_after" in wh else ""),
        "|---|---|---|---|" + ("---|" if "image_after" in wh else ""),
    ]
    after = {tuple(r["r_mm"]): r for r in wh["image_after"]["rings"]} if "image_after" in wh else {}
    for r in im["rings"]:
        a = after.get(tuple(r["r_mm"]))
        L.append(
            f"| {r['r_mm'][0]:g} – {r['r_mm'][1]:g} | {r['mean_residual']:.3g} | {r['band']:.3g} | {r['noise_units']:+.2f} |"
            + (f" {a['noise_units']:+.2f} |" if a else "")
        )
    if "image_after" in wh:
        L.append(f"\n(after: residual once `{wh['image_after']['effect']}` at its fitted magnitude is added.)")
    return L


def _md_shrink(res: dict) -> list[str]:
    """The report's lines on how far the gap shrinks (withheld phantoms, retrained inverse)."""
    ev = res["evaluation"]
    L: list[str] = []
    L += ["", "## How far it shrinks (withheld phantoms)", ""]
    sf = res.get("shrink_features")
    if sf:
        L += [
            f"Magnitude refitted on {len(sf['fit_phantoms'])} phantoms, gap measured on {len(sf['withheld'])} withheld "
            f"({', '.join(sf['withheld'])}) with `{ev['best']}` at {', '.join(f'{x:.4g}' for x in sf['magnitude'])}:",
            "",
            f"| | RMS ({' + '.join(sf['views'])}, noise + model units) | rel. gap O1 | O2 | O3 |",
            "|---|---|---|---|---|",
            f"| before (baseline) | {sf['rms_noise_units_before']:.3g} | "
            + " | ".join(f"{100 * sf['relative_gap_before'][k]:.2f} %" for k in FEATURES)
            + " |",
            f"| after | {sf['rms_noise_units_after']:.3g} | "
            + " | ".join(f"{100 * sf['relative_gap_after'][k]:.2f} %" for k in FEATURES)
            + " |",
            "",
            f"Gap shrink: **{100 * sf['shrink']:.1f} %**.",
        ]
    si = res.get("shrink_inverse")
    if si:
        L += [
            "",
            f"(d, h, E) after retraining the inverse (SCG ensemble, {si['n_train']} simulations each):",
            "",
            "| inverse | d | h | E | mean |",
            "|---|---|---|---|---|",
        ]
        for name, lab in (
            ("inverse_own", "baseline inverse on noise-free baseline sims (own error)"),
            ("before", "baseline inverse on measured"),
            ("after", "retrained with the effect, on measured"),
        ):
            e = si[name]["mean_relative_error"]
            L.append(
                f"| {lab} | {100 * e['d']:.1f} % | {100 * e['h']:.1f} % | {100 * e['E']:.1f} % | "
                f"{100 * np.mean(list(e.values())):.1f} % |"
            )
        L += ["", f"(d, h, E) error shrink: **{100 * si['shrink']:.1f} %**."]
    return L


def to_html(md: str, folder: Path) -> str:
    """A plain self-contained HTML page from the Markdown (tables, headings, lists, images inlined)."""

    def inline(t: str) -> str:
        t = html.escape(t)
        t = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", t)
        t = re.sub(r"`(.+?)`", r"<code>\1</code>", t)
        return t

    out, table = [], False
    for line in md.splitlines():
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if all(set(c) <= set("-: ") for c in cells):
                continue
            if not table:
                out.append("<table>")
                table = True
                out.append("<tr>" + "".join(f"<th>{inline(c)}</th>" for c in cells) + "</tr>")
            else:
                out.append("<tr>" + "".join(f"<td>{inline(c)}</td>" for c in cells) + "</tr>")
            continue
        if table:
            out.append("</table>")
            table = False
        m = re.match(r"!\[(.*?)\]\((.*?)\)", line)
        if m:
            p = folder / m.group(2)
            if p.exists():
                b64 = base64.b64encode(p.read_bytes()).decode()
                out.append(
                    f'<p><img alt="{html.escape(m.group(1))}" src="data:image/png;base64,{b64}" style="max-width:100%"></p>'
                )
            continue
        h = re.match(r"(#+) (.*)", line)
        if h:
            n = len(h.group(1))
            out.append(f"<h{n}>{inline(h.group(2))}</h{n}>")
        elif line.startswith("* "):
            out.append(f"<ul><li>{inline(line[2:])}</li></ul>")
        elif line.startswith("> "):
            out.append(f"<blockquote>{inline(line[2:])}</blockquote>")
        elif line.strip():
            out.append(f"<p>{inline(line)}</p>")
    if table:
        out.append("</table>")
    style = (
        "body{font-family:sans-serif;max-width:1100px;margin:2em auto;line-height:1.4}"
        "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #bbb;padding:2px 6px;font-size:90%}"
        "blockquote{background:#fee;padding:.5em 1em;border-left:4px solid #c00}"
    )
    return (
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>gap diagnosis</title><style>{style}</style>"
        f"</head><body>{''.join(out)}</body></html>\n"
    )


def _subplots(*shape, figsize):
    """A figure and its axes, without pyplot (no global figure state, no backend switch)."""
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(*shape)


def _figures(res: dict, out: Path) -> list[str]:
    syn = "SYNTHETIC — " if res["measured"]["synthetic"] else ""
    figs = []
    ev, wh = res["evaluation"], res["where"]
    dhe = np.asarray(res["measured"]["dhe"])
    rel = wh["relative_gap"]
    me = res["_model_error"]
    y0 = res["_V0"]["features"]
    yv, se = res["_views"]["features"]
    band = np.sqrt(se**2 + me["sigma"]["features"] ** 2) / np.abs(y0)
    fig, axes = _subplots(3, 3, figsize=(11, 9))
    for q, name in enumerate(("d (mm)", "h (mm)", "E (kPa)")):
        for j, k in enumerate(FEATURES):
            ax = axes[j, q]
            ax.errorbar(
                dhe[:, q],
                100 * rel[:, j],
                yerr=100 * band[:, j],
                fmt="o",
                ms=4,
                capsize=2,
                label="gap ± (noise + model error)",
            )
            ax.axhline(0, color="k", lw=0.5)
            ax.set_xlabel(name)
            ax.set_ylabel(f"{k} gap (%)")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"{syn}measured − simulated (baseline), relative, per phantom")
    fig.tight_layout()
    fig.savefig(out / "gap_by_region.png", dpi=80)
    figs.append("gap_by_region.png")

    rows = ev["ranking"]
    fig, ax = _subplots(figsize=(7, 0.32 * len(rows) + 1.6))
    names = [r["effect"] for r in rows][::-1]
    setn = {v["_row"]["effect"] for v in ev.get("reported", {}).values()} if ev["ambiguous_set"] else set()
    ax.barh(names, [r["ssr_cv"] for r in rows][::-1], color=["C2" if r["effect"] in setn else "C0" for r in rows][::-1])
    ax.axvline(ev["chi2_threshold"], color="r", ls="--", lw=1, label=f"χ²_N(1−α), α={ev['alpha']:g}")
    ax.axvline(ev["chi2_baseline"], color="k", ls=":", lw=1, label="baseline")
    ax.set_xscale("log")
    ax.set_xlabel("held-out χ² (noise + model error)")
    ax.legend(fontsize=8)
    ax.set_title(f"{syn}candidates (green: reported set)")
    fig.tight_layout()
    fig.savefig(out / "candidates.png", dpi=80)
    figs.append("candidates.png")

    if "profile" in res["_views"]:
        _profile_figure(res, rows, syn, out)
        figs.append("profile.png")
    if "image" in wh:
        _residual_map_figure(res, syn, out)
        figs.append("residual_map.png")
    return figs


def _profile_figure(res: dict, rows: list[dict], syn: str, out: Path) -> None:
    """profile.png: left, each phantom's radial profile of the difference image, measured
    (markers) and baseline model (dashed), one colour per phantom; right, the normalised residual
    (measured − baseline) / S per annulus with the RMS over the phantoms before and after the best
    candidate, S = sqrt(se² + σ_model²)."""
    ev = res["evaluation"]
    me = res["_model_error"]
    P, Pse = res["_views"]["profile"]
    P0 = res["_V0"]["profile"]
    S = np.sqrt(Pse**2 + me["sigma"]["profile"] ** 2)
    z = (P - P0) / S
    rc = 0.5 * (np.asarray(EDGES[:-1]) + np.asarray(EDGES[1:]))
    ids = res["measured"]["ids"]
    fig, axes = _subplots(1, 2, figsize=(12, 4.6))
    for i in range(len(P)):
        c = f"C{i % 10}"
        axes[0].plot(rc, P[i], "o-", ms=4, lw=0.8, color=c, label=f"phantom {ids[i]}")
        axes[0].plot(rc, P0[i], "--", lw=1.0, color=c)
        axes[1].plot(rc, z[i], "o-", ms=3, lw=0.6, color=c, alpha=0.7)
    style = [
        Line2D([], [], color="0.3", marker="o", ms=4, lw=0.8, label="measured"),
        Line2D([], [], color="0.3", ls="--", lw=1.0, label="baseline model"),
    ]
    handles, _ = axes[0].get_legend_handles_labels()
    axes[0].legend(handles=style + handles, fontsize=7, ncol=2, loc="upper right")
    best = next((r for r in rows if r["effect"] == ev["best"]), None)
    if best is not None and "profile" in ev["views"]:
        f = best["_model"].predict(best["_theta"], ["profile"])
        za = (P - f) / S
        axes[1].plot(rc, np.sqrt(np.mean(z**2, axis=0)), "k:", lw=2, label="RMS over phantoms, baseline")
        axes[1].plot(rc, np.sqrt(np.mean(za**2, axis=0)), "k-", lw=2, label=f"RMS over phantoms, with {ev['best']}")
    axes[1].axhspan(-1, 1, color="0.85", label="±1 S (noise + model error)")
    axes[1].axhline(0, color="k", lw=0.5)
    axes[0].set_title("radial profile of the difference image", fontsize=10)
    axes[0].set_xlabel("r, distance from the probe axis (mm)")
    axes[0].set_ylabel("annulus mean of D (fraction of full scale)")
    axes[1].set_title("normalised residual, one line per phantom", fontsize=10)
    axes[1].set_xlabel("r, distance from the probe axis (mm)")
    axes[1].set_ylabel("(measured − baseline) / S")
    axes[1].legend(fontsize=7)
    fig.suptitle(f"{syn}radial profile of the camera difference images ({len(P)} phantoms)")
    fig.tight_layout()
    fig.savefig(out / "profile.png", dpi=150)


def _residual_map_figure(res: dict, syn: str, out: Path) -> None:
    """residual_map.png: the mean difference images over the phantoms, measured and simulated
    (viridis, one colour scale), their mean residual (diverging, symmetric) and the residual in
    units of its band (noise of the mean + model error; diverging, one symmetric scale for before
    and after the best candidate).  Axes in mm from the probe axis."""
    wh = res["where"]
    im = wh["image"]
    ny, nx = np.shape(im["mean_residual"])
    pix = im["pixel_mm"]
    ext = [-nx / 2 * pix, nx / 2 * pix, -ny / 2 * pix, ny / 2 * pix]  # pixel edges, centre on the axis
    zs = [im["z"]] + ([wh["image_after"]["z"]] if "image_after" in wh else [])
    zr = max(3.0, float(np.percentile(np.abs(im["z"]), 99)))
    vr = max(float(np.max(np.abs(im["mean_residual"]))), 1e-12)
    lo = float(min(np.min(im["mean_measured"]), np.min(im["mean_simulated"])))
    hi = float(max(np.max(im["mean_measured"]), np.max(im["mean_simulated"])))
    panels = [
        ("mean measured D", im["mean_measured"], "D (fraction of full scale)", dict(cmap="viridis", vmin=lo, vmax=hi)),
        (
            "mean simulated D (baseline)",
            im["mean_simulated"],
            "D (fraction of full scale)",
            dict(cmap="viridis", vmin=lo, vmax=hi),
        ),
        (
            "mean residual",
            im["mean_residual"],
            "measured − simulated (fraction of full scale)",
            dict(cmap="RdBu_r", vmin=-vr, vmax=vr),
        ),
        ("residual / band, baseline", zs[0], "(measured − simulated) / band", dict(cmap="RdBu_r", vmin=-zr, vmax=zr)),
    ]
    if len(zs) > 1:
        panels.append(
            (
                f"residual / band, with {wh['image_after']['effect']}",
                zs[1],
                "(measured − simulated) / band",
                dict(cmap="RdBu_r", vmin=-zr, vmax=zr),
            )
        )
    fig, axes = _subplots(2, 3, figsize=(12.5, 8.0))
    for ax, (t, a, u, kw) in zip(axes.flat, panels):
        h = ax.imshow(a, origin="lower", extent=ext, **kw)
        ax.set_title(t, fontsize=9)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        cb = fig.colorbar(h, ax=ax, shrink=0.85)
        cb.set_label(u, fontsize=8)
    for ax in list(axes.flat)[len(panels) :]:
        ax.set_axis_off()
    fig.suptitle(
        f"{syn}camera difference images, mean over {im['n']} phantoms "
        f"(band: noise of the mean + model error; residual/band shown to ±{zr:.3g})"
    )
    fig.tight_layout()
    fig.savefig(out / "residual_map.png", dpi=150)
