"""Blind benchmark of the diagnosis with model-form error (``gap selftest``).

The measured data of every trial come from **another discretisation or formulation** than the
diagnosis uses: by default the next finer mesh level, sized by the inclusion's diameter
(``sizing="by_d"``: a finer zone around it) and with the unilateral ``contact`` interface, rendered
through the camera with frame noise.  The diagnosis uses the tied interface and the fixed sizing
on its own mesh and estimates its model error against the next finer tied, fixed-sizing mesh, so
no level of its own is the data's.  (For the 12 bench phantoms without an effect the contact
does not open: at the default mesh ``contact`` and ``tied`` give the same O1, O2, O3 and force
to every stored digit — checked without effects only; the sizing
is what makes the data's discretisation differ from the error mesh's, by 0.02–0.4 % in O1, O2,
O3 and the plate force of two bench phantoms.)  Trials cycle through
three kinds:

* **none** -- no effect at all: the right answer is "no significant gap" (with the model-form
  level: "no gap beyond the model-form level");
* **in** -- one effect drawn from the candidates, magnitude uniform over its ``blind`` range:
  right when the reported set (the winner, or the ambiguity set) holds it; its fitted magnitude
  is scored against its 95 % interval;
* **out** -- one effect that is *not* among the candidates (``outside``, default
  aspect, skin, led_imbalance, stray_light; the outside-only ``core_shell`` and the
  phantom-labelling errors ``mislabel_d``, ``mislabel_h``, ``mislabel_E`` may be named too, a
  labelling error on one phantom drawn per trial; a candidate named here, ``lens_distortion``
  say, leaves the candidates): answering "explained" or "ambiguous" is a
  confident wrong attribution.

The label is sealed (a SHA-256 commitment is visible; it opens only once the answer is
recorded).  Scores: no-effect "no significant gap" rate, in-library set-holds-truth rate and
interval coverage, out-of-library confident-wrong rate, confusion matrix.  SYNTHETIC data.
"""

from __future__ import annotations

import hashlib
import json
import time

import numpy as np

from elastimap.errors import UserError

from . import effects as fx
from .diagnose import diagnose
from .selection import common_factor, isolated_member
from .settings import Settings
from .simulate import Simulator
from .synth import phantom_design, synthesize

OUTSIDE = ("aspect", "skin", "led_imbalance", "stray_light")
KINDS = ("none", "in", "out", "in")
GOALS = {
    "no_effect_no_gap_rate": (">=", 0.9),
    "in_library_set_holds_truth_rate": (">=", 0.9),
    "in_library_interval_coverage": ("in", (0.9, 0.98)),
    "out_of_library_confident_wrong_rate": ("<=", 0.1),
}


class Sealed:
    """A label that can be opened only once the prediction is recorded."""

    def __init__(self, truth: dict, salt: str):
        self._blob = json.dumps(truth, sort_keys=True)
        self.commitment = hashlib.sha256((salt + self._blob).encode()).hexdigest()
        self._salt = salt

    def open(self, prediction_recorded: bool) -> dict:
        if not prediction_recorded:
            raise RuntimeError("the label is sealed until the prediction is recorded")
        assert hashlib.sha256((self._salt + self._blob).encode()).hexdigest() == self.commitment
        return json.loads(self._blob)


def _sig(x: float, n: int = 3) -> float:
    return float(f"{x:.{n}g}")


def default_candidates(outside=OUTSIDE) -> list[fx.Effect]:
    return [fx.EFFECTS[n] for n in fx.DEFAULT_CANDIDATES if n not in outside]


