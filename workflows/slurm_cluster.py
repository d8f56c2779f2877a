"""Start a dask cluster on SLURM (dask-jobqueue), keep it at --workers, publish its address.

Needs the optional extra:  make slurm   (installs dask-jobqueue into .venv with uv)

    python workflows/slurm_cluster.py --workers 32 --partition compute --walltime 04:00:00 \\
        --address-file scheduler.address &
    # wait for the file (it appears only once the scheduler is up and a worker has joined):
    while [ ! -s scheduler.address ]; do kill -0 $! || exit 1; sleep 2; done
    elastimap sweep run --n 4096 --mesh default --out /shared/sweeps/big --scheduler "$(cat scheduler.address)"

One SLURM job per dask worker, one core and one thread per worker (one solve at a time each).
The cluster is kept at --workers jobs: a worker job that ends (wall time, scancel, a lost node)
is replaced by a new one.  Each worker retires on its own shortly before its wall time
(``--lifetime``, staggered), so that its sample is handed back instead of being killed mid-solve.
The address file is written (atomically) once the scheduler is up and --wait-workers workers have
joined, and removed when the cluster stops; a stale file from an earlier run is removed at start.
The process keeps the cluster alive until Ctrl-C / SIGTERM (scancel) and then cancels the worker
jobs.  Nothing here is imported by the package or its tests.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time

import dask


def _seconds(walltime: str) -> int:
    """SLURM's [D-]HH:MM:SS, HH:MM:SS, MM:SS or MM as seconds."""
    days = 0
    if "-" in walltime:
        d, walltime = walltime.split("-", 1)
        days = int(d)
    parts = [int(p) for p in walltime.split(":")]
    if len(parts) == 1:
        h, m, s = 0, parts[0], 0
    elif len(parts) == 2:
        h, (m, s) = 0, parts
    else:
        h, m, s = parts[-3:]
    return ((days * 24 + h) * 60 + m) * 60 + s


def _parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workers", type=int, default=8, help="dask workers = SLURM jobs (one core each), kept up")
    ap.add_argument("--partition", default=None, help="SLURM partition (queue)")
    ap.add_argument("--account", default=None, help="SLURM account")
    ap.add_argument("--walltime", default="04:00:00", help="wall time of each worker job ([D-]HH:MM:SS)")
    ap.add_argument("--memory", default="4GiB", help="memory per worker (a default-mesh solve needs < 1.5 GiB)")
    ap.add_argument(
        "--venv",
        default=os.environ.get("VIRTUAL_ENV", ".venv"),
        help="virtual environment the workers activate (must be on a shared filesystem)",
    )
    ap.add_argument(
        "--address-file", default="scheduler.address", help="written once the cluster is up, removed when it stops"
    )
    ap.add_argument(
        "--wait-workers",
        type=int,
        default=1,
        help="workers that must have joined before the address file is written (0: scheduler only)",
    )
    ap.add_argument("--log-dir", default=None, help="folder for the worker jobs' SLURM logs (default: SLURM's)")
    ap.add_argument("--dashboard", default=":8787", help="dashboard address (':0' for any free port)")
    ap.add_argument(
        "--interface",
        default=None,
        help="network interface the scheduler and the workers listen on (e.g. ib0; lo keeps a one-node check on loopback)",
    )
    return ap.parse_args()


