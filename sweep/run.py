"""The sweep driver: plan samples, skip what has landed, fan out one job per sample, summarise.

Order of work (nothing is written before step 3, so bad input leaves no trace):

1. check every setting against ``SweepConfig``'s declared rules (``UserError`` names the
   parameter; the command line shows it as its flag);
2. build the sample list (design + ``--samples`` + ``--phantoms``) and validate
   every sample's solve inputs;
   an existing output directory must hold the same solver settings and the
   same design (another ``--seed``, ``--n``, ``--design``, ``--ranges``,
   ``--samples`` or ``--phantoms`` that adds samples is refused unless
   ``--append``);
3. connect to ``--scheduler`` (bounded, see :mod:`.cluster`), lock the output
   directory, check/extend its manifest (``_sweep.json``), read the ids that
   have landed, and keep the missing (and, with ``--retry-failed``, the
   failed) samples;
4. compile the solver's forms once here (``warmup``) and start a dask
   ``LocalCluster`` (processes, one thread each), or, on an external
   scheduler, register a worker plugin that warms every worker when it joins;
   submit one task per sample (each lands its own row), collect results with
   a progress bar, record worker crashes as failed rows, merge row files into
   batches as they accumulate; a cluster with no worker for ``--worker-wait``
   seconds ends the run (exit 3);
5. stop the cluster, compact, print the summary (what the whole folder holds).

SIGTERM (``scancel``, a SLURM time limit) is handled like Ctrl-C: landed rows
stay, the lock and the per-run markers are removed, the summary is printed.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import functools
import json
import math
import os
import signal
import sys
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from elastimap.constraints import Interval, Options, Predicate, validate_params
from elastimap.dataset import io, store
from elastimap.dataset.phantoms import phantom_samples
from elastimap.errors import UserError
from elastimap.provenance import code_version, host, library_versions
from elastimap.sensor import PAPER_HASH, Sensor
from elastimap.solver.params import (
    GEOMETRIES,
    INTERFACES,
    MESH_LEVELS,
    SIZINGS,
    Discretisation,
    SolveParams,
    from_sensor,
)

from . import design as dsg
from . import jobs

MAX_JOBS = 256
CLOSE_TIMEOUT = 10.0  # s to close the client of an external scheduler (one that may be gone)


def _is_host_port(a) -> bool:
    """``HOST:PORT``, ``:PORT`` or ``[IPv6]:PORT`` with PORT in [0, 65535]."""
    host, sep, port = str(a).rpartition(":")
    return bool(sep) and port.isdigit() and int(port) <= 65535 and (":" not in host or host[:1] + host[-1:] == "[]")


@dataclass
class SweepConfig:
    """One sweep's settings; ``ranges`` is a dict (see :func:`elastimap.sweep.design.check_ranges`),
    ``None`` for the default ranges."""

    n: int | None = None  # None: 512, or 0 when samples is given
    jobs: int = 2
    seed: int = 0
    out: str | None = None
    mesh: str = "default"
    interface: str = "tied"
    geometry: str = "remesh"  # or "morph": reference meshes moved to each (d, h) (solver/morph.py)
    sizing: str = "fixed"  # or "by_d": element size near the inclusion scaled with d (solver/geometry.py)
    design: str = "lhs"
    moduli_per_mesh: int = 1  # k inclusion moduli per design geometry, sharing its mesh (design.design_points)
    ranges: dict | None = None
    samples: str | None = None
    phantoms: bool = False
    retry_failed: bool = False
    scheduler: str | None = None
    dashboard: str | None = None  # the local cluster's dashboard address; None: no dashboard
    append: bool = False  # extend an existing folder with another design
    break_lock: bool = False  # remove another host's lock (a driver that is gone)
    connect_timeout: float = 30.0  # s for --scheduler to answer
    worker_wait: float = 60.0  # s the run goes on with no worker in the cluster
    batch_rows: int = io.BATCH_ROWS
    timeout: float | None = 1800.0  # s per sample; None or 0: no limit
    progress: bool = True
    compact: bool = True
    argv: list[str] = field(default_factory=list)
    # None: the forward model; tests pass the SYNTHETIC stand-in (see sweep.jobs), which the
    # workers receive as a task argument
    solver: Callable | None = None
    #: the sensor description (elastimap.sensor.Sensor); None: the paper's.  ``interface`` above
    #: replaces the description's interface model (the command line fills it from the description)
    sensor: Sensor | None = None

    #: What each setting alone must be (relations between settings are checked in ``make_plan``).
    _parameter_constraints = {
        "n": [None, Interval(int, 0, dsg.MAX_N)],
        "jobs": [Interval(int, 1, MAX_JOBS)],
        "seed": [Interval(int, 0, None)],
        "mesh": [Options(MESH_LEVELS)],
        "interface": [Options(INTERFACES)],
        "geometry": [Options(GEOMETRIES)],
        "sizing": [Options(SIZINGS)],
        "design": [Options(dsg.DESIGNS)],
        "moduli_per_mesh": [Interval(int, 1, dsg.MAX_MODULI_PER_MESH)],
        "ranges": [None, Predicate(lambda r: isinstance(r, dict), "a dict {name: (lo, hi[, scale])}")],
        "batch_rows": [Interval(int, 1, None)],
        "timeout": [None, Interval(float, 0, None, unit="s")],
        "scheduler": [
            None,
            Predicate(
                lambda a: isinstance(a, str) and bool(a.strip()),
                "a dask scheduler address like tcp://host:8786 (leave it out for a local cluster)",
            ),
        ],
        "dashboard": [
            None,
            Predicate(_is_host_port, "an address HOST:PORT or :PORT with PORT in [0, 65535] (e.g. 127.0.0.1:8787)"),
        ],
        "connect_timeout": [Interval(float, 0, None, closed="neither", unit="s")],
        "worker_wait": [Interval(float, 0, None, closed="neither", unit="s")],
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
    design: dict = field(default_factory=dict)  # how the samples were chosen (recorded in the manifest)
    new_ids: int = 0  # planned ids the folder's manifest does not list yet


class ClusterLost(RuntimeError):
    """The cluster had no worker for ``--worker-wait`` seconds."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, handled like Ctrl-C."""