def run(
    trials: int,
    sim: Simulator,
    sim_data: Simulator,
    candidates: list[fx.Effect],
    outside: list[fx.Effect],
    sim_fine: Simulator | None = None,
    n_phantoms: int = 12,
    frames: int = 10,
    seed: int = 0,
    st: Settings | None = None,
    data_disc: dict | None = None,
    log=print,
    on_trial=None,
    start: int = 0,
    phantom_seed: int | None = None,
) -> dict:
    """``sim``: the diagnosis's simulator; ``sim_fine``: its model-error level; ``sim_data`` (with
    ``data_disc``, e.g. ``{"interface": "contact"}``): what generates the measured data.
    ``start``: run trials start..trials-1 only (the same draws as a whole run: resume a cut run).
    ``seed`` draws the trials (effects, magnitudes, frame noise); ``phantom_seed`` (default:
    ``seed``) the phantom set, which a lab keeps from one diagnosis to the next.  Out-of-library
    trials take the outside effects in a seeded random order, each in turn, so every one is
    tried once there are as many out trials as outside effects."""
    st = st or Settings(inverse=False)
    names = {e.name for e in candidates}
    clash = [e.name for e in outside if e.name in names]
    if clash:
        raise ValueError(f"outside effects {clash} are also candidates")
    rng = np.random.default_rng(seed)
    phantom_seed = seed if phantom_seed is None else phantom_seed
    dhe = phantom_design(n_phantoms, phantom_seed)
    order = rng.permutation(len(outside))  # the outside effects' turn order
    n_out = 0
    out_trials = []
    void: list[dict] = []
    t0 = time.perf_counter()

    def summary(done):
        return _summary(
            done,
            trials,
            sim,
            sim_data,
            sim_fine,
            candidates,
            outside,
            n_phantoms,
            frames,
            seed,
            st,
            data_disc,
            t0,
            start,
        ) | {"void_trials": list(void), "phantom_seed": phantom_seed}

    for t in range(trials):
        kind = KINDS[t % len(KINDS)]
        truth, effs = _draw(kind, candidates, outside, order, n_out, rng)
        if any(e.stage == "label" for e, _ in effs):  # its own stream: the other draws stay as they were
            truth["label_phantom"] = int(np.random.default_rng([seed, t]).integers(n_phantoms))
        n_out += kind == "out"
        sealed = Sealed(truth, salt=f"{seed}-{t}-{rng.integers(1 << 30)}")
        if t < start:  # resumed run: the draws of the earlier trials are replayed, not their work
            continue
        try:
            meas, _ = synthesize(
                dhe,
                effs,
                sim_data,
                frames=frames,
                seed=seed * 1000 + t,
                disc=data_disc,
                label_phantom=truth.get("label_phantom", 0),
            )
        except UserError as exc:  # the data could not be made: the trial is void (not scored), the run goes on
            opened = sealed.open(prediction_recorded=True)
            void.append({"trial": t, **opened, "error": str(exc)})
            if log:
                log(f"trial {t + 1}/{trials} VOID: {opened['effect']}={opened['magnitude']} data failed: {exc}")
            if on_trial is not None:
                on_trial(summary(out_trials))
            continue
        meas.description = "SYNTHETIC selftest trial (label sealed)"
        del effs, truth
        ts = time.perf_counter()
        res = diagnose(meas, candidates, sim, st, sim_fine)
        ev = res["evaluation"]
        answer = ev["winner"] if ev["outcome"] == "explained" else ev["outcome"]
        rec = {
            "trial": t,
            "commitment": sealed.commitment,
            "answer": answer,
            "outcome": ev["outcome"],
            "set": list(ev["ambiguous_set"]),
            "best": ev["best"],
            "reduced_chi2_baseline": ev["reduced_chi2_baseline"],
            "best_reduced_chi2_cv": ev["ranking"][0]["reduced_chi2_cv"],
            "seconds": time.perf_counter() - ts,
            "proposal": (res["proposal"] or {}).get("recommendation"),
        }
        truth = sealed.open(prediction_recorded=True)
        rec.update(kind=truth["kind"], true_effect=truth["effect"], true_magnitude=truth["magnitude"])
        if "label_phantom" in truth:
            rec["label_phantom"] = meas.ids[truth["label_phantom"]]
        _score(rec, truth, ev)
        out_trials.append(rec)
        if log:
            log(_trial_line(t, trials, truth, answer, rec, ev, time.perf_counter() - t0))
        if on_trial is not None:
            on_trial(summary(out_trials))
    return summary(out_trials)


def _draw(kind: str, candidates, outside, order, n_out: int, rng) -> tuple[dict, list]:
    """A trial's label and effects: none; an in-library effect drawn from the candidates; or the
    next outside effect in the seeded ``order``; magnitude uniform over the effect's blind range."""
    if kind == "none":
        return {"kind": "none", "effect": "none", "magnitude": None}, []
    if kind == "out":
        e = outside[int(order[n_out % len(outside)])]
    else:
        e = candidates[int(rng.integers(len(candidates)))]
    m = _sig(rng.uniform(*e.blind))
    return {"kind": kind, "effect": e.name, "magnitude": m}, [(e, m)]