def _make_cluster(args: argparse.Namespace, wall: int):
    """The SLURMCluster: one job per worker, one core and one thread each, retiring before its
    wall time; its scheduler (in this process) has the sweep's retry policy."""
    from dask_jobqueue import SLURMCluster  # optional extra 'slurm' (make slurm)

    # Retire each worker before SLURM kills it: a gracefully closing worker hands its task back
    # without counting it as a crash.  Leave 1/6 of the wall time (at most 5 min) and stagger by
    # up to a third of that, so that workers started together do not all leave together.
    margin = min(300, max(10, wall // 6))
    lifetime = ["--lifetime", f"{max(wall - margin, 10)}s", "--lifetime-stagger", f"{max(margin // 3, 1)}s"]

    # The scheduler lives in this process: give it the sweep's retry policy (a sample whose
    # worker dies is retried once, then reported to the driver as KilledWorker and recorded failed).
    # worker-saturation 1.0: a worker holds only the task it runs, so a crash blames only that sample.
    # lost-worker-timeout: how soon a worker whose job ended is forgotten, and so replaced (default 15 s).
    dask.config.set(
        {
            "distributed.scheduler.allowed-failures": 1,
            "distributed.scheduler.worker-saturation": 1.0,
            "distributed.deploy.lost-worker-timeout": "5s",
        }
    )
    return SLURMCluster(
        cores=1,
        processes=1,
        interface=args.interface,
        memory=args.memory,
        walltime=args.walltime,
        queue=args.partition,
        account=args.account,
        log_directory=args.log_dir,
        job_script_prologue=[
            f"source {os.path.abspath(args.venv)}/bin/activate",
            "export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1",
            # each node compiles the DOLFINx forms into its own cache unless HOME is shared;
            # a node-local cache avoids NFS locking trouble:
            'export XDG_CACHE_HOME="${TMPDIR:-/tmp}/elastimap-cache-${USER:-$(id -un)}"',
        ],
        worker_extra_args=lifetime,
        scheduler_options={"dashboard_address": args.dashboard},
    )


def _write_address(cluster, address_file: str) -> None:
    """The scheduler's address into ``address_file``, atomically (a reader never sees half a line)."""
    tmp = f"{address_file}.{os.getpid()}.tmp"
    with open(tmp, "w") as fh:
        fh.write(cluster.scheduler_address + "\n")
    os.replace(tmp, address_file)


def _remove_address(cluster, address_file: str) -> None:
    """Remove ``address_file`` if it still holds this cluster's address (not a later run's)."""
    try:
        with open(address_file) as fh:
            mine = fh.read().strip() == cluster.scheduler_address
        if mine:
            os.unlink(address_file)
    except FileNotFoundError:
        pass


def _keep_up(cluster, args: argparse.Namespace, address_file: str, stop: list) -> None:
    """Keep the cluster at ``--workers`` jobs until ``stop`` is set (SIGTERM) or Ctrl-C; write
    the address once ``--wait-workers`` have joined."""
    t0 = time.monotonic()
    last_note = t0
    jobs = {}  # worker name -> SLURM job id
    written = False
    while not stop:
        n = len(cluster.scheduler_info.get("workers", {}))
        if not written and n >= args.wait_workers:
            _write_address(cluster, address_file)
            written = True
            print(
                f"{n} worker(s) joined after {time.monotonic() - t0:.0f} s; address written to "
                f"{address_file}; Ctrl-C or SIGTERM stops the cluster",
                flush=True,
            )
        # SpecCluster forgets a worker whose job ended (after distributed.deploy.lost-worker-timeout)
        # but keeps it in its spec: scale() opens a new job for every such name.
        cluster.scale(jobs=args.workers)
        time.sleep(5)
        now = time.monotonic()
        new = {name: getattr(w, "job_id", None) for name, w in list(cluster.workers.items())}
        replaced = [f"job {jobs[k]} by job {v}" for k, v in new.items() if jobs.get(k) and v and v != jobs[k]]
        jobs.update({k: v for k, v in new.items() if v})
        if replaced or now - last_note > 300:
            print(
                f"[{time.strftime('%H:%M:%S')}] {n} worker(s) joined, {len(new)} job(s)"
                + (f"; replaced {', '.join(replaced)}" if replaced else ""),
                flush=True,
            )
            last_note = now


def main() -> int:
    args = _parse_args()
    if args.workers < 1 or not 0 <= args.wait_workers <= args.workers:
        print("error: --workers must be >= 1 and --wait-workers in [0, --workers]", file=sys.stderr)
        return 2
    try:
        wall = _seconds(args.walltime)
    except ValueError:
        print(f"error: --walltime: expected [D-]HH:MM:SS (got {args.walltime!r})", file=sys.stderr)
        return 2

    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    address_file = os.path.abspath(args.address_file)
    if os.path.exists(address_file):
        os.unlink(address_file)  # an earlier run's address must never be read as this one's
    cluster = _make_cluster(args, wall)
    try:
        cluster.scale(jobs=args.workers)
        print(
            f"scheduler {cluster.scheduler_address}  (dashboard {cluster.dashboard_link}); "
            f"{args.workers} worker job(s) submitted",
            flush=True,
        )
        print(cluster.job_script(), flush=True)
        _keep_up(cluster, args, address_file, stop)
    except KeyboardInterrupt:
        pass
    finally:
        _remove_address(cluster, address_file)  # only if it holds this cluster's address
        cluster.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