def sweep_sensor(cfg: SweepConfig) -> Sensor:
    """The sensor a sweep runs: ``cfg.sensor`` (the paper's when None) with ``cfg.interface``."""
    s = cfg.sensor or Sensor()
    return s.replace(interface=dataclasses.replace(s.interface, model=cfg.interface))


def default_out(cfg: SweepConfig, n: int) -> str:
    parts = [cfg.mesh, cfg.interface] + [v for v in (cfg.geometry, cfg.sizing) if v in ("morph", "by_d")]
    if not sweep_sensor(cfg).is_paper:
        parts.append(f"sensor{sweep_sensor(cfg).hash()[:8]}")
    if cfg.samples:
        parts.append(Path(cfg.samples).stem)
    if n:
        parts.append(f"{cfg.design}{n}-s{cfg.seed}" + (f"-m{cfg.moduli_per_mesh}" if cfg.moduli_per_mesh > 1 else ""))
    if cfg.phantoms:
        parts.append("phantoms")
    return str(Path("sweeps") / "-".join(parts))


def _jsonable(d: dict) -> dict:
    return json.loads(json.dumps(d))


def make_plan(cfg: SweepConfig) -> Plan:
    """Check everything and list the samples; writes nothing."""
    cfg.validate()
    n = cfg.n if cfg.n is not None else (0 if cfg.samples else 512)
    disc = Discretisation(mesh=cfg.mesh, interface=cfg.interface, geometry=cfg.geometry, sizing=cfg.sizing)
    sensor = sweep_sensor(cfg).validate()
    base = from_sensor(sensor, disc=disc).validate()
    ranges = dsg.check_ranges(cfg.ranges, base.tissue.thickness)
    samples = dsg.design_points(n, cfg.design, cfg.seed, ranges, base.tissue.thickness, cfg.moduli_per_mesh)
    if cfg.samples:
        samples += dsg.load_samples(cfg.samples)
    if cfg.phantoms:
        samples += phantom_samples()
    if not samples:
        raise UserError("n", "nothing to run (n = 0, and no samples table or phantoms)")
    seen: dict[str, dict] = {}
    for s in samples:
        if s["sample_id"] in seen:
            raise UserError(
                "samples", f"sample id {s['sample_id']!r} occurs twice (in the design/phantoms and the table?)"
            )
        seen[s["sample_id"]] = s
        try:
            jobs.sample_params(s, base).validate()
        except UserError as exc:
            where = "samples" if s["tag"] == "user" else ("phantoms" if s["tag"].startswith("phantom") else "ranges")
            raise UserError(
                where,
                f"sample {s['sample_id']} (d={s['d']:g} mm, h={s['h']:g} mm, E={s['E']:g} kPa) "
                f"is not a valid solve: {exc}",
            ) from None
    out = Path(cfg.out or default_out(cfg, n))
    if out.exists() and not out.is_dir():
        raise UserError("out", f"{out} exists and is not a directory")
    from elastimap.outputs import check_out_dir

    check_out_dir(out, "out", allow_existing=True)  # writable (or creatable), before any solve
    man = None
    if out.is_dir():
        man = io.read_manifest(out)
        if man is None and any(out.iterdir()):
            raise UserError(
                "out", f"{out} is not empty and holds no sweep manifest ({io.MANIFEST}); choose another --out"
            )
        label = store.solver_label(cfg.solver)
        if man is not None and man.get("solver", store.FEM) != label:
            raise UserError(
                "out",
                f"{out} holds a sweep by the {man.get('solver', store.FEM)!r} solver, not {label!r}; use another --out",
            )
        if man is not None and man.get("sensor_hash", PAPER_HASH) != sensor.hash():
            theirs = man.get("sensor", {}).get("name", "paper") if man.get("sensor") else "paper"
            raise UserError(
                "out",
                f"{out} holds a sweep of another sensor ({theirs!r}, hash {man.get('sensor_hash', PAPER_HASH)}); "
                f"this command's is {sensor.name!r} (hash {sensor.hash()}); one folder holds one sensor: "
                "use another --out",
            )
        if man is not None and man.get("base_params") != _jsonable(base.to_dict()):
            old = man.get("base_params", {}).get("disc", {})
            raise UserError(
                "out",
                f"{out} holds a sweep with other solver settings (mesh={old.get('mesh')}, "
                f"interface={old.get('interface')}); use the same settings to resume, or another --out",
            )
        _check_landed_match(out, samples)
    design = {
        "design": cfg.design,
        "n": n,
        "seed": cfg.seed,
        "ranges": dsg.ranges_text(ranges) if n else None,
        **({"moduli_per_mesh": cfg.moduli_per_mesh} if cfg.moduli_per_mesh > 1 else {}),
        "samples": cfg.samples,
        "phantoms": cfg.phantoms,
    }
    new_ids = len(samples)
    if man is not None:
        known = set(man.get("planned", []))
        new_ids = sum(1 for s in samples if s["sample_id"] not in known)
        if new_ids and known and not cfg.append:
            raise UserError("out", _design_conflict(out, man, design, new_ids))
    return Plan(cfg, base, samples, out, ranges, design, new_ids)


