"""One sample as one job: sample dict -> SolveParams -> solve -> one landed row (or the samples
of one geometry as one job: :func:`run_group`).

The solver is passed in explicitly: ``solver=None`` is the forward model
(:func:`elastimap.solver.solve`, warmed up by :func:`elastimap.solver.warmup`); tests pass the
SYNTHETIC stand-in (:class:`elastimap.solver.synthetic.SyntheticSolver`, which can also crash,
hang or fail on purpose).  A solver is any callable ``solve(SolveParams) -> SolveResult`` that
pickles by module path (a module-level function or an instance of a module-level class): the
driver hands it to the dask workers as a task argument.  Its ``solver_name`` attribute labels
the rows (``solver`` column; ``fem`` for the forward model).

:func:`run_sample` (:func:`run_group`) runs in a dask worker.  It lands its row itself
(atomically, see :mod:`elastimap.dataset.io`) before returning, so a result exists on disk as
soon as its solve ends and nothing is held only in memory; it returns a small summary (no
image) to the driver.  Every row carries the solve key (:mod:`elastimap.dataset.store`), so a
sweep folder is also a solve store.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import resource
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from elastimap.dataset import io, store
from elastimap.errors import UserError
from elastimap.provenance import code_version, host
from elastimap.solver.params import SolveParams

SOLVERS = ("fem", "synthetic[:KEY=VALUE,...]")


def resolve_solver(spec: str | None) -> Callable | None:
    """``None``/``'fem'``: the forward model (returned as None); ``'synthetic[:...]'``: the SYNTHETIC
    stand-in for tests and dry runs (see :meth:`elastimap.solver.synthetic.SyntheticSolver.from_spec`)."""
    if spec is None or spec == "fem":
        return None
    if spec.partition(":")[0] == "synthetic":
        from elastimap.solver.synthetic import SyntheticSolver

        return SyntheticSolver.from_spec(spec)
    raise UserError("solver", f"must be one of {', '.join(SOLVERS)} (got {spec!r})")


def solve_with(solver: Callable | None, p: SolveParams):
    """``solver(p)``, the forward model when ``solver`` is None."""
    if solver is None:
        from elastimap.solver import solve as solver
    return solver(p)


def warmup(solver: Callable | None, p: SolveParams) -> None:
    """Compile what the solver needs once, before the fan-out (a no-op for solvers without ``warmup``).

    In the main thread (the sweep driver) SIGINT and SIGTERM still reach Python's handlers
    afterwards: ``gmsh.initialize`` puts both back to their default action at C level (while
    ``signal.getsignal`` still reports Python's handler), so a Ctrl-C or ``scancel`` after the
    warm-up killed the driver without its summary, leaving its lock and markers.  Both signals
    are blocked during the warm-up, Python's handlers installed again, then one that came
    meanwhile is delivered."""
    if solver is None:
        from elastimap.solver import warmup as warm
    else:
        warm = getattr(solver, "warmup", None)
    if warm is None:
        return
    if threading.current_thread() is not threading.main_thread():
        warm(p)
        return
    sigs = {signal.SIGINT, signal.SIGTERM}
    handlers = {s: signal.getsignal(s) for s in sigs}
    signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    try:
        warm(p)
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, sigs)


def sample_params(sample: dict, base: SolveParams) -> SolveParams:
    """The solve inputs of one sample: ``base`` with the sample's inclusion (and tissue overrides)."""
    p = base.with_inclusion(d=float(sample["d"]), h=float(sample["h"]), E=float(sample["E"]))
    tissue = {}
    if sample.get("tissue_E") is not None:
        tissue["E"] = float(sample["tissue_E"])
    if sample.get("tissue_thickness") is not None:
        tissue["thickness"] = float(sample["tissue_thickness"])
    if tissue:
        p = p.replace(tissue=dataclasses.replace(p.tissue, **tissue))
    return p


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _base_row(sample: dict, p: SolveParams, solver: str = store.FEM) -> dict:
    return {
        "sample_id": sample["sample_id"],
        "tag": sample.get("tag", "design"),
        "d": float(sample["d"]),
        "h": float(sample["h"]),
        "E": float(sample["E"]),
        "params_json": json.dumps(p.to_dict(), sort_keys=True),
        "key": store.params_key(p),
        "solver": solver,
        "code_version": code_version(),
        "host": host(),
    }


def failed_row(
    sample: dict, p: SolveParams, error: str, seconds: float = float("nan"), solver: str = store.FEM
) -> dict:
    row = _base_row(sample, p, solver)
    nan = float("nan")
    row.update(
        O1=nan,
        O2=nan,
        O3=nan,
        force=nan,
        force_ref=nan,
        delta=nan,
        image=None,
        status="failed",
        error=error,
        ndofs=None,
        newton_iterations=None,
        seconds=seconds,
        peak_memory_mb=_peak_mb(),
    )
    return row


def result_row(sample: dict, p: SolveParams, res, seconds: float, solver: str = store.FEM) -> dict:
    """The store's row of the result (without ``image_raw``) under the sample's id and tag."""
    row = store.result_row(p, res, solver=solver, raw=False)
    row.update(_base_row(sample, p, solver), seconds=float(seconds))
    if row["peak_memory_mb"] is None or not row["peak_memory_mb"]:
        row["peak_memory_mb"] = _peak_mb()
    return row


def _mark(out_dir: str, kind: str, sample_id: str) -> Path:
    return Path(out_dir) / f".{kind}-{hashlib.sha1(sample_id.encode()).hexdigest()[:16]}"


def record_start(out_dir: str, sample_id: str) -> None:
    """Append one line to the sample's attempt file (O_APPEND: safe across processes)."""
    fd = os.open(_mark(out_dir, "attempts", sample_id), os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, f"{os.getpid()}\n".encode())
    finally:
        os.close(fd)


def attempts(out_dir: str, sample_id: str) -> int:
    """How many times a job of this sample has started in this run (see :func:`record_start`)."""
    try:
        return _mark(out_dir, "attempts", sample_id).read_bytes().count(b"\n")
    except FileNotFoundError:
        return 0


def _summary(row: dict) -> dict:
    return {"sample_id": row["sample_id"], "status": row["status"], "seconds": row["seconds"], "error": row["error"]}


def _failure(exc: BaseException) -> str:
    """A failed row's error text: the exception's type and message on one line."""
    msg = str(exc).strip().replace("\n", " ")
    return f"{type(exc).__name__}: {msg}"[:2000]


def _timed_out_before(sample: dict, out_dir: str, timeout: float | None) -> dict | None:
    """The summary of a sample whose solve timed out before (its marker: dask's retry of its task,
    which must return at once instead of hanging a second worker), else None."""
    if timeout and _mark(out_dir, "timeout", sample["sample_id"]).exists():
        msg = f"Timeout: no result after {timeout:g} s; the worker was stopped"
        return {"sample_id": sample["sample_id"], "status": "failed", "seconds": float(timeout), "error": msg}
    return None


def run_sample(
    sample: dict, base: dict, out_dir: str, timeout: float | None = None, solver: Callable | None = None
) -> dict:
    """Solve one sample with ``solver`` (None: the forward model) and land its row in ``out_dir``;
    return ``{sample_id, status, seconds, error}``.

    With ``timeout`` (s), a watchdog thread lands a ``failed`` row ("Timeout ...") and ends the
    worker process if the solve has not returned by then (a hung solve cannot be interrupted from
    Python); it leaves a marker so that dask's retry of the task returns at once instead of hanging
    a second worker.
    """
    before = _timed_out_before(sample, out_dir, timeout)
    if before is not None:
        return before
    p = sample_params(sample, SolveParams.from_dict(base))
    label = store.solver_label(solver)
    watch = _Watchdog(out_dir, timeout, label)
    watch.start(sample, p)
    shape = pixel = None  # a failed row has no image: its file carries no image geometry
    t0 = time.perf_counter()
    try:
        try:
            res = solve_with(solver, p)
            seconds = time.perf_counter() - t0
            row = result_row(sample, p, res, seconds, label)
            if row["status"] == "ok":
                shape, pixel = tuple(np.shape(res.image)), float(res.pixel)
        except Exception as exc:  # a failing sample is data, not a crash of the sweep
            row = failed_row(sample, p, _failure(exc), time.perf_counter() - t0, label)
        io.land_rows(out_dir, [row], shape, pixel)
    finally:
        watch.stop()
    return _summary(row)


#: at most this many samples of one geometry go to a worker as one task (``sweep run
#: --moduli-per-mesh``): they share its mesh, its model and its reference press
#: (:func:`elastimap.solver.batch.solve_group`); a worker that dies loses at most one task
GROUP_MAX = 16


def _geometry(sample: dict) -> tuple:
    return (sample["d"], sample["h"], *(sample.get(k) for k in ("tissue_E", "tissue_thickness")))


def group_samples(samples: list[dict]) -> list[list[dict]]:
    """``samples`` as tasks: the samples of one geometry (equal d, h and tissue overrides) together,
    in first-seen order, at most :data:`GROUP_MAX` a task; every other sample a task of its own."""
    groups: dict[tuple, list[list[dict]]] = {}
    order: list[list[dict]] = []
    for s in samples:
        chunks = groups.setdefault(_geometry(s), [])
        if not chunks or len(chunks[-1]) >= GROUP_MAX:
            chunks.append([])
            order.append(chunks[-1])
        chunks[-1].append(s)
    return order


def run_group(
    samples: list[dict], base: dict, out_dir: str, timeout: float | None = None, solver: Callable | None = None
) -> list[dict]:
    """Solve the samples of one geometry (:func:`group_samples`) and land each row as it is
    solved; return their summaries (:func:`run_sample`'s).  With the forward model (``solver`` None)
    they share one mesh, model and reference press (:func:`elastimap.solver.batch.solve_group`, its
    reference press in single precision as a single ``solve``'s); any other solver, or a group of
    one, runs :func:`run_sample` sample by sample.  ``timeout`` (s) is each sample's, as in
    :func:`run_sample`; a sample that timed out before (its marker) is not solved again."""
    if solver is not None or len(samples) == 1:
        return [run_sample(s, base, out_dir, timeout, solver) for s in samples]
    from elastimap.solver.batch import solve_group

    label = store.solver_label(solver)
    done: list[dict] = []
    live: list[tuple[dict, SolveParams]] = []
    for s in samples:
        before = _timed_out_before(s, out_dir, timeout)
        if before is not None:
            done.append(before)
        else:
            live.append((s, sample_params(s, SolveParams.from_dict(base))))
    if not live:
        return done
    watch = _Watchdog(out_dir, timeout, label)
    landed = [False] * len(live)

    def land(i: int, res) -> None:
        s, p = live[i]
        if isinstance(res, Exception):
            row = failed_row(s, p, _failure(res), float("nan"), label)
            io.land_rows(out_dir, [row])
        else:
            row = result_row(s, p, res, res.seconds, label)
            ok = row["status"] == "ok"
            io.land_rows(out_dir, [row], *((tuple(np.shape(res.image)), float(res.pixel)) if ok else ()))
        landed[i] = True
        done.append(_summary(row))
        if i + 1 < len(live):
            watch.start(*live[i + 1])

    watch.start(*live[0])
    try:
        solve_group([p for _, p in live], land, errors="return", single_factors=True)
    except Exception as exc:  # a failing group is data, not a crash of the sweep
        for i, (s, p) in enumerate(live):
            if not landed[i]:
                row = failed_row(s, p, _failure(exc), float("nan"), label)
                io.land_rows(out_dir, [row])
                done.append(_summary(row))
    finally:
        watch.stop()
    return done


class _Watchdog:
    """A sample's timeout (:func:`run_sample`, each sample of :func:`run_group` in turn):
    ``start(sample, params)`` records the sample's start and (re)arms a timer that lands its
    ``failed`` row, leaves its marker and ends the worker process; ``stop()`` disarms it."""

    def __init__(self, out_dir: str, timeout: float | None, label: str):
        self.out_dir, self.timeout, self.label, self.timer = out_dir, timeout, label, None

    def start(self, sample: dict, p: SolveParams) -> None:
        self.stop()
        sid = sample["sample_id"]
        record_start(self.out_dir, sid)
        if not self.timeout:
            return
        msg = f"Timeout: no result after {self.timeout:g} s; the worker was stopped"

        def _fire():
            try:
                io.land_rows(self.out_dir, [failed_row(sample, p, msg, float(self.timeout), self.label)])
                _mark(self.out_dir, "timeout", sid).write_text(sid)
            finally:
                os._exit(75)

        self.timer = threading.Timer(self.timeout, _fire)
        self.timer.daemon = True
        self.timer.start()

    def stop(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None


def land_failure(sample: dict, base: dict, out_dir: str, error: str, solver: Callable | None = None) -> None:
    """Record a sample whose job never returned (worker crashed twice) — run by the driver."""
    p = sample_params(sample, SolveParams.from_dict(base))
    io.land_rows(out_dir, [failed_row(sample, p, error, solver=store.solver_label(solver))])
