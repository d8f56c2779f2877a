"""Detection study (paper section 5.3) on SYNTHETIC scans.

The paper scanned a MammaCare phantom with eight inclusions and the same
phantom without inclusions (eight clean scans): Tp = 6, Fn = 2 (sensitivity
75 %), Tn = 7, Fp = 1 (specificity 87.5 %), ROC AUC 0.835.

Here every scan is one synthetic camera frame of a press:

* positives: the eight inclusions of :data:`DETECTION_INCLUSIONS` (FEM raw
  deflection with the inclusion); negatives: the same presses with no
  inclusion (FEM ``image_raw - image``);
* nuisances per scan (all seeded): press depth jitter ``press_jitter``
  (relative sd; the tied interface is linear so the deflection scales with
  the indentation), LED power drift ``led_jitter`` (relative sd per LED),
  tissue/skin heterogeneity ``clutter_mm`` (a Gaussian random field of
  correlation length ``clutter_corr_mm`` added to the deflection), and the
  camera noise of :class:`elastimap.camera.optics.SensorModel` times ``noise_scale``;
* a reference frame: a clean press at the nominal depth and LED powers,
  averaged over ``ref_frames`` frames (acquired once, like a background).

Detection score (no knowledge of the inclusion): fit the scan as
``alpha * reference + beta`` over the footprint (absorbs press and overall
brightness changes), Gaussian-smooth the residual (``score_sigma_px``), and
take its maximum inside the footprint minus a ``border_mm`` margin (the
flat-punch edge peaks live there), in fraction of full scale.

Threshold: fixed *before* looking at the test scans, as the
``threshold_quantile`` (95 %) quantile of the scores of ``n_threshold``
independent clean scans.  ROC AUC is the Mann-Whitney statistic; its 95 %
interval comes from a stratified bootstrap over scans.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from elastimap.errors import UserError

from .optics import SensorModel

PAPER = {"sensitivity": 0.75, "specificity": 0.875, "auc": 0.835, "n_pos": 8, "n_neg": 8}

# Eight inclusions in the spirit of the MammaCare training phantom: 4-10 mm, shallow to deep,
# soft-ish to hard (d mm, centre depth h mm, E kPa); background 5 kPa, 20 mm.  This project's choice.
DETECTION_INCLUSIONS = (
    (4.0, 5.0, 60.0),
    (5.0, 8.0, 40.0),
    (6.0, 10.0, 60.0),
    (6.0, 6.0, 30.0),
    (7.0, 12.0, 80.0),
    (8.0, 14.0, 60.0),
    (9.0, 9.0, 25.0),
    (10.0, 13.0, 40.0),
)


@dataclass(frozen=True)
class DetectionSettings:
    press_jitter: float = 0.05
    led_jitter: float = 0.02
    clutter_mm: float = 0.002
    clutter_corr_mm: float = 2.0
    ref_frames: int = 30
    score_sigma_px: float = 2.0
    border_mm: float = 3.0
    n_threshold: int = 40
    threshold_quantile: float = 0.95
    repeats: int = 1  # scans per inclusion (and clean scans per inclusion)
    n_boot: int = 2000
    seed: int = 0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _clutter(shape, pixel: float, s: DetectionSettings, rng) -> np.ndarray:
    if s.clutter_mm <= 0:
        return np.zeros(shape)
    f = ndimage.gaussian_filter(rng.normal(size=shape), s.clutter_corr_mm / pixel, mode="wrap")
    return f * (s.clutter_mm / f.std())


def _scan(model: SensorModel, raw: np.ndarray, pixel: float, s: DetectionSettings, rng) -> np.ndarray:
    scale = 1.0 + s.press_jitter * rng.normal()
    power = tuple(p * (1.0 + s.led_jitter * rng.normal()) for p in model.led_power)
    m = model.replace(led_power=power)
    w = scale * raw + _clutter(raw.shape, pixel, s, rng)
    return m.render(w, pixel, 1, rng)[0].astype(float)


def detection_score(
    scan: np.ndarray, reference: np.ndarray, model: SensorModel, s: DetectionSettings | None = None
) -> float:
    """Score of one frame against the clean reference frame (both in DN)."""
    s = s or DetectionSettings()
    r0, c0, n = model.window
    a = scan[r0 : r0 + n, c0 : c0 + n] / model.full_scale
    b = reference[r0 : r0 + n, c0 : c0 + n] / model.full_scale
    A = np.column_stack([b.ravel(), np.ones(b.size)])
    coef, *_ = np.linalg.lstsq(A, a.ravel(), rcond=None)
    res = a - (coef[0] * b + coef[1])
    if s.score_sigma_px > 0:
        res = ndimage.gaussian_filter(res, s.score_sigma_px, mode="reflect")
    k = int(round(s.border_mm / model.pixel_mm))
    inner = res[k : n - k, k : n - k] if n - 2 * k > 0 else res
    return float(inner.max())


def auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """Area under the ROC curve (Mann-Whitney, ties count 1/2)."""
    pos, neg = np.asarray(pos, float), np.asarray(neg, float)
    if pos.size == 0 or neg.size == 0:
        raise UserError("scores", "need at least one positive and one negative scan")
    gt = (pos[:, None] > neg[None, :]).sum()
    eq = (pos[:, None] == neg[None, :]).sum()
    return float((gt + 0.5 * eq) / (pos.size * neg.size))


def roc_curve(pos: np.ndarray, neg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(false-positive rate, true-positive rate, thresholds), from (0,0) to (1,1)."""
    thr = np.unique(np.concatenate([pos, neg]))[::-1]
    fpr = [0.0] + [float(np.mean(neg >= t)) for t in thr]
    tpr = [0.0] + [float(np.mean(pos >= t)) for t in thr]
    return np.array(fpr), np.array(tpr), np.concatenate([[np.inf], thr])