_DESIGN_FLAGS = (
    ("seed", "--seed"),
    ("n", "--n"),
    ("design", "--design"),
    ("moduli_per_mesh", "--moduli-per-mesh"),
    ("ranges", "--ranges"),
    ("samples", "--samples"),
    ("phantoms", "--phantoms"),
)


def _recorded_designs(man: dict) -> list[dict]:
    """The designs a manifest records (older manifests: read from the run log)."""
    if man.get("designs"):
        return list(man["designs"])
    out = []
    for r in man.get("runs", []):
        d = {
            "design": r.get("design"),
            "n": r.get("n") if r.get("n") is not None else (0 if r.get("samples") else 512),
            "seed": r.get("seed"),
            "ranges": r.get("ranges"),
            "samples": r.get("samples"),
            "phantoms": bool(r.get("phantoms")),
        }
        if d not in out:
            out.append(d)
    return out


def _design_text(d: dict) -> str:
    parts = []
    if d.get("n"):
        parts.append(f"--design {d.get('design')} --n {d.get('n')} --seed {d.get('seed')} --ranges {d.get('ranges')}")
        if d.get("moduli_per_mesh", 1) > 1:
            parts.append(f"--moduli-per-mesh {d['moduli_per_mesh']}")
    if d.get("samples"):
        parts.append(f"--samples {d['samples']}")
    if d.get("phantoms"):
        parts.append("--phantoms")
    return " ".join(parts) or "no samples"


