"""Start a dask cluster on SLURM (dask-jobqueue) and print its scheduler address.

Needs the optional extra:  pip install -e '.[slurm]'   (dask-jobqueue)

    python workflows/slurm_cluster.py --workers 32 --partition compute --walltime 04:00:00 &
    # prints: scheduler tcp://10.0.0.12:8786  (and writes it to scheduler.address)
    sweep run --n 4096 --mesh default --out /shared/sweeps/big --scheduler "$(cat scheduler.address)"

One SLURM job per dask worker, one core and one thread per worker (one solve at
a time each).  The process keeps the cluster alive until it is interrupted
(Ctrl-C / scancel) and then cancels the worker jobs.  Nothing here is imported
by the package or its tests.
"""

from __future__ import annotations

import argparse
import os
import signal
import time

import dask


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workers", type=int, default=8, help="dask workers = SLURM jobs (one core each)")
    ap.add_argument("--partition", default=None, help="SLURM partition (queue)")
    ap.add_argument("--account", default=None, help="SLURM account")
    ap.add_argument("--walltime", default="04:00:00", help="wall time of each worker job")
    ap.add_argument("--memory", default="4GiB", help="memory per worker (a default-mesh solve needs < 1.5 GiB)")
    ap.add_argument("--venv", default=os.environ.get("VIRTUAL_ENV", ".venv"),
                    help="virtual environment the workers activate (must be on a shared filesystem)")
    ap.add_argument("--address-file", default="scheduler.address")
    args = ap.parse_args()

    from dask_jobqueue import SLURMCluster  # optional extra 'slurm'

    # The scheduler lives in this process: give it the sweep's retry policy (a sample whose
    # worker dies is retried once, then reported to the driver as KilledWorker and recorded failed).
    # worker-saturation 1.0: a worker holds only the task it runs, so a crash blames only that sample.
    dask.config.set({"distributed.scheduler.allowed-failures": 1, "distributed.scheduler.worker-saturation": 1.0})
    cluster = SLURMCluster(
        cores=1, processes=1, memory=args.memory, walltime=args.walltime,
        queue=args.partition, account=args.account,
        job_script_prologue=[
            f"source {os.path.abspath(args.venv)}/bin/activate",
            "export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1",
            # each node compiles the DOLFINx forms into its own cache unless HOME is shared;
            # a node-local cache avoids NFS locking trouble:
            'export XDG_CACHE_HOME="${TMPDIR:-/tmp}/elastimap-cache-$USER"',
        ],
        worker_extra_args=["--nthreads", "1"],
        scheduler_options={"dashboard_address": ":8787"},
    )
    cluster.scale(jobs=args.workers)
    with open(args.address_file, "w") as fh:
        fh.write(cluster.scheduler_address + "\n")
    print(f"scheduler {cluster.scheduler_address}  (dashboard {cluster.dashboard_link})", flush=True)
    print(f"address written to {args.address_file}; Ctrl-C to stop the cluster", flush=True)
    print(cluster.job_script(), flush=True)

    stop = False

    def _stop(*_):
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, _stop)
    try:
        while not stop:
            time.sleep(5)
    except KeyboardInterrupt:
        pass
    finally:
        cluster.close()


if __name__ == "__main__":
    main()
