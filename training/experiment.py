"""Hold-out and leave-one-out validation with repeats, as one batched training problem.

* **HOV** -- the test set is the calibration-phantom rows (tag ``phantom:*``,
  the paper's 9 inclusions) or, with ``test_split``, a random fraction of the
  rows.  ``repeats`` networks (independent initialisations) train on the
  remaining rows.
* **LOOCV** -- ``n`` folds, one held-out sample each; ``n x repeats``
  networks, all trained at once.

Every network gets its own ``mapminmax`` scaling fitted on its own training
fold (noise-free features; rows of an optional validation split included, as
MATLAB does), and its own feature-noise draw when ``feature_noise > 0``
(multiplicative: ``O_k (1 + feature_noise * N(0, 1))`` on every row the
network sees, training and test).

Metrics per output ``j`` and per repeat, pooled over the repeat's test
predictions ``i`` (HOV: the test rows; LOOCV: the ``n`` held-out samples):

* ``mse100`` -- paper eq. (1), ``(1/n) Σ_i (T_ij − Y_ij)² × 100`` in %, with
  ``T`` and ``Y`` in the network's ``mapminmax`` ``[-1, 1]`` target scaling;
* ``mre`` -- mean relative error ``(1/n) Σ_i |Y_ij − T_ij| / |T_ij| × 100`` in %
  (physical units);
* ``rmse`` -- root-mean-square error in physical units (mm, mm, kPa).

Across repeats we report the mean, the 2.5/97.5 % percentiles of the repeat
values (``lo``/``hi``: the 95 % interval of one training run's outcome),
the standard deviation and a Student-t 95 % confidence interval of the mean
(``ci_lo``/``ci_hi``).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from elastimap.constraints import InstanceOf, Interval, Options, Predicate, validate_params
from elastimap.dataset.phantoms import is_phantom
from elastimap.errors import UserError

from . import net as _net
from .data import FEATURES, TARGETS, Samples
from .net import Arch
from .optim import TrainResult, train_lm, train_scg
from .problem import NetObjective, mapminmax_apply, mapminmax_fit, mapminmax_reverse

ALGOS = ("lm", "scg")
VALIDATIONS = ("hov", "loocv")
METRICS = ("mse100", "mre", "rmse")
METRIC_LABEL = {"mse100": "MSE×100 (%)", "mre": "MRE (%)", "rmse": "RMSE"}


@dataclass
class TrainConfig:
    """Everything about how one network is trained (not which rows)."""

    hidden: tuple = ((25, "tansig"), (10, "tansig"))
    epochs: int = 100
    feature_noise: float = 0.0
    val_fraction: float = 0.0  # > 0: random validation rows per network, early stop after 6 failures
    max_fail: int = 6
    device: str | None = None
    dtype: torch.dtype = torch.float64
    mem_bytes: int | None = None  # memory budget for one chunk of networks
    progress: bool = True
    workers: int = 1  # CPU processes training chunks of networks in parallel (0 = one per core)
    n_in: int = len(FEATURES)  # network inputs: the three features, or an image model's K inputs

    #: What each setting must be (the command line shows the names as its flags).
    _parameter_constraints = {
        "hidden": [
            Predicate(
                lambda h: len(h) >= 1 and all(int(n) >= 1 and a in _net.ACTIVATIONS for n, a in h),
                "a non-empty tuple of (size >= 1, transfer function) layers",
            )
        ],
        "epochs": [Interval(int, 1, None)],  # 0 epochs would save the untrained initial weights
        "feature_noise": [Interval(float, 0, 1)],
        "val_fraction": [Interval(float, 0, 1, closed="left")],
        "max_fail": [Interval(int, 1, None)],
        "device": [
            None,
            InstanceOf(torch.device, "a torch.device"),
            Predicate(
                lambda d: d in ("cpu", "cuda") or (d.startswith("cuda:") and d[5:].isdigit()), "cpu, cuda or cuda:N"
            ),
        ],
        "dtype": [Options((torch.float32, torch.float64))],
        "mem_bytes": [None, Interval(int, 1, None)],
        "workers": [Interval(int, 0, 256)],
        "n_in": [Interval(int, 1, None)],
    }

    def validate(self) -> TrainConfig:
        """Raise :class:`UserError` naming the first setting that breaks its rule; return self."""
        validate_params(vars(self), self._parameter_constraints)
        return self

    @property
    def arch(self) -> Arch:
        return Arch(self.n_in, tuple(self.hidden), len(TARGETS))

    def resolved_device(self) -> torch.device:
        if self.device:
            return torch.device(self.device)
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")

    def n_workers(self, n_chunks: int) -> int:
        """Processes actually used: never more than the chunks, always 1 on a GPU."""
        if self.resolved_device().type != "cpu" or n_chunks < 2:
            return 1
        w = self.workers if self.workers > 0 else (os.cpu_count() or 1)
        return max(1, min(w, n_chunks))

    def budget(self) -> int:
        if self.mem_bytes:
            return int(self.mem_bytes)
        return (8 << 30) if self.resolved_device().type == "cuda" else (1 << 30)


def check_trainable(n_train: int, arch: Arch, what: str = "training fold") -> None:
    """Refuse folds that cannot determine the network (``n_train * n_out < n_params``)."""
    if n_train < 2:
        raise UserError("data", f"the {what} has {n_train} sample(s); need at least 2")
    if n_train * arch.n_out < arch.n_params:
        need = math.ceil(arch.n_params / arch.n_out)
        raise UserError(
            "data",
            f"too few samples for the network: the {what} has {n_train} samples "
            f"({n_train * arch.n_out} target values) but {arch.describe()} has "
            f"{arch.n_params} weights; need >= {need} samples or a smaller --hidden",
        )


@dataclass
class Batch:
    """``B`` networks over the same ``n`` rows: masks, scaling and the objective."""

    obj: NetObjective
    theta0: torch.Tensor
    x_lo: np.ndarray  # (B, 3)
    x_hi: np.ndarray
    t_lo: np.ndarray
    t_hi: np.ndarray
    X_phys: np.ndarray  # (B, n, 3) features as the networks saw them (noise included) or (1, n, 3)
    train: np.ndarray  # (B, n) bool (training rows, excluding validation rows)
    test: np.ndarray  # (B, n) bool


def make_batch(
    X: np.ndarray,
    T: np.ndarray,
    fit_rows: np.ndarray,
    test_rows: np.ndarray | None,
    cfg: TrainConfig,
    rng: np.random.Generator,
    gen: torch.Generator,
    names: tuple[str, ...] = FEATURES,
) -> Batch:
    """Build the batched problem.  ``fit_rows``/``test_rows``: ``(B, n)`` bool; ``names``: the
    columns of ``X`` (for the error naming a constant one)."""
    arch = cfg.arch
    dev = cfg.resolved_device()
    B, n = fit_rows.shape
    x_lo, x_hi = mapminmax_fit(np.broadcast_to(X, (B, n, X.shape[1])), fit_rows)
    t_lo, t_hi = mapminmax_fit(np.broadcast_to(T, (B, n, T.shape[1])), fit_rows)
    for lo, hi, cols in ((x_lo, x_hi, names), (t_lo, t_hi, TARGETS)):
        const = ~(hi > lo)
        if const.any():
            j = int(np.nonzero(const.any(axis=0))[0][0])
            raise UserError("data", f"column {cols[j]} is constant over a training fold; cannot scale it")
    if cfg.feature_noise > 0:
        Xp = X[None] * (1.0 + cfg.feature_noise * rng.standard_normal((B, n, X.shape[1])))
    else:
        Xp = X[None]
    train = fit_rows.copy()
    val = None
    if cfg.val_fraction > 0:
        val = np.zeros_like(fit_rows)
        for b in range(B):
            rows = np.nonzero(fit_rows[b])[0]
            k = int(round(cfg.val_fraction * rows.size))
            if k < 1 or rows.size - k < 2:
                raise UserError("val_fraction", f"{cfg.val_fraction:g} leaves no usable validation or training rows")
            pick = rng.choice(rows, size=k, replace=False)
            val[b, pick] = True
        train &= ~val
    check_trainable(int(train.sum(1).min()), arch)
    tt = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=cfg.dtype, device=dev)  # noqa: E731
    Xs = mapminmax_apply(Xp, x_lo, x_hi)
    Ts = mapminmax_apply(T[None], t_lo, t_hi)
    obj = NetObjective(
        arch, tt(Xs), tt(Ts), tt(train), None if val is None else tt(val), None if test_rows is None else tt(test_rows)
    )
    theta0 = _net.init_nguyen_widrow(arch, B, gen, dtype=cfg.dtype, device=dev)
    return Batch(
        obj, theta0, x_lo, x_hi, t_lo, t_hi, Xp, train, np.zeros_like(train) if test_rows is None else test_rows
    )


def chunk_size(algo: str, cfg: TrainConfig, n: int) -> int:
    """How many networks one optimiser call handles within the memory budget."""
    P = cfg.arch.n_params
    el = torch.finfo(cfg.dtype).bits // 8
    if algo == "lm":
        per = 4 * P * P * el + 8 * n * 8 * el
        if cfg.resolved_device().type == "cpu":
            # keep each chunk's (nets, P, P) JᵀJ under glibc's largest mmap threshold (32 MiB) so
            # it reuses freed memory every epoch instead of faulting in fresh pages
            return max(1, min(int(cfg.budget() // per), (24 << 20) // (P * P * el)))
    else:
        width = sum(s for s, _ in cfg.hidden) + 3 * len(TARGETS)
        per = 12 * n * width * el + 8 * P * el
    return max(1, int(cfg.budget() // per))


def _worker_init(threads: int) -> None:
    from .perf import set_threads, tune_malloc

    tune_malloc()
    set_threads(threads)


def _train_chunk(algo: str, obj: NetObjective, theta0: torch.Tensor, epochs: int, max_fail: int) -> TrainResult:
    fn = train_lm if algo == "lm" else train_scg
    return fn(obj, theta0, epochs=epochs, max_fail=max_fail)


def train_batch(algo: str, obj: NetObjective, theta0: torch.Tensor, cfg: TrainConfig, desc: str = "") -> TrainResult:
    """Run LM or SCG on all networks of ``obj``, a memory-bounded chunk at a time.

    With ``cfg.workers != 1`` on the CPU the chunks are shared out to that many
    spawned processes (one torch thread each); every chunk is computed exactly
    as in the serial loop, so the results do not depend on the number of workers.
    """
    if algo not in ALGOS:
        raise UserError("algo", f"unknown algorithm {algo!r}; use one of {', '.join(ALGOS)}")
    B = obj.B
    n = obj.X.shape[1]
    step = chunk_size(algo, cfg, n)
    chunks = [torch.arange(s, min(B, s + step), device=theta0.device) for s in range(0, B, step)]
    workers = cfg.n_workers(len(chunks))
    bar = None
    if cfg.progress:
        from tqdm import tqdm

        bar = tqdm(
            total=len(chunks) * (cfg.epochs + 1),
            desc=desc or algo,
            unit="epoch",
            leave=False,
            postfix={"nets": B, "workers": workers},
        )
    results: list = [None] * len(chunks)
    if workers > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(
            workers, mp_context=mp.get_context("spawn"), initializer=_worker_init, initargs=(1,)
        ) as pool:
            futs = {
                pool.submit(_train_chunk, algo, obj.subset(idx), theta0[idx], cfg.epochs, cfg.max_fail): i
                for i, idx in enumerate(chunks)
            }
            for f in as_completed(futs):
                results[futs[f]] = f.result()
                if bar is not None:
                    bar.update(cfg.epochs + 1)
    else:
        for i, idx in enumerate(chunks):
            last = [-1]

            def prog(epoch, last=last):
                if bar is not None:
                    bar.update(epoch - last[0])
                    last[0] = epoch

            fn = train_lm if algo == "lm" else train_scg
            r = fn(obj.subset(idx), theta0[idx], epochs=cfg.epochs, progress=prog, max_fail=cfg.max_fail)
            if bar is not None:
                bar.update(cfg.epochs + 1 - (last[0] + 1))
            results[i] = r
    if bar is not None:
        bar.close()
    return TrainResult(
        theta=torch.cat([r.theta for r in results]),
        epochs=torch.cat([r.epochs for r in results]),
        stop=[s for r in results for s in r.stop],
        history={k: torch.cat([r.history[k] for r in results]) for k in results[0].history},
        workers=workers,
    )


def predict_scaled(theta: torch.Tensor, Xs: torch.Tensor, arch: Arch, mem_bytes: int = 256 << 20) -> np.ndarray:
    """Outputs in the scaled target space for ``(B, n, 3)`` inputs, chunked; numpy ``(B, n, 3)``."""
    B, n, _ = Xs.shape
    width = sum(s for s, _ in arch.hidden) + arch.n_out
    step = max(1, mem_bytes // (n * width * 8 * 2))
    out = []
    with torch.no_grad():
        for s in range(0, B, step):
            out.append(_net.forward(theta[s : s + step], Xs[s : s + step], arch).cpu().numpy())
    return np.concatenate(out).astype(np.float64)


def _t975(dof: int) -> float:
    from scipy.stats import t

    return float(t.ppf(0.975, dof)) if dof > 0 else float("nan")


def summarize(values: np.ndarray) -> dict:
    """Mean, std, 2.5/97.5 % percentiles and t-interval of the mean of per-repeat values."""
    v = np.asarray(values, dtype=np.float64)
    R = v.size
    mean = float(v.mean())
    std = float(v.std(ddof=1)) if R > 1 else 0.0
    half = _t975(R - 1) * std / math.sqrt(R) if R > 1 else float("nan")
    return {
        "mean": mean,
        "std": std,
        "lo": float(np.percentile(v, 2.5)),
        "hi": float(np.percentile(v, 97.5)),
        "ci_lo": mean - half,
        "ci_hi": mean + half,
    }


@dataclass
class ValidationResult:
    algo: str
    validate: str
    repeats: int
    row: dict  # one table row (flat)
    per_repeat: dict  # metric -> (R, 3)
    curves: dict  # name -> (B, epochs+1) numpy, NaN after stop
    stops: dict  # reason -> count
    wall_s: float
    extra: dict = field(default_factory=dict)


#: What the arguments of one validation run must be (:func:`run_validation`; the CLI checks them first).
RUN_CONSTRAINTS = {
    "algo": [Options(ALGOS)],
    "validate": [Options(VALIDATIONS)],
    "repeats": [Interval(int, 1, None)],
    "seed": [Interval(int, 0, None)],
    "test_split": [None, Interval(float, 0, 1, closed="neither")],
}


def split_rows(samples: Samples, validate: str, test_split: float | None, rng: np.random.Generator):
    """HOV test rows (bool ``(n,)``) and a note saying how they were chosen."""
    n = samples.n
    if validate != "hov":
        return None, ""
    if test_split is not None:
        if not 0 < test_split < 1:
            raise UserError("test_split", f"must be in (0, 1) (got {test_split:g})")
        k = max(1, int(round(test_split * n)))
        test = np.zeros(n, bool)
        test[rng.choice(n, size=k, replace=False)] = True
        return test, f"random {test_split:g} of the rows ({k})"
    test = is_phantom(samples.df["tag"])
    if test.any():
        return test, f"{int(test.sum())} calibration-phantom rows"
    k = max(1, int(round(0.1 * n)))
    test = np.zeros(n, bool)
    test[rng.choice(n, size=k, replace=False)] = True
    return test, f"no phantom rows: random 0.1 of the rows ({k}); set --test-split to choose"


def rng_for(seed: int, validate: str):
    """Random streams for one validation scheme (shared by the algorithms: paired comparisons)."""
    ss = np.random.SeedSequence([int(seed), VALIDATIONS.index(validate) if validate in VALIDATIONS else 9])
    rng = np.random.default_rng(ss)
    gen = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))
    return rng, gen


@dataclass
class Folds:
    """Which rows each of the ``B = repeats x folds`` networks of one validation run tests on."""

    validate: str
    repeats: int
    folds: int  # 1 (HOV) or n (LOOCV)
    test: np.ndarray  # (B, n) bool
    held_out: np.ndarray  # (n,) bool: the rows some network tests on (HOV: the test set; LOOCV: all)
    note: str  # how the test rows were chosen
    rng: np.random.Generator  # the run's random streams (after choosing the test rows)
    gen: torch.Generator


def plan_folds(samples: Samples, validate: str, repeats: int, seed: int = 0, test_split: float | None = None) -> Folds:
    """The test rows of HOV (``split_rows``) or LOOCV for ``repeats`` repeats, and the random
    streams the training that follows draws from (the same for every algorithm: paired comparisons)."""
    validate_params(dict(validate=validate, repeats=repeats, seed=seed, test_split=test_split), RUN_CONSTRAINTS)
    n = samples.n
    rng, gen = rng_for(seed, validate)
    test1, note = split_rows(samples, validate, test_split, rng)
    if validate == "hov":
        if test1.all():
            raise UserError("data", "every row is a test (phantom) row; nothing left to train on")
        return Folds(validate, repeats, 1, np.broadcast_to(test1, (repeats, n)).copy(), test1, note, rng, gen)
    if n < 3:
        raise UserError("data", f"LOOCV needs at least 3 samples (got {n})")
    test = np.tile(np.eye(n, dtype=bool), (repeats, 1))
    return Folds(validate, repeats, n, test, np.ones(n, bool), f"{n} folds", rng, gen)


def run_validation(
    samples: Samples,
    algo: str,
    validate: str,
    repeats: int,
    cfg: TrainConfig,
    seed: int = 0,
    test_split: float | None = None,
) -> ValidationResult:
    """Train and score the feature MLP (O1, O2, O3 -> d, h, E) under ``validate`` with ``repeats``
    random initialisations (:func:`validate_inputs` on the sample table's features)."""
    validate_params(dict(algo=algo), {"algo": RUN_CONSTRAINTS["algo"]})
    folds = plan_folds(samples, validate, repeats, seed, test_split)
    X = samples.df[list(FEATURES)].to_numpy(np.float64)
    T = samples.df[list(TARGETS)].to_numpy(np.float64)
    return validate_inputs(X, T, folds, algo, cfg)


def validate_inputs(
    X: np.ndarray,
    T: np.ndarray,
    folds: Folds,
    algo: str,
    cfg: TrainConfig,
    *,
    names: tuple[str, ...] = FEATURES,
    label: str | None = None,
    row_extra: dict | None = None,
    X_repeats: np.ndarray | None = None,
    train_targets=None,
    to_physical=None,
    X_eval: np.ndarray | None = None,
) -> ValidationResult:
    """Train and score ``algo`` on any input matrix ``X`` ``(n, c)`` (columns ``names``) against the
    targets ``T`` ``(n, 3)`` (d mm, h mm, E kPa) over ``folds`` (:func:`plan_folds`).

    ``X_repeats`` ``(repeats, n, c)``: the inputs each repeat's networks see instead of ``X`` (e.g.
    one noise draw per repeat, shared by its LOOCV folds); the scaling is fitted on the noise-free
    ``X`` either way.  ``train_targets``/``to_physical``: a transform of the targets the networks
    learn (e.g. ln E) and its inverse; the metrics are computed on ``T`` itself, MSE x 100 on the
    linear [-1, 1] mapminmax scaling of ``T`` over each training fold, so rows stay comparable.
    ``X_eval`` ``(n, c)``: one more input matrix whose held-out rows every network predicts
    (``extra['pred_eval']``, as ``extra['pred']``).  ``label``: the table's ``algo`` (default
    ``algo``); ``row_extra``: more columns, after ``feature_noise``.

    ``extra['pred']``: the held-out predictions ``(repeats, n, 3)`` (physical units; NaN where a row
    was no network's test row in that repeat); ``extra['test']``: ``folds.held_out``."""
    validate_params(dict(algo=algo), {"algo": RUN_CONSTRAINTS["algo"]})
    X = np.asarray(X, dtype=np.float64)
    T = np.asarray(T, dtype=np.float64)
    cfg = dataclasses.replace(cfg, n_in=X.shape[1]).validate()
    test, R, nf, n = folds.test, folds.repeats, folds.folds, X.shape[0]
    fit = ~test
    check_trainable(int(fit[0].sum()) - int(round(cfg.val_fraction * fit[0].sum())), cfg.arch)
    Tt = T if train_targets is None else train_targets(T)
    t0 = time.perf_counter()
    batch = make_batch(X, Tt, fit, test, cfg, folds.rng, folds.gen, names)
    obj = _with_inputs(batch, cfg, None if X_repeats is None else np.repeat(np.asarray(X_repeats), nf, axis=0))
    res = train_batch(algo, obj, batch.theta0, cfg, desc=f"{label or algo} {folds.validate}")
    wall = time.perf_counter() - t0

    Ys, Yp, Ts, Tp = _scored_outputs(res.theta, obj, batch, cfg, T, to_physical)
    shp = (R, nf, n)
    per, cnt, train_mse = _metrics(Ts, Ys, Yp, Tp, test, batch.train, shp)
    extra = {"pred": _held_out(Yp, test, shp), "test": folds.held_out}
    if X_eval is not None:
        Xe = mapminmax_apply(
            np.broadcast_to(np.asarray(X_eval, np.float64), (test.shape[0], *np.shape(X_eval))), batch.x_lo, batch.x_hi
        )
        Xe_t = torch.as_tensor(Xe, dtype=obj.X.dtype, device=obj.X.device)
        extra["pred_eval"] = _held_out(_physical_outputs(res.theta, Xe_t, batch, cfg, to_physical)[1], test, shp)
    row = _validation_row(label or algo, folds, n, int(cnt[0, 0]), batch, cfg, row_extra, res, wall)
    stops = _summarise_into(row, per, train_mse, res.stop)
    curves = {k: v.numpy() for k, v in res.history.items() if k in ("train", "test", "val")}
    return ValidationResult(label or algo, folds.validate, R, row, per, curves, stops, wall, extra)


def _physical_outputs(theta: torch.Tensor, Xs_t: torch.Tensor, batch: Batch, cfg: TrainConfig, to_physical):
    """The networks' outputs on the scaled inputs ``Xs_t``: (scaled Ys, physical Yp), Yp the
    mapminmax inverse of Ys over each network's training targets, then ``to_physical`` (if any;
    d mm, h mm, E kPa)."""
    Ys = predict_scaled(theta, Xs_t, cfg.arch)
    Yp = mapminmax_reverse(Ys, batch.t_lo, batch.t_hi)
    return Ys, (Yp if to_physical is None else to_physical(Yp))


def _scored_outputs(theta: torch.Tensor, obj: NetObjective, batch: Batch, cfg: TrainConfig, T, to_physical):
    """(Ys, Yp, Ts, Tp) the metrics compare: the outputs on the batch's own inputs, scaled and
    physical (:func:`_physical_outputs`), and the targets, scaled and physical (T broadcast per
    network).  With ``to_physical`` both are scored on the linear [-1, 1] mapminmax scaling of
    (d, h, E) over each training fold instead of the transformed one the networks learnt."""
    Ys, Yp = _physical_outputs(theta, obj.X, batch, cfg, to_physical)
    Ts = obj.T.cpu().numpy()
    Tp = np.broadcast_to(T, Yp.shape)
    if to_physical is not None:  # score on the linear scaling of (d, h, E) over each training fold
        lo, hi = mapminmax_fit(Tp, batch.train)
        Ys, Ts = mapminmax_apply(Yp, lo, hi), mapminmax_apply(Tp, lo, hi)
    return Ys, Yp, Ts, Tp


def _held_out(Y: np.ndarray, test: np.ndarray, shp: tuple) -> np.ndarray:
    """Each repeat's held-out predictions (R, n, 3) from the networks' outputs ``Y`` (B, n, 3),
    B = R x folds (``shp`` = (R, folds, n)): each row's from the network it was a test row of,
    NaN where it was none's in that repeat."""
    tm = test.reshape(shp)[..., None]
    tested = test.reshape(shp).any(axis=1)  # (R, n)
    pred = np.where(tm, Y.reshape(*shp, 3), 0.0).sum(axis=1)  # (R, n, 3)
    pred[~tested] = np.nan
    return pred


def _validation_row(
    label: str, folds: Folds, n: int, n_test: int, batch: Batch, cfg: TrainConfig, row_extra, res, wall: float
) -> dict:
    """The run's table row before its metrics: what was trained, on what, how long it took (s)."""
    B = folds.test.shape[0]
    return {
        "algo": label,
        "validate": folds.validate,
        "repeats": folds.repeats,
        "n_samples": n,
        "n_train": int(batch.train[0].sum()),
        "n_test_per_repeat": n_test,
        "trainings": B,
        "hidden": ",".join(f"{s}" if a == "tansig" else f"{s}:{a}" for s, a in cfg.hidden),
        "epochs": cfg.epochs,
        "feature_noise": cfg.feature_noise,
        **(row_extra or {}),
        "val_fraction": cfg.val_fraction,
        "test_set": folds.note,
        "wall_s": round(wall, 3),
        "trainings_per_s": round(B / wall, 3),
        "mean_epochs_run": float(res.epochs.double().mean()),
        "dtype": str(cfg.dtype).replace("torch.", ""),
        "workers": res.workers,
    }


def _with_inputs(batch: Batch, cfg: TrainConfig, X_b: np.ndarray | None) -> NetObjective:
    """The batch's objective with its inputs replaced by ``X_b`` ``(B, n, c)`` (scaled as the
    batch's, fitted on the noise-free inputs); ``X_b`` None: the batch's own."""
    obj = batch.obj
    if X_b is None:
        return obj
    Xs = mapminmax_apply(np.asarray(X_b, np.float64), batch.x_lo, batch.x_hi)
    Xs = torch.as_tensor(Xs, dtype=obj.X.dtype, device=obj.X.device)
    return NetObjective(cfg.arch, Xs, obj.T, obj.w, obj.w_val, obj.w_test)


def _metrics(Ts, Ys, Yp, Tp, test: np.ndarray, train: np.ndarray, shp: tuple):
    """Per repeat over its test predictions (module docstring): ``{metric: (R, 3)}``, the test
    counts ``(R, 1)`` and the training MSE x 100 ``(R, 3)``; ``shp`` = (repeats, folds, n)."""
    tm = test.reshape(shp)[..., None]
    cnt = tm.sum(axis=(1, 2))
    per = {
        "mse100": 100.0 * (((Ts - Ys) ** 2).reshape(*shp, 3) * tm).sum(axis=(1, 2)) / cnt,
        "mre": 100.0 * ((np.abs(Yp - Tp) / np.abs(Tp)).reshape(*shp, 3) * tm).sum(axis=(1, 2)) / cnt,
        "rmse": np.sqrt((((Yp - Tp) ** 2).reshape(*shp, 3) * tm).sum(axis=(1, 2)) / cnt),
    }
    trm = train.reshape(shp)[..., None]
    train_mse = 100.0 * ((((Ts - Ys) ** 2).reshape(*shp, 3) * trm).sum(axis=2) / trm.sum(axis=2)).mean(axis=1)
    return per, cnt, train_mse


def _summarise_into(row: dict, per: dict, train_mse: np.ndarray, stop: list[str]) -> dict[str, int]:
    """Add each metric's summary over repeats, the mean training MSE and the stop reasons to ``row``."""
    for m in METRICS:
        for j, tname in enumerate(TARGETS):
            for k, v in summarize(per[m][:, j]).items():
                row[f"{m}_{tname}_{k}"] = v
    for j, tname in enumerate(TARGETS):
        row[f"train_mse100_{tname}_mean"] = float(train_mse[:, j].mean())
    stops: dict[str, int] = {}
    for s in stop:
        stops[s] = stops.get(s, 0) + 1
    row["stops"] = ";".join(f"{k}:{v}" for k, v in sorted(stops.items()))
    return stops


def train_final(
    X: np.ndarray,
    T: np.ndarray,
    algo: str,
    repeats: int,
    cfg: TrainConfig,
    seed: int = 0,
    *,
    names: tuple[str, ...] = FEATURES,
    X_repeats: np.ndarray | None = None,
) -> tuple[TrainResult, Batch]:
    """Train ``repeats`` networks (independent initialisations) on every row of ``X`` ``(n, c)``
    -> targets ``T`` (as the networks learn them); ``X_repeats`` as in :func:`validate_inputs`.
    Returns the optimiser's result and the batch (its scaling) for building the saved ensemble."""
    X = np.asarray(X, dtype=np.float64)
    cfg = dataclasses.replace(cfg, n_in=X.shape[1]).validate()
    rng, gen = rng_for(seed, "final")
    batch = make_batch(X, np.asarray(T, np.float64), np.ones((repeats, X.shape[0]), bool), None, cfg, rng, gen, names)
    obj = _with_inputs(batch, cfg, X_repeats)
    return train_batch(algo, obj, batch.theta0, cfg, desc=f"{algo} final"), batch