def _design_conflict(out: Path, man: dict, design: dict, new_ids: int) -> str:
    rec = _recorded_designs(man)
    last = rec[-1] if rec else {}

    def value(d: dict, k: str):
        return d.get(k, 1 if k == "moduli_per_mesh" else None)  # recorded only when above 1

    differ = [
        f"{flag} {value(design, k)!s} (folder: {value(last, k)!s})"
        for k, flag in _DESIGN_FLAGS
        if last and value(design, k) != value(last, k) and not (k == "ranges" and not design.get("n"))
    ]
    what = ", ".join(differ) if differ else "other sample rows"
    return (
        f"{out} holds a sweep of another design ({_design_text(last) if last else 'unrecorded'}); this command "
        f"would add {new_ids} sample(s): {what}; rerun with the folder's options to resume, add --append to "
        f"extend the folder, or choose another --out"
    )


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
            bad.append(
                f"{s['sample_id']} (landed d={got[0]:g}, h={got[1]:g}, E={got[2]:g}; "
                f"now d={s['d']:g}, h={s['h']:g}, E={s['E']:g})"
            )
    if bad:
        raise UserError(
            "out",
            f"{out} already holds {len(bad)} sample id(s) with other parameters: "
            f"{'; '.join(bad[:3])}; use another --out or other sample ids",
        )


# ----------------------------------------------------------------------------- lock

# ----------------------------------------------------------------------------- run


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def check_foreign_lock(out: Path, break_lock: bool) -> None:
    """A lock written on another host cannot be checked for life from here: refuse it, naming the
    host, unless ``--break-lock`` (then remove it and say whose it was)."""
    lock = out / io.LOCK
    try:
        text = lock.read_text()
        since = _dt.datetime.fromtimestamp(lock.stat().st_mtime, _dt.UTC).isoformat(timespec="seconds")
    except FileNotFoundError:
        return
    try:
        other = json.loads(text or "{}")
    except ValueError:
        other = {}
    who = f"pid {other.get('pid', '?')} on {other.get('host', '?')}, locked since {since}"
    if break_lock:
        print(f"note: --break-lock: removing {lock} ({who})", file=sys.stderr)
        lock.unlink(missing_ok=True)
        return
    if other.get("host") and other["host"] != host():
        raise UserError(
            "out",
            f"{out} is locked by a sweep on another host ({who}); if that sweep is no longer "
            "running (a cancelled or timed-out job), rerun with --break-lock",
        )


def _start_client(cfg: SweepConfig):
    import dask
    from distributed import Client

    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")  # workers inherit: one core per solve
    # a task whose worker dies is retried once, then fails with KilledWorker (set before the
    # scheduler starts; a remote scheduler needs it in its own config, see workflows/)
    dask.config.set(
        {
            "distributed.scheduler.allowed-failures": 1,
            # one task per one-thread worker at a time: when a worker dies, only the sample it
            # was running counts the death (with dask's default 1.1 a second sample queued
            # on that worker was blamed too, and could end as KilledWorker without running)
            "distributed.scheduler.worker-saturation": 1.0,
        }
    )
    if not cfg.scheduler:
        # The local scheduler and the nannies live in the driver process.  dask's default polling
        # (memory monitor 100 ms, system monitor 500 ms, tick 20 ms) costs the idle driver about
        # 7 % of a core, measured; these intervals bring it to about 2 %, which on a 2-core machine
        # goes back to the solves.  A memory runaway is still caught within a second.
        dask.config.set(
            {
                "distributed.worker.memory.monitor-interval": "1s",
                "distributed.admin.system-monitor.interval": "2s",
                "distributed.admin.tick.interval": "200ms",
            }
        )
    if cfg.scheduler:
        from .cluster import connect

        return connect(cfg.scheduler.strip(), cfg.connect_timeout), None
    from .cluster import local_cluster

    cluster = local_cluster(cfg.jobs, cfg.dashboard)
    return Client(cluster), cluster