def bootstrap_auc(pos, neg, n_boot: int = 2000, seed: int = 0, level: float = 0.95) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    pos, neg = np.asarray(pos, float), np.asarray(neg, float)
    vals = np.empty(n_boot)
    for i in range(n_boot):
        vals[i] = auc(rng.choice(pos, pos.size), rng.choice(neg, neg.size))
    q = (1 - level) / 2
    return float(np.quantile(vals, q)), float(np.quantile(vals, 1 - q))


def run_detection(
    fem_results: list,
    model: SensorModel | None = None,
    settings: DetectionSettings | None = None,
    inclusions=DETECTION_INCLUSIONS,
) -> dict:
    """The detection study from one FEM result per inclusion (``image``, ``image_raw``, ``pixel``)."""
    model = (model or SensorModel()).validate()
    s = settings or DetectionSettings()
    if len(fem_results) != len(inclusions):
        raise UserError("inclusions", f"{len(fem_results)} FEM results for {len(inclusions)} inclusions")
    rng = np.random.default_rng(s.seed)
    pixel = fem_results[0].pixel
    raws = [np.asarray(r.image_raw, float) for r in fem_results]
    bgs = [np.asarray(r.image_raw, float) - np.asarray(r.image, float) for r in fem_results]
    bg_mean = np.mean(bgs, axis=0)
    reference = model.render(bg_mean, pixel, s.ref_frames, rng).astype(float).mean(axis=0)
    thr_scores = [
        detection_score(_scan(model, bgs[i % len(bgs)], pixel, s, rng), reference, model, s)
        for i in range(s.n_threshold)
    ]
    threshold = float(np.quantile(thr_scores, s.threshold_quantile))
    pos, neg, pos_id = [], [], []
    for _ in range(s.repeats):
        for i, raw in enumerate(raws):
            pos.append(detection_score(_scan(model, raw, pixel, s, rng), reference, model, s))
            pos_id.append(i)
        for bg in bgs:
            neg.append(detection_score(_scan(model, bg, pixel, s, rng), reference, model, s))
    pos, neg = np.array(pos), np.array(neg)
    tp = int(np.sum(pos > threshold))
    tn = int(np.sum(neg <= threshold))
    a = auc(pos, neg)
    lo, hi = bootstrap_auc(pos, neg, s.n_boot, s.seed + 1)
    fpr, tpr, _ = roc_curve(pos, neg)
    return {
        "synthetic": True,
        "n_pos": int(pos.size),
        "n_neg": int(neg.size),
        "tp": tp,
        "fn": int(pos.size - tp),
        "tn": tn,
        "fp": int(neg.size - tn),
        "sensitivity": tp / pos.size,
        "specificity": tn / neg.size,
        "threshold": threshold,
        "threshold_rule": f"{s.threshold_quantile:g} quantile of {s.n_threshold} independent clean scans",
        "auc": a,
        "auc_ci95": [lo, hi],
        "scores_pos": pos.tolist(),
        "scores_neg": neg.tolist(),
        "pos_inclusion": [list(inclusions[i]) for i in pos_id],
        "roc_fpr": fpr.tolist(),
        "roc_tpr": tpr.tolist(),
        "noise_scale": model.noise_scale,
        "settings": s.to_dict(),
        "sensor": model.to_dict(),
        "paper": PAPER,
    }


def plot_roc(result: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 5))
    ax.plot(
        result["roc_fpr"],
        result["roc_tpr"],
        "C0-o",
        ms=3,
        drawstyle="steps-post",
        label=f"synthetic: AUC {result['auc']:.3f} [{result['auc_ci95'][0]:.3f}, {result['auc_ci95'][1]:.3f}]",
    )
    ax.plot(
        [1 - result["specificity"]],
        [result["sensitivity"]],
        "C0s",
        ms=8,
        label=f"threshold: sens {100 * result['sensitivity']:.1f} %, spec {100 * result['specificity']:.1f} %",
    )
    ax.plot(
        [1 - PAPER["specificity"]],
        [PAPER["sensitivity"]],
        "C3*",
        ms=12,
        label="paper: sens 75 %, spec 87.5 %, AUC 0.835",
    )
    ax.plot([0, 1], [0, 1], "k:", lw=0.8)
    ax.set_xlabel("1 - specificity (false-positive rate)")
    ax.set_ylabel("sensitivity (true-positive rate)")
    ax.set_title(
        f"SYNTHETIC detection ROC ({result['n_pos']}+{result['n_neg']} scans, noise x{result['noise_scale']:g})",
        fontsize=10,
    )
    ax.legend(fontsize=7, loc="lower right")
    ax.set_xlim(-0.02, 1.02)
    ax.set_ylim(-0.02, 1.02)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