def _score(rec: dict, truth: dict, ev: dict) -> None:
    """Score a trial's answer against its opened label (in place): right or wrong, and for an
    in-library effect the reported magnitude, its interval's coverage and its error."""
    rows = {r["effect"]: r for r in ev["ranking"]}
    if truth["kind"] == "none":
        rec["right"] = ev["outcome"] == "no significant gap"
    elif truth["kind"] == "in":
        # the reported set holds the truth: by name, or as a member of a reported pair of effects
        pair = next(
            (
                n
                for n in ev["ambiguous_set"]
                if n in rows and rows[n].get("pair") and truth["effect"] in rows[n]["members"]
            ),
            None,
        )
        rec["right"] = truth["effect"] in ev["ambiguous_set"] or pair is not None
        rec["via"] = (pair or ev["reported"][truth["effect"]]["via"]) if rec["right"] else None
        rec["family_member_right"] = rec["right"] or any(
            family_isolates(rows[n], truth["effect"]) for n in ev["ambiguous_set"] if n in rows
        )
        # the magnitude scored: the reported one (a family's member fit when reported via it, a pair's member)
        r = ev["reported"][truth["effect"]] if rec["right"] and pair is None else rows.get(pair or truth["effect"])
        if r is not None:
            j = r["members"].index(truth["effect"]) if pair is not None else 0
            rec["fitted_magnitude"], rec["fitted_ci"] = r["magnitude"][j], r["magnitude_ci"][j]
            rec["ci_covers_truth"] = bool(r["magnitude_ci"][j][0] <= truth["magnitude"] <= r["magnitude_ci"][j][1])
            eff = fx.get(truth["effect"])
            rec["magnitude_error_rel_effect"] = abs(r["magnitude"][j] - truth["magnitude"]) / abs(
                truth["magnitude"] - eff.nominal
            )
    else:
        rec["confident_wrong"] = ev["outcome"] in ("explained", "ambiguous")
        rec["right"] = not rec["confident_wrong"]


def _trial_line(t: int, trials: int, truth: dict, answer: str, rec: dict, ev: dict, seconds: float) -> str:
    """The log line of one scored trial."""
    return (
        f"trial {t + 1}/{trials} [{truth['kind']}] true {truth['effect']}"
        + (f"={truth['magnitude']:g}" if truth["magnitude"] is not None else "")
        + f" -> {answer}"
        + (f" {rec['set']}" if ev["outcome"] == "ambiguous" else "")
        + f" (baseline red.chi2 {ev['reduced_chi2_baseline']:.3g}, best {ev['best']} "
        f"red.chi2 {rec['best_reduced_chi2_cv']:.3g})  [{seconds:.0f} s]"
    )


def family_isolates(row: dict, effect: str) -> bool:
    """Whether a family (a ranking row with several members) names ``effect`` alone
    (:func:`elastimap.gap.selection.isolated_member`, :func:`elastimap.gap.selection.common_factor`)."""
    cf = common_factor(row)
    return isolated_member(row) == effect or (cf is not None and cf[0] == effect)


def _summary(
    out_trials, trials, sim, sim_data, sim_fine, candidates, outside, n_phantoms, frames, seed, st, data_disc, t0, start
):
    return score(out_trials, [e.name for e in candidates]) | {
        "trials_planned": trials - start,
        "first_trial": start,
        "partial": len(out_trials) < trials - start,
        "trials": out_trials,
        "n_phantoms": n_phantoms,
        "frames": frames,
        "seed": seed,
        "mesh": sim.mesh,
        "error_mesh": sim_fine.mesh if sim_fine is not None else None,
        "data_mesh": sim_data.mesh,
        "data_disc": data_disc or {},
        "backend": sim.backend,
        "candidates": [e.name for e in candidates],
        "outside": [e.name for e in outside],
        "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in st.__dict__.items()},
        "simulator": dict(sim.stats),
        "data_simulator": dict(sim_data.stats),
        "seconds": time.perf_counter() - t0,
    }


def _rate(xs) -> float:
    return float(np.mean(xs)) if len(xs) else float("nan")


def score(trials: list[dict], names: list[str]) -> dict:
    none = [r for r in trials if r["kind"] == "none"]
    inl = [r for r in trials if r["kind"] == "in"]
    out = [r for r in trials if r["kind"] == "out"]
    cov = [r["ci_covers_truth"] for r in inl if "ci_covers_truth" in r]
    me = [r["magnitude_error_rel_effect"] for r in inl if r["right"] and "magnitude_error_rel_effect" in r]
    res = {
        "n_trials": len(trials),
        "n_none": len(none),
        "n_in": len(inl),
        "n_out": len(out),
        "no_effect_no_gap_rate": _rate([r["right"] for r in none]),
        "in_library_set_holds_truth_rate": _rate([r["right"] for r in inl]),
        "in_library_single_winner_right_rate": _rate([r["answer"] == r["true_effect"] for r in inl]),
        "in_library_family_member_rate": _rate([r.get("family_member_right", r["right"]) for r in inl]),
        "in_library_interval_coverage": _rate(cov),
        "magnitude_error_rel_effect_median": float(np.median(me)) if me else float("nan"),
        "out_of_library_confident_wrong_rate": _rate([r["confident_wrong"] for r in out]),
        "median_seconds_per_diagnosis": float(np.median([r["seconds"] for r in trials])) if trials else float("nan"),
    }
    cols = []
    conf: dict[str, dict[str, int]] = {}
    for r in trials:
        a = r["answer"] if r["outcome"] == "explained" else r["outcome"]
        if a not in cols:
            cols.append(a)
        conf.setdefault(r["true_effect"] + (" (outside)" if r["kind"] == "out" else ""), {})
        row = conf[r["true_effect"] + (" (outside)" if r["kind"] == "out" else "")]
        row[a] = row.get(a, 0) + 1
    res["confusion"] = {k: {c: v.get(c, 0) for c in cols} for k, v in conf.items()}
    goals = {}
    for k, (op, g) in GOALS.items():
        v = res[k]
        goals[k] = (
            None if not np.isfinite(v) else bool(v >= g if op == ">=" else v <= g if op == "<=" else g[0] <= v <= g[1])
        )
    goals["trials>=30"] = len(trials) >= 30
    res["goals"] = goals
    return res