def _close_remote(client) -> None:
    from .cluster import close_client

    close_client(client, CLOSE_TIMEOUT)


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
    check_foreign_lock(out, cfg.break_lock)
    remote = _start_client(cfg) if cfg.scheduler else None  # a bad address fails before anything is written
    try:
        out.mkdir(parents=True, exist_ok=True)
        lock = io.acquire_lock(out)
    except BaseException:
        if remote is not None:
            _close_remote(remote[0])
        raise
    summary = {
        "out": str(out),
        "planned": len(plan.samples),
        "done": 0,
        "ok": 0,
        "failed": 0,
        "skipped": 0,
        "todo": 0,
        "interrupted": False,
    }
    restore = _handle_sigterm()
    try:
        io.remove_stale_tmp(out)
        _clear_markers(out)
        landed = io.landed_status(out)
        todo = [
            s
            for s in plan.samples
            if s["sample_id"] not in landed or (cfg.retry_failed and landed[s["sample_id"]] != "ok")
        ]
        if plan.base.disc.geometry == "morph":
            # samples of one reference mesh one after another, so a worker reuses its morphed Model
            from elastimap.solver.morph import reference_for

            def _ref(s):
                p = jobs.sample_params(s, plan.base)
                r = reference_for(p.inclusion.d, p.inclusion.h, p.tissue.thickness, p.inclusion.aspect)
                return (r.d0, r.h0)

            todo.sort(key=_ref)
        summary["skipped"] = len(plan.samples) - len(todo)
        summary["todo"] = len(todo)
        _record_run(cfg, plan)
        if todo:
            _fan_out(cfg, plan, todo, summary, remote)
    except KeyboardInterrupt as exc:
        summary["interrupted"] = True  # landed rows stay; the caller reports and exits 130 (143 for SIGTERM)
        summary["signal"] = "SIGTERM" if isinstance(exc, Terminated) else "SIGINT"
    except ClusterLost as exc:
        summary["aborted"] = str(exc)  # landed rows stay; the caller reports and exits 3
    finally:
        try:
            if cfg.compact and any(out.glob("r-*.parquet")) and not summary["interrupted"]:
                summary["compaction"] = io.compact(out, cfg.batch_rows)
            final = io.landed_status(out)
            planned_ids = {s["sample_id"] for s in plan.samples}
            summary["dataset_ok"] = sum(1 for k, v in final.items() if k in planned_ids and v == "ok")
            summary["dataset_failed"] = sum(1 for k, v in final.items() if k in planned_ids and v != "ok")
            summary["missing"] = len(planned_ids - set(final))
            summary["folder_ok"] = sum(1 for v in final.values() if v == "ok")
            summary["folder_failed"] = len(final) - summary["folder_ok"]
            summary["wall_s"] = time.perf_counter() - t_start
            summary["samples_per_min"] = 60.0 * summary["done"] / summary["wall_s"] if summary["wall_s"] > 0 else 0.0
            man = io.read_manifest(out)
            if man and man.get("runs"):
                man["runs"][-1].update(finished=_now(), summary={k: v for k, v in summary.items() if k != "errors"})
                io.write_manifest(out, man)
        finally:
            _clear_markers(out)
            lock.unlink(missing_ok=True)
            restore()
            if remote is not None:
                _close_remote(remote[0])
    return summary


def _record_run(cfg: SweepConfig, plan: Plan) -> None:
    """Write the run into the folder's manifest before anything is solved: the planned ids it adds,
    the design that added them, and this run's log (command, options, code and library versions,
    host; its summary is added when it ends)."""
    out = plan.out
    man = io.read_manifest(out) or {
        "format": "elastimap-sweep",
        "schema_version": io.SCHEMA_VERSION,
        "created": _now(),
        "base_params": _jsonable(plan.base.to_dict()),
        "solver": store.solver_label(cfg.solver),
        "planned": [],
        "runs": [],
    }
    man.update(sweep_sensor(cfg).record())  # an old manifest (no record) is the paper's sensor's
    known = set(man["planned"])
    new = [s["sample_id"] for s in plan.samples if s["sample_id"] not in known]
    man["planned"] += new
    designs = man.setdefault("designs", _recorded_designs(man) if man["runs"] else [])
    if new or not designs:
        designs.append({**plan.design, "added": _now(), "new_samples": len(new), "append": bool(known) and cfg.append})
    run_log = {
        "started": _now(),
        "argv": cfg.argv,
        "n": cfg.n,
        "design": cfg.design,
        "moduli_per_mesh": cfg.moduli_per_mesh,
        "seed": cfg.seed,
        "ranges": dsg.ranges_text(plan.ranges),
        "samples": cfg.samples,
        "phantoms": cfg.phantoms,
        "append": cfg.append,
        "jobs": cfg.jobs,
        "scheduler": cfg.scheduler,
        "code_version": code_version(),
        "versions": library_versions(),
        "host": host(),
    }
    man["runs"].append(run_log)
    io.write_manifest(out, man)


