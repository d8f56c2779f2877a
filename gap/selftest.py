"""Blind check of the diagnosis (``gap selftest``): effects withheld from the analyst.

Each trial draws an effect uniformly from the candidates and a true magnitude uniformly from
its ``blind`` range (:mod:`elastimap.gap.effects`; ranges that move the features by well over 3x the
noise floor), generates SYNTHETIC measured data on a fixed phantom design, seals the label
(only a SHA-256 commitment is visible until scoring) and runs the diagnosis twice:

* mode **identify**: all candidates -> top-1 correct?  fitted-magnitude error, feature-space
  gap shrink on the withheld phantoms (and the (d, h, E) shrink with ``inverse``);
* mode **withheld**: the true effect removed from the candidates -> the right answer is
  "unexplained"; answering "explained" (by a wrong effect) is a confident wrong attribution.

Every solve goes through the :class:`elastimap.gap.simulate.Simulator` cache (true magnitudes are
rounded to 3 significant digits so reruns hit the cache).
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import replace

import numpy as np

from . import effects as fx
from .diagnose import Settings, diagnose
from .simulate import Simulator
from .synth import phantom_design, synthesize


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


def run(trials: int, sim: Simulator, candidates: list[fx.Effect], n_phantoms: int = 12, frames: int = 10,
        seed: int = 0, st: Settings | None = None, withheld_mode: bool = True, log=print) -> dict:
    st = st or Settings(inverse=False)
    rng = np.random.default_rng(seed)
    dhe = phantom_design(n_phantoms, seed)
    names = [e.name for e in candidates]
    out_trials = []
    t0 = time.perf_counter()
    for t in range(trials):
        e = candidates[int(rng.integers(len(candidates)))]
        m = _sig(rng.uniform(*e.blind))
        sealed = Sealed({"effect": e.name, "magnitude": m}, salt=f"{seed}-{t}-{rng.integers(1 << 30)}")
        meas, _ = synthesize(dhe, [(e, m)], sim, frames=frames, seed=seed * 1000 + t)
        meas.description = "SYNTHETIC selftest trial (label sealed)"
        del e, m                                # the analyst below sees only the data
        res = diagnose(meas, candidates, sim, st)
        ev = res["evaluation"]
        pred = ev["winner"] if ev["outcome"] == "explained" else ev["outcome"]
        fitted = {r["effect"]: (r["magnitude"], r["magnitude_ci"]) for r in ev["ranking"]}
        rec = {"trial": t, "commitment": sealed.commitment, "prediction": pred, "runner_up": ev["runner_up"],
               "best": ev["best"], "outcome": ev["outcome"],
               "explained_fraction": ev["ranking"][0]["explained_fraction"],
               "reduced_chi2_cv": ev["ranking"][0]["reduced_chi2_cv_with_interpolation"],
               "reduced_chi2_baseline": ev["reduced_chi2_baseline"],
               "shrink_features": res["shrink_features"]["shrink"] if res["shrink_features"] else None,
               "shrink_inverse": res["shrink_inverse"]["shrink"] if res["shrink_inverse"] else None}
        res_w = None
        if withheld_mode:
            # the true effect's name is needed to remove it: the analyst still never sees it
            truth_name = json.loads(sealed._blob)["effect"]
            cands_w = [c for c in candidates if c.name != truth_name]
            res_w = diagnose(meas, cands_w, sim, replace(st, inverse=False))
            evw = res_w["evaluation"]
            rec["withheld_prediction"] = evw["winner"] if evw["outcome"] == "explained" else evw["outcome"]
            rec["withheld_best"] = evw["best"]
            rec["withheld_explained_fraction"] = evw["ranking"][0]["explained_fraction"]
            rec["withheld_reduced_chi2_cv"] = evw["ranking"][0]["reduced_chi2_cv_with_interpolation"]
        truth = sealed.open(prediction_recorded=True)
        eff = fx.get(truth["effect"])
        rec["true_effect"], rec["true_magnitude"] = truth["effect"], truth["magnitude"]
        rec["correct"] = pred == truth["effect"]
        mf, ci = fitted.get(truth["effect"], (float("nan"), [float("nan")] * 2))
        rec["fitted_magnitude"], rec["fitted_ci"] = mf, ci
        rec["magnitude_error_rel_effect"] = abs(mf - truth["magnitude"]) / abs(truth["magnitude"] - eff.nominal)
        rec["ci_covers_truth"] = bool(ci[0] <= truth["magnitude"] <= ci[1])
        if withheld_mode:
            rec["withheld_confident_wrong"] = rec["withheld_prediction"] not in ("unexplained", "no significant gap")
        out_trials.append(rec)
        if log:
            log(f"trial {t + 1}/{trials}: true {truth['effect']}={truth['magnitude']:g} -> {pred} "
                f"(EF {100 * rec['explained_fraction']:.1f} %, red.chi2 {rec['reduced_chi2_cv']:.3g}, m^ {mf:.4g})"
                + (f"; withheld -> {rec['withheld_prediction']} (best {rec['withheld_best']}, EF "
                   f"{100 * rec['withheld_explained_fraction']:.1f} %, red.chi2 {rec['withheld_reduced_chi2_cv']:.3g})"
                   if withheld_mode else "") + f"  [{time.perf_counter() - t0:.0f} s]")
    return score(out_trials, names, withheld_mode) | {
        "trials": out_trials, "n_phantoms": n_phantoms, "frames": frames, "seed": seed, "mesh": sim.mesh,
        "backend": sim.backend, "candidates": names, "settings": st.__dict__, "simulator": dict(sim.stats),
        "seconds": time.perf_counter() - t0}


def score(trials: list[dict], names: list[str], withheld_mode: bool) -> dict:
    n = len(trials)
    labels = names + ["unexplained", "no significant gap"]
    conf = {a: {b: 0 for b in labels} for a in names}
    for r in trials:
        conf[r["true_effect"]][r["prediction"] if r["prediction"] in labels else "unexplained"] += 1
    sh = [r["shrink_features"] for r in trials if r["correct"] and r["shrink_features"] is not None]
    shi = [r["shrink_inverse"] for r in trials if r["correct"] and r["shrink_inverse"] is not None]
    me = [r["magnitude_error_rel_effect"] for r in trials if r["correct"]]
    out = {"n_trials": n, "top1_accuracy": float(np.mean([r["correct"] for r in trials])) if n else float("nan"),
           "magnitude_error_rel_effect_median": float(np.median(me)) if me else float("nan"),
           "magnitude_ci_coverage": float(np.mean([r["ci_covers_truth"] for r in trials if r["correct"]])) if me else float("nan"),
           "feature_gap_shrink_median": float(np.median(sh)) if sh else float("nan"),
           "feature_gap_shrink_min": float(np.min(sh)) if sh else float("nan"),
           "dhe_error_shrink_median": float(np.median(shi)) if shi else None,
           "confusion": conf}
    if withheld_mode:
        out["withheld_confident_wrong_rate"] = float(np.mean([r["withheld_confident_wrong"] for r in trials])) if n else float("nan")
        wc = {a: {b: 0 for b in labels} for a in names}
        for r in trials:
            wc[r["true_effect"]][r["withheld_prediction"] if r["withheld_prediction"] in labels else "unexplained"] += 1
        out["withheld_confusion"] = wc
    out["goals"] = {"top1>=0.9": out["top1_accuracy"] >= 0.9,
                    "shrink>=0.7": bool(sh) and out["feature_gap_shrink_median"] >= 0.7,
                    "withheld_confident_wrong<=0.2": (not withheld_mode) or out["withheld_confident_wrong_rate"] <= 0.2,
                    "trials>=20": n >= 20}
    return out


def markdown(res: dict) -> str:
    L = ["# SYNTHETIC blind self-test of the gap diagnosis", "",
         f"{res['n_trials']} trials, backend `{res['backend']}`, mesh `{res['mesh']}`, {res['n_phantoms']} phantoms, "
         f"{res['frames']} frames, seed {res['seed']}, {res['seconds']:.0f} s "
         f"({res['simulator']['solved']} solves run, {res['simulator']['hits']} cache hits).", "",
         "| metric | value | goal |", "|---|---|---|",
         f"| top-1 accuracy | {100 * res['top1_accuracy']:.1f} % | ≥ 90 % |",
         f"| fitted magnitude error (median, relative to the effect size) | {100 * res['magnitude_error_rel_effect_median']:.1f} % | |",
         f"| magnitude 95 % CI covers the truth | {100 * res['magnitude_ci_coverage']:.0f} % | |",
         f"| feature-gap shrink on withheld phantoms (median / min) | {100 * res['feature_gap_shrink_median']:.1f} % / "
         f"{100 * res['feature_gap_shrink_min']:.1f} % | ≥ 70 % |"]
    if res.get("dhe_error_shrink_median") is not None:
        L.append(f"| (d, h, E) error shrink (median) | {100 * res['dhe_error_shrink_median']:.1f} % | |")
    if "withheld_confident_wrong_rate" in res:
        L.append(f"| true effect withheld: confident wrong attribution | {100 * res['withheld_confident_wrong_rate']:.1f} % | ≤ 20 % |")
    for title, key in (("Confusion matrix (rows: true effect; columns: answer)", "confusion"),
                       ("True effect withheld from the candidates (right answer: unexplained)", "withheld_confusion")):
        if key not in res:
            continue
        conf = res[key]
        cols = [c for c in next(iter(conf.values())).keys() if any(conf[r][c] for r in conf) or c in conf]
        L += ["", f"## {title}", "", "| true \\ answer | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
        for r, row in conf.items():
            if sum(row.values()):
                L.append(f"| {r} | " + " | ".join(str(row[c]) for c in cols) + " |")
    L += ["", "## Trials", "", "| # | true | magnitude | answer | fitted | EF | red. χ² | shrink | withheld answer |",
          "|---|---|---|---|---|---|---|---|---|"]
    for r in res["trials"]:
        shr = "" if r["shrink_features"] is None else f"{100 * r['shrink_features']:.1f} %"
        L.append(f"| {r['trial']} | {r['true_effect']} | {r['true_magnitude']:g} | {r['prediction']} | "
                 f"{r['fitted_magnitude']:.4g} | {100 * r['explained_fraction']:.1f} % | {r['reduced_chi2_cv']:.3g} | "
                 f"{shr} | "
                 f"{r.get('withheld_prediction', '')} |")
    return "\n".join(L) + "\n"
