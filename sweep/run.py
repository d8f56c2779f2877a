"""The sweep driver: plan samples, skip what has landed, fan out one job per sample, summarise.

Order of work (nothing is written before step 3, so bad input leaves no trace):

1. check every setting against ``SweepConfig``'s declared rules (``UserError`` names the
   parameter; the command line shows it as its flag);
2. build the sample list (design + ``--samples`` + ``--phantoms``) and validate
   every sample's solve inputs;
3. lock the output directory, check/extend its manifest (``_sweep.json``),
   read the ids that have landed, and keep the missing (and, with
   ``--retry-failed``, the failed) samples;
4. compile the solver's forms once here (``warmup``), start a dask
   ``LocalCluster`` (processes, one thread each) or connect to ``--scheduler``,
   submit one task per sample (each lands its own row), collect results with
   a progress bar, record worker crashes as failed rows, merge row files into
   batches as they accumulate;
5. stop the cluster, compact, print the summary.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
import sys
import time
import uuid
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

from elastimap.constraints import Interval, Options, Predicate, validate_params
from elastimap.dataset import io, store
from elastimap.errors import UserError
from elastimap.provenance import code_version, host
from elastimap.solver.params import INTERFACES, MESH_LEVELS, Discretisation, SolveParams

from . import design as dsg
from . import jobs

MAX_JOBS = 256


@dataclass
class SweepConfig:
    """One sweep's settings; ``ranges`` is a dict (see :func:`elastimap.sweep.design.check_ranges`),
    ``None`` for the default ranges."""

    n: int | None = None            # None: 512, or 0 when samples is given
    jobs: int = 2
    seed: int = 0
    out: str | None = None
    mesh: str = "default"
    interface: str = "tied"
    design: str = "lhs"
    ranges: dict | None = None
    samples: str | None = None
    phantoms: bool = False
    retry_failed: bool = False
    scheduler: str | None = None
    batch_rows: int = io.BATCH_ROWS
    timeout: float | None = 1800.0  # s per sample; None or 0: no limit
    progress: bool = True
    compact: bool = True
    argv: list[str] = field(default_factory=list)
    # None: the forward model; tests pass the SYNTHETIC stand-in (see sweep.jobs), which the
    # workers receive as a task argument
    solver: Callable | None = None

    #: What each setting alone must be (relations between settings are checked in ``make_plan``).
    _parameter_constraints = {
        "n": [None, Interval(int, 0, dsg.MAX_N)],
        "jobs": [Interval(int, 1, MAX_JOBS)],
        "seed": [Interval(int, 0, None)],
        "mesh": [Options(MESH_LEVELS)],
        "interface": [Options(INTERFACES)],
        "design": [Options(dsg.DESIGNS)],
        "ranges": [None, Predicate(lambda r: isinstance(r, dict), "a dict {name: (lo, hi[, scale])}")],
        "batch_rows": [Interval(int, 1, None)],
        "timeout": [None, Interval(float, 0, None, unit="s")],
    }

    def validate(self) -> SweepConfig:
        validate_params(vars(self), self._parameter_constraints)
        return self


@dataclass
class Plan:
    cfg: SweepConfig
    base: SolveParams
    samples: list[dict]
    out: Path
    ranges: dict


def default_out(cfg: SweepConfig, n: int) -> str:
    parts = [cfg.mesh, cfg.interface]
    if cfg.samples:
        parts.append(Path(cfg.samples).stem)
    if n:
        parts.append(f"{cfg.design}{n}-s{cfg.seed}")
    if cfg.phantoms:
        parts.append("phantoms")
    return str(Path("sweeps") / "-".join(parts))


def _jsonable(d: dict) -> dict:
    return json.loads(json.dumps(d))


def make_plan(cfg: SweepConfig) -> Plan:
    """Check everything and list the samples; writes nothing."""
    cfg.validate()
    n = cfg.n if cfg.n is not None else (0 if cfg.samples else 512)
    base = SolveParams(disc=Discretisation(mesh=cfg.mesh, interface=cfg.interface)).validate()
    ranges = dsg.check_ranges(cfg.ranges, base.tissue.thickness)
    samples = dsg.design_points(n, cfg.design, cfg.seed, ranges, base.tissue.thickness)
    if cfg.samples:
        samples += dsg.load_samples(cfg.samples)
    if cfg.phantoms:
        samples += dsg.load_phantoms()
    if not samples:
        raise UserError("n", "nothing to run (n = 0, and no samples table or phantoms)")
    seen: dict[str, dict] = {}
    for s in samples:
        if s["sample_id"] in seen:
            raise UserError("samples", f"sample id {s['sample_id']!r} occurs twice (in the design/phantoms and the table?)")
        seen[s["sample_id"]] = s
        try:
            jobs.sample_params(s, base).validate()
        except UserError as exc:
            where = "samples" if s["tag"] == "user" else ("phantoms" if s["tag"].startswith("phantom") else "ranges")
            raise UserError(where, f"sample {s['sample_id']} (d={s['d']:g} mm, h={s['h']:g} mm, E={s['E']:g} kPa) "
                                   f"is not a valid solve: {exc}") from None
    out = Path(cfg.out or default_out(cfg, n))
    if out.exists() and not out.is_dir():
        raise UserError("out", f"{out} exists and is not a directory")
    if out.is_dir():
        man = io.read_manifest(out)
        if man is None and any(out.iterdir()):
            raise UserError("out", f"{out} is not empty and holds no sweep manifest ({io.MANIFEST}); choose another --out")
        label = store.solver_label(cfg.solver)
        if man is not None and man.get("solver", store.FEM) != label:
            raise UserError("out", f"{out} holds a sweep by the {man.get('solver', store.FEM)!r} solver, not {label!r}; "
                                     "use another --out")
        if man is not None and man.get("base_params") != _jsonable(base.to_dict()):
            old = man.get("base_params", {}).get("disc", {})
            raise UserError("out", f"{out} holds a sweep with other solver settings (mesh={old.get('mesh')}, "
                                     f"interface={old.get('interface')}); use the same settings to resume, or another --out")
        _check_landed_match(out, samples)
    return Plan(cfg, base, samples, out, ranges)


def _check_landed_match(out: Path, samples: list[dict]) -> None:
    """Refuse to resume when a landed id carries other (d, h, E) than the planned sample of that id
    (an edited phantoms file or --samples table reusing ids): its row would silently be kept."""
    if not any(out.glob("*.parquet")):
        return
    df = io.read_table(out, ["sample_id", "d", "h", "E"])
    landed = {r.sample_id: (r.d, r.h, r.E) for r in df.itertuples()}
    bad = []
    for s in samples:
        got = landed.get(s["sample_id"])
        if got is not None and any(abs(a - float(s[k])) > 1e-9 * max(1.0, abs(a)) for a, k in zip(got, dsg.NAMES)):
            bad.append(f"{s['sample_id']} (landed d={got[0]:g}, h={got[1]:g}, E={got[2]:g}; "
                       f"now d={s['d']:g}, h={s['h']:g}, E={s['E']:g})")
    if bad:
        raise UserError("out", f"{out} already holds {len(bad)} sample id(s) with other parameters: "
                                 f"{'; '.join(bad[:3])}; use another --out or other sample ids")


# ----------------------------------------------------------------------------- lock

# ----------------------------------------------------------------------------- run

def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _start_client(cfg: SweepConfig):
    import dask
    from distributed import Client, LocalCluster

    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")  # workers inherit: one core per solve
    # a task whose worker dies is retried once, then fails with KilledWorker (set before the
    # scheduler starts; a remote scheduler needs it in its own config, see workflows/)
    dask.config.set({"distributed.scheduler.allowed-failures": 1,
                     # one task per one-thread worker at a time: when a worker dies, only the sample it
                     # was running counts the death (with dask's default 1.1 a second sample queued
                     # on that worker was blamed too, and could end as KilledWorker without running)
                     "distributed.scheduler.worker-saturation": 1.0})
    if not cfg.scheduler:
        # The local scheduler and the nannies live in the driver process.  dask's default polling
        # (memory monitor 100 ms, system monitor 500 ms, tick 20 ms) costs the idle driver about
        # 7 % of a core, measured; these intervals bring it to about 2 %, which on a 2-core machine
        # goes back to the solves.  A memory runaway is still caught within a second.
        dask.config.set({"distributed.worker.memory.monitor-interval": "1s",
                         "distributed.admin.system-monitor.interval": "2s",
                         "distributed.admin.tick.interval": "200ms"})
    if cfg.scheduler:
        try:
            client = Client(cfg.scheduler, timeout="20s")
        except Exception as exc:
            raise UserError("scheduler", f"cannot connect to {cfg.scheduler} ({type(exc).__name__}: {exc})") from None
        return client, None
    # ":0": a free port for the scheduler's HTTP endpoint, so concurrent sweeps do not collide on 8787
    cluster = LocalCluster(n_workers=cfg.jobs, threads_per_worker=1, processes=True,
                           dashboard_address=":0", silence_logs=logging.CRITICAL)
    return Client(cluster), cluster


def _clear_markers(out: Path) -> None:
    """Per-run job markers (attempt counts, timeouts) in the dataset directory."""
    for pattern in (".timeout-*", ".attempts-*"):
        for m in out.glob(pattern):
            m.unlink(missing_ok=True)


def run(cfg: SweepConfig, plan: Plan | None = None) -> dict:
    """Run a sweep; returns the summary dict (also stored in the manifest's run log)."""
    t_start = time.perf_counter()
    plan = plan or make_plan(cfg)
    out = plan.out
    remote = _start_client(cfg) if cfg.scheduler else None  # a bad address fails before anything is written
    out.mkdir(parents=True, exist_ok=True)
    lock = io.acquire_lock(out)
    summary = {"out": str(out), "planned": len(plan.samples), "done": 0, "ok": 0, "failed": 0, "skipped": 0,
               "todo": 0, "interrupted": False}
    try:
        io.remove_stale_tmp(out)
        _clear_markers(out)
        landed = io.landed_status(out)
        todo = [s for s in plan.samples
                if s["sample_id"] not in landed or (cfg.retry_failed and landed[s["sample_id"]] != "ok")]
        summary["skipped"] = len(plan.samples) - len(todo)
        summary["todo"] = len(todo)
        man = io.read_manifest(out) or {"format": "elastimap-sweep", "schema_version": io.SCHEMA_VERSION,
                                        "created": _now(), "base_params": _jsonable(plan.base.to_dict()),
                                        "solver": store.solver_label(cfg.solver),
                                        "planned": [], "runs": []}
        known = set(man["planned"])
        man["planned"] += [s["sample_id"] for s in plan.samples if s["sample_id"] not in known]
        run_log = {"started": _now(), "argv": cfg.argv, "n": cfg.n, "design": cfg.design, "seed": cfg.seed,
                   "ranges": dsg.ranges_text(plan.ranges), "samples": cfg.samples, "phantoms": cfg.phantoms,
                   "jobs": cfg.jobs, "scheduler": cfg.scheduler, "code_version": code_version(), "host": host()}
        man["runs"].append(run_log)
        io.write_manifest(out, man)
        if todo:
            _fan_out(cfg, plan, todo, summary, remote)
    except KeyboardInterrupt:
        summary["interrupted"] = True  # landed rows stay; the caller reports and exits 130
    finally:
        try:
            if cfg.compact and any(out.glob("r-*.parquet")) and not summary["interrupted"]:
                summary["compaction"] = io.compact(out, cfg.batch_rows)
            final = io.landed_status(out)
            planned_ids = {s["sample_id"] for s in plan.samples}
            summary["dataset_ok"] = sum(1 for k, v in final.items() if k in planned_ids and v == "ok")
            summary["dataset_failed"] = sum(1 for k, v in final.items() if k in planned_ids and v != "ok")
            summary["missing"] = len(planned_ids - set(final))
            summary["wall_s"] = time.perf_counter() - t_start
            summary["samples_per_min"] = 60.0 * summary["done"] / summary["wall_s"] if summary["wall_s"] > 0 else 0.0
            man = io.read_manifest(out)
            if man and man.get("runs"):
                man["runs"][-1].update(finished=_now(), summary={k: v for k, v in summary.items() if k != "errors"})
                io.write_manifest(out, man)
        finally:
            _clear_markers(out)
            lock.unlink(missing_ok=True)
            if remote is not None:
                remote[0].close()
    return summary


def _fan_out(cfg: SweepConfig, plan: Plan, todo: list[dict], summary: dict, remote=None) -> None:
    from distributed import as_completed
    from tqdm import tqdm

    base = plan.base.to_dict()
    out = str(plan.out.resolve())
    solver = cfg.solver
    t0 = time.perf_counter()
    # with the base inclusion, not a sampled one: a sample whose geometry fails must fail as a
    # sample, not stop the sweep.  If the warm-up itself fails the workers compile on first use.
    try:
        jobs.warmup(solver, plan.base)
    except Exception as exc:
        print(f"warning: solver warm-up failed ({type(exc).__name__}: {exc}); workers will compile "
              "the forms themselves", file=sys.stderr)
    summary["warmup_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    client, cluster = remote if remote is not None else _start_client(cfg)
    summary["cluster_start_s"] = time.perf_counter() - t0
    summary["workers"] = len(client.scheduler_info(n_workers=-1)["workers"]) if cluster is None else cfg.jobs
    errors: list[tuple[str, str]] = []
    solve_seconds = 0.0
    try:
        t_fan = time.perf_counter()
        cpu0 = time.process_time()
        token = uuid.uuid4().hex[:8]
        # one map call: the whole batch reaches the scheduler at once, as one task group, so dask
        # queues it and hands each one-thread worker one sample at a time (worker-saturation 1.0)
        futures = client.map(jobs.run_sample, todo, base=base, out_dir=out, timeout=cfg.timeout or None,
                             solver=solver, key=[f"sweep-sample-{i:07d}-{token}" for i in range(len(todo))], pure=False)
        by_future = dict(zip(futures, todo))
        resubmitted: dict[str, int] = {}
        tty = sys.stderr.isatty()
        try:
            size = os.get_terminal_size(sys.stderr.fileno())
        except (OSError, ValueError):
            size = os.terminal_size((0, 0))
        # a pseudo-terminal of size 0x0 (some CI runners, `script`) would make tqdm print nothing
        sized = size.columns > 0 and size.lines > 0
        bar = tqdm(total=len(todo), desc="sweep", unit="sample", file=sys.stderr, disable=not cfg.progress,
                   mininterval=0.5 if tty else 15.0, dynamic_ncols=sized, ncols=None if sized else 100,
                   nrows=None if sized else 50, smoothing=0.1)
        since_compact = 0
        pending = as_completed(list(by_future))
        for fut in pending:
            s = by_future.pop(fut)
            try:
                r = fut.result()
            except Exception as exc:  # KilledWorker (crashed twice) or a bug in the job itself
                name = type(exc).__name__
                sid = s["sample_id"]
                n_started = jobs.attempts(out, sid)
                if name == "KilledWorker" and n_started < 2 and resubmitted.get(sid, 0) < 3:
                    # dask blames every task a dying worker held; this one did not crash twice
                    # itself (it was waiting next to a crashing sample): run it again
                    resubmitted[sid] = resubmitted.get(sid, 0) + 1
                    again = client.submit(jobs.run_sample, s, base=base, out_dir=out, timeout=cfg.timeout or None,
                                          solver=solver, key=f"sweep-retry-{uuid.uuid4().hex}", pure=False)
                    by_future[again] = s
                    pending.add(again)
                    fut.release()
                    continue
                msg = (f"worker crashed twice on this sample (segfault, abort or out of memory): {name}"
                       if name == "KilledWorker" else f"{name}: {exc}")
                jobs.land_failure(s, base, out, msg[:2000], solver)
                r = {"sample_id": s["sample_id"], "status": "failed", "seconds": float("nan"), "error": msg}
            fut.release()
            summary["done"] += 1
            if r["status"] == "ok":
                summary["ok"] += 1
                solve_seconds += r["seconds"]
            else:
                summary["failed"] += 1
                errors.append((r["sample_id"], r["error"]))
            bar.set_postfix(ok=summary["ok"], failed=summary["failed"], refresh=False)
            bar.update(1)
            since_compact += 1
            if cfg.compact and since_compact >= cfg.batch_rows:
                io.compact(plan.out, cfg.batch_rows, only_rows=True)
                since_compact = 0
        bar.close()
        fan_wall = time.perf_counter() - t_fan
        summary["fan_out_s"] = fan_wall
        summary["driver_cpu_ms_per_sample"] = 1000.0 * (time.process_time() - cpu0) / max(summary["done"], 1)
        summary["mean_solve_s"] = solve_seconds / summary["ok"] if summary["ok"] else float("nan")
        if fan_wall > 0 and summary["ok"]:
            summary["worker_utilisation"] = solve_seconds / (fan_wall * max(summary["workers"], 1))
    finally:
        summary["errors"] = errors
        if cluster is not None:  # a local cluster is ours to stop; a remote client is closed by run()
            try:
                client.close()
            finally:
                cluster.close()


def format_summary(s: dict) -> str:
    lines = [f"sweep: {s['out']}: {s['done']} done this run (ok {s['ok']}, failed {s['failed']}), "
             f"{s['skipped']} skipped (already landed), wall {s['wall_s']:.1f} s, "
             f"{s['samples_per_min']:.1f} samples/min"]
    if s["done"]:
        extra = [f"warm-up {s.get('warmup_s', 0):.1f} s", f"cluster start {s.get('cluster_start_s', 0):.1f} s"]
        if s.get("mean_solve_s") == s.get("mean_solve_s") and "mean_solve_s" in s:
            extra.append(f"mean solve {s['mean_solve_s']:.2f} s")
        if "worker_utilisation" in s:
            extra.append(f"worker utilisation {100 * s['worker_utilisation']:.0f} %")
        extra.append(f"driver CPU {s.get('driver_cpu_ms_per_sample', 0):.1f} ms/sample")
        lines.append("       " + ", ".join(extra))
    lines.append(f"       dataset: {s['dataset_ok']} ok, {s['dataset_failed']} failed, {s['missing']} missing "
                 f"of {s['planned']} planned")
    for sid, err in s.get("errors", [])[:10]:
        lines.append(f"       failed {sid}: {err[:200]}")
    if len(s.get("errors", [])) > 10:
        lines.append(f"       ... and {len(s['errors']) - 10} more (dataset inspect {s['out']})")
    if s["dataset_failed"]:
        lines.append("       rerun with --retry-failed to run the failed samples again")
    return "\n".join(lines)