def _handle_sigterm():
    """Turn the first SIGTERM into :class:`Terminated` (a KeyboardInterrupt) in the main thread;
    later ones are ignored while the run cleans up (SLURM follows with SIGKILL after KillWait).
    Returns a function that puts the previous handler back."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    fired = []

    def _term(signum, frame):
        if not fired:
            fired.append(signum)
            raise Terminated()

    old = signal.signal(signal.SIGTERM, _term)
    return lambda: signal.signal(signal.SIGTERM, old)


def _warm_up(solver, plan: Plan, remote) -> None:
    """Compile the forward model's forms before the first sample.  Local workers share this
    machine's JIT cache: compile once here, with the base inclusion, not a sampled one (a sample
    whose geometry fails must fail as a sample, not stop the sweep); if the warm-up itself fails the
    workers compile on first use.  Remote workers have their own caches (node-local on SLURM): a
    worker plugin warms each worker once, now for those present and later for every one that joins."""
    if remote is None:
        try:
            jobs.warmup(solver, plan.base)
        except Exception as exc:
            print(
                f"warning: solver warm-up failed ({type(exc).__name__}: {exc}); workers will compile "
                "the forms themselves",
                file=sys.stderr,
            )
    elif solver is None or hasattr(solver, "warmup"):
        from .cluster import WarmUpWorkers

        plugin = WarmUpWorkers(functools.partial(jobs.warmup, solver), plan.base.to_dict())
        remote[0].register_plugin(plugin, name="elastimap-warmup")


def _progress_bar(total: int, progress: bool):
    """The sweep's tqdm bar on stderr: every 0.5 s on a terminal, every 15 s into a log; a
    pseudo-terminal of size 0x0 (some CI runners, `script`) gets a fixed width, or tqdm would print
    nothing."""
    from tqdm import tqdm

    tty = sys.stderr.isatty()
    try:
        size = os.get_terminal_size(sys.stderr.fileno())
    except (OSError, ValueError):
        size = os.terminal_size((0, 0))
    sized = size.columns > 0 and size.lines > 0
    return tqdm(
        total=total,
        desc="sweep",
        unit="sample",
        file=sys.stderr,
        disable=not progress,
        mininterval=0.5 if tty else 15.0,
        dynamic_ncols=sized,
        ncols=None if sized else 100,
        nrows=None if sized else 50,
        smoothing=0.1,
    )


class _Tally:
    """The fan-out's count of landed summaries: ``summary``'s done/ok/failed, the errors, the solve
    seconds, the progress bar, and a compaction of the row files every ``cfg.batch_rows`` rows."""

    def __init__(self, summary: dict, cfg: SweepConfig, plan: Plan, bar):
        self.summary, self.cfg, self.plan, self.bar = summary, cfg, plan, bar
        self.errors: list[tuple[str, str]] = []
        self.solve_seconds = 0.0
        self.since_compact = 0

    def add(self, r: dict) -> None:
        s = self.summary
        s["done"] += 1
        if r["status"] == "ok":
            s["ok"] += 1
            self.solve_seconds += r["seconds"] if math.isfinite(r["seconds"]) else 0.0
        else:
            s["failed"] += 1
            self.errors.append((r["sample_id"], r["error"]))
        self.bar.set_postfix(ok=s["ok"], failed=s["failed"], refresh=False)
        self.bar.update(1)
        self.since_compact += 1
        if self.cfg.compact and self.since_compact >= self.cfg.batch_rows:
            io.compact(self.plan.out, self.cfg.batch_rows, only_rows=True)
            self.since_compact = 0

    def close(self, fan_wall: float, driver_cpu: float) -> None:
        """The fan-out's timings: its wall, the driver's CPU a sample, the mean solve, the workers' use."""
        self.bar.close()
        s = self.summary
        s["fan_out_s"] = fan_wall
        s["driver_cpu_ms_per_sample"] = 1000.0 * driver_cpu / max(s["done"], 1)
        s["mean_solve_s"] = self.solve_seconds / s["ok"] if s["ok"] else float("nan")
        if fan_wall > 0 and s["ok"]:
            s["worker_utilisation"] = self.solve_seconds / (fan_wall * max(s["workers"], 1))