def _p(x) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{100 * x:.0f} %"


def markdown(res: dict) -> str:
    form = ", ".join(f"{k} {v}" for k, v in res["data_disc"].items())
    L = [
        "# SYNTHETIC blind benchmark of the gap diagnosis (model-form error)",
        "",
        *(
            [f"**PARTIAL: {res['n_trials']} of {res['trials_planned']} planned trials finished.**", ""]
            if res.get("partial")
            else []
        ),
        f"{res['n_trials']} trials ({res['n_none']} no-effect, {res['n_in']} in-library, {res['n_out']} out-of-library), "
        f"backend `{res['backend']}`; diagnosis mesh `{res['mesh']}`, model error against `{res['error_mesh']}`; "
        f"**data from mesh `{res['data_mesh']}`{', ' + form if form else ''}**; {res['n_phantoms']} phantoms, "
        f"{res['frames']} frames, seed {res['seed']} (phantoms: seed {res.get('phantom_seed', res['seed'])}); {res['seconds']:.0f} s "
        f"(median {res['median_seconds_per_diagnosis']:.0f} s per diagnosis).",
        "",
        f"Candidates: {', '.join(res['candidates'])}.  Outside the candidates: {', '.join(res['outside'])}.",
        "",
        "| metric | value | goal |",
        "|---|---|---|",
        f'| no-effect sets called "no significant gap" | {_p(res["no_effect_no_gap_rate"])} | ≥ 90 % |',
        f"| in-library: reported set (winner or ambiguity set) holds the truth | {_p(res['in_library_set_holds_truth_rate'])} | ≥ 90 % |",
        f"| in-library: single winner is the truth | {_p(res['in_library_single_winner_right_rate'])} | |",
        f"| in-library: set holds the truth, or a family in it isolates the true member (only it off nominal) | {_p(res.get('in_library_family_member_rate', float('nan')))} | |",
        f"| in-library: 95 % interval covers the true magnitude | {_p(res['in_library_interval_coverage'])} | 90–98 % |",
        f"| in-library: magnitude error (median, relative to the effect size) | {_p(res['magnitude_error_rel_effect_median'])} | |",
        f"| out-of-library: confident wrong attribution | {_p(res['out_of_library_confident_wrong_rate'])} | ≤ 10 % |",
        "",
        "## Confusion matrix (rows: truth; columns: answer)",
        "",
    ]
    for v in res.get("void_trials", []):
        L.insert(-2, f"Trial {v['trial']} is VOID (not scored): its data could not be made ({v['error']}).")
    conf = res["confusion"]
    cols = list(next(iter(conf.values())).keys()) if conf else []
    L += ["| truth \\ answer | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for r, row in conf.items():
        L.append(f"| {r} | " + " | ".join(str(row[c]) for c in cols) + " |")
    L += [
        "",
        "## Trials",
        "",
        "| # | kind | truth | magnitude | answer | set | fitted [95 %] | baseline red. χ² | right |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in res["trials"]:
        fm = (
            f"{r['fitted_magnitude']:.4g} [{r['fitted_ci'][0]:.4g}, {r['fitted_ci'][1]:.4g}]"
            if "fitted_magnitude" in r
            else ""
        )
        mag = "" if r["true_magnitude"] is None else f"{r['true_magnitude']:g}"
        L.append(
            f"| {r['trial']} | {r['kind']} | {r['true_effect']} | {mag} | {r['answer']} | {', '.join(r['set'])} | "
            f"{fm} | {r['reduced_chi2_baseline']:.3g} | {'yes' if r['right'] else 'no'} |"
        )
    return "\n".join(L) + "\n"