def _fan_out(cfg: SweepConfig, plan: Plan, todo: list[dict], summary: dict, remote=None) -> None:
    from distributed import as_completed

    base = plan.base.to_dict()
    out = str(plan.out.resolve())
    solver = cfg.solver
    t0 = time.perf_counter()
    _warm_up(solver, plan, remote)
    summary["warmup_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    client, cluster = remote if remote is not None else _start_client(cfg)
    summary["cluster_start_s"] = time.perf_counter() - t0
    summary["workers"] = len(client.scheduler_info(n_workers=-1)["workers"]) if cluster is None else cfg.jobs
    tally = _Tally(summary, cfg, plan, _progress_bar(len(todo), cfg.progress))
    try:
        t_fan = time.perf_counter()
        cpu0 = time.process_time()
        token = uuid.uuid4().hex[:8]
        # one map call: the whole batch reaches the scheduler at once, as one task group, so dask
        # queues it and hands each one-thread worker one task at a time (worker-saturation 1.0); a
        # task is one sample, or the samples of one geometry (``--moduli-per-mesh``, jobs.group_samples)
        groups = jobs.group_samples(todo)
        futures = client.map(
            jobs.run_group,
            groups,
            base=base,
            out_dir=out,
            timeout=cfg.timeout or None,
            solver=solver,
            key=[f"sweep-task-{i:07d}-{token}" for i in range(len(groups))],
            pure=False,
        )
        by_future = dict(zip(futures, groups))
        resubmitted: dict[str, int] = {}
        submit = functools.partial(
            client.submit, jobs.run_group, base=base, out_dir=out, timeout=cfg.timeout or None, solver=solver
        )
        pending = as_completed(list(by_future))
        watch = _WorkerWatch(client, cfg, cluster is not None)
        while not pending.is_empty():
            # every turn, not only when idle: nothing below may keep the driver from the watch
            watch.check()  # raises ClusterLost after --worker-wait s with no worker
            ready = pending.next_batch(block=False) if pending.has_ready() else []
            if not ready:
                time.sleep(0.05)
                continue
            for fut in ready:
                group = by_future.pop(fut)
                try:
                    # bounded: a result held by a worker that is gone before it is read makes an
                    # unbounded result() wait for a recompute that, with no worker left, never comes
                    results = fut.result(timeout=watch.fetch_timeout)
                except Exception as exc:  # KilledWorker (its worker died on every attempt) or a bug in the job
                    if _not_failed(fut, exc):
                        # not the task's error: its result was lost with its worker (dask runs it
                        # again when a worker joins), or fetching it took too long; wait for it
                        # again, with the watch in between
                        by_future[fut] = group
                        pending.add(fut)
                        continue
                    fut.release()
                    results = _task_failed(group, exc, out, base, solver, resubmitted, submit, by_future, pending)
                else:
                    fut.release()
                for r in results:
                    tally.add(r)
        tally.close(time.perf_counter() - t_fan, time.process_time() - cpu0)
    except ClusterLost:
        # nothing of this run stays queued on the scheduler: release() only posts a message,
        # where cancel() would wait for the answer of a scheduler that may be what is gone
        for fut in by_future:
            fut.release()
        raise
    finally:
        summary["errors"] = tally.errors
        if cluster is not None:  # a local cluster is ours to stop; a remote client is closed by run()
            try:
                client.close()
            finally:
                cluster.close()


def _task_failed(group, exc, out, base, solver, resubmitted, submit, by_future, pending) -> list[dict]:
    """The summaries of a task that failed with ``exc`` (KilledWorker: its worker died on every
    attempt; or a bug in the job): a sample it landed before is done; a sample its worker died at
    twice (started twice, not landed) is recorded failed; every other one runs again alone
    (``submit([sample])``, at most three times: dask blames every task a dying worker held)."""
    name = type(exc).__name__
    results = []
    # a task of several samples: those it landed before its worker died are done
    landed = io.landed_status(out) if len(group) > 1 else {}
    for s in group:
        sid = s["sample_id"]
        if sid in landed:
            results.append({"sample_id": sid, "status": landed[sid], "seconds": math.nan, "error": ""})
            continue
        n_started = jobs.attempts(out, sid)
        if name == "KilledWorker" and n_started < 2 and resubmitted.get(sid, 0) < 3:
            resubmitted[sid] = resubmitted.get(sid, 0) + 1
            again = submit([s], key=f"sweep-retry-{uuid.uuid4().hex}", pure=False)
            by_future[again] = [s]
            pending.add(again)
            continue
        tries = f"all {n_started} attempts" if n_started > 1 else f"{n_started} attempt(s)"
        msg = (
            f"worker crashed on {tries} at this sample (segfault, abort, out of memory, or a worker job ended): {name}"
            if name == "KilledWorker"
            else f"{name}: {exc}"
        )
        jobs.land_failure(s, base, out, msg[:2000], solver)
        results.append({"sample_id": sid, "status": "failed", "seconds": float("nan"), "error": msg})
    return results


def _not_failed(fut, exc: BaseException) -> bool:
    """Whether ``fut.result()`` raised ``exc`` for want of a worker, not because the task failed:
    the future is ``lost`` or ``pending`` again (its result went with its worker before it was
    read; dask runs the task again when a worker joins), or it is ``finished`` and the fetch of
    its result ran past its time limit."""
    return fut.status in ("lost", "pending") or (fut.status == "finished" and isinstance(exc, TimeoutError))


class _WorkerWatch:
    """Counts the cluster's workers every few seconds while the driver waits for results; raises
    :class:`ClusterLost` once there has been none for ``cfg.worker_wait`` seconds.

    Nothing in the collect loop waits without a bound, so the loop is back at :meth:`check` soon
    after the last worker goes, whatever it was waiting on: a result's fetch waits at most
    ``fetch_timeout`` s, the count at most ``count_timeout`` s.  The count's bound is never
    below the wait (nor 10 s): one slow answer of a busy scheduler is not a lost cluster; a
    scheduler that does not answer at all ends the run after about ``count_timeout`` + ``every``."""

    COUNT_TIMEOUT = 10.0  # s, at least, for the scheduler to say how many workers it has
    FETCH_TIMEOUT = 10.0  # s, at most, for one result's fetch (a late one is fetched again)

    def __init__(self, client, cfg: SweepConfig, local: bool):
        self.client, self.wait = client, cfg.worker_wait
        self.where = "in the local cluster" if local else f"at {cfg.scheduler}"
        self.every = min(2.0, self.wait / 4)
        self.count_timeout = max(self.wait, self.COUNT_TIMEOUT)
        self.fetch_timeout = max(1.0, min(self.wait, self.FETCH_TIMEOUT))
        self.last_seen = self.next_check = time.monotonic()

    def check(self) -> None:
        from .cluster import count_workers

        if time.monotonic() < self.next_check:
            return
        n = count_workers(self.client, self.count_timeout)
        now = time.monotonic()
        self.next_check = now + self.every
        if n:
            self.last_seen = now
        elif now - self.last_seen >= self.wait:
            why = "the scheduler does not answer" if n is None else "all workers gone: wall time, scancel, lost nodes?"
            raise ClusterLost(
                f"no dask worker {self.where} for {self.wait:g} s ({why}); landed rows are kept: "
                "rerun the same command to resume when the cluster has workers (--worker-wait to wait longer)"
            )


def format_summary(s: dict) -> str:
    lines = [
        f"sweep: {s['out']}: {s['done']} done this run (ok {s['ok']}, failed {s['failed']}), "
        f"{s['skipped']} skipped (already landed), wall {s['wall_s']:.1f} s, "
        f"{s['samples_per_min']:.1f} samples/min"
    ]
    if s["done"]:
        extra = [f"warm-up {s.get('warmup_s', 0):.1f} s", f"cluster start {s.get('cluster_start_s', 0):.1f} s"]
        if s.get("mean_solve_s") == s.get("mean_solve_s") and "mean_solve_s" in s:
            extra.append(f"mean solve {s['mean_solve_s']:.2f} s")
        if "worker_utilisation" in s:
            extra.append(f"worker utilisation {100 * s['worker_utilisation']:.0f} %")
        extra.append(f"driver CPU {s.get('driver_cpu_ms_per_sample', 0):.1f} ms/sample")
        lines.append("       " + ", ".join(extra))
    held = s.get("folder_ok", 0) + s.get("folder_failed", 0)
    lines.append(
        f"       dataset: the folder holds {held} samples: {s.get('folder_ok', 0)} ok, "
        f"{s.get('folder_failed', 0)} failed; of this command's {s['planned']} planned: "
        f"{s['dataset_ok']} ok, {s['dataset_failed']} failed, {s['missing']} missing"
    )
    for sid, err in s.get("errors", [])[:10]:
        lines.append(f"       failed {sid}: {err[:200]}")
    if len(s.get("errors", [])) > 10:
        lines.append(f"       ... and {len(s['errors']) - 10} more (dataset inspect {s['out']})")
    if s["dataset_failed"]:
        lines.append("       rerun with --retry-failed to run the failed samples again")
    return "\n".join(lines)
