"""The driver's side of an external dask scheduler: a bounded connect, a worker count, a warm-up
that runs on every worker when it joins.

* :func:`connect` asks the address for its identity before a :class:`distributed.Client` is made,
  inside one deadline: a port that is no dask scheduler (a dashboard, a plain TCP listener) or no
  answer at all ends as one :class:`~elastimap.errors.UserError` naming the ``scheduler``
  parameter (``--scheduler`` on the command line) instead of a hang (dask's own handshake waits
  for a reply with no time limit).
* :func:`count_workers` is what the driver polls while it waits for results, to notice a cluster
  that has lost every worker (wall time, ``scancel``) instead of waiting for ever.
* :func:`local_cluster` is the cluster of a sweep without ``--scheduler``: worker processes on this
  machine, the scheduler on the loopback interface, the dashboard off unless asked for
  (``--dashboard``), workers that leave Ctrl-C to the driver (:func:`dask_setup`).
* :class:`WarmUpWorkers` is a dask worker plugin: registered on the scheduler, it runs the solver's
  warm-up once in every worker, also in workers that join later (a replacement SLURM
  job), so the first sample of a fresh worker does not pay the form compile.

Imported only by the driver (it imports ``distributed``).
"""

from __future__ import annotations

import asyncio
import logging
import signal
import socket
import sys
import threading
from collections.abc import Callable

from distributed.diagnostics.plugin import WorkerPlugin

from elastimap.errors import UserError
from elastimap.solver.params import SolveParams

log = logging.getLogger(__name__)


async def _identity(address: str, timeout: float) -> object:
    from distributed.comm import connect as comm_connect

    comm = await comm_connect(address, timeout=timeout)
    try:
        await comm.write({"op": "identity", "reply": True})
        return await comm.read()
    finally:
        comm.abort()


def _port_open(address: str, timeout: float) -> bool | None:
    """Whether a TCP connection to ``address`` is accepted (``None``: not a TCP address)."""
    from distributed.comm.addressing import parse_address, parse_host_port

    scheme, loc = parse_address(address)
    if scheme not in ("tcp", "tls"):
        return None
    host, port = parse_host_port(loc)
    try:
        socket.create_connection((host, port), timeout=timeout).close()
        return True
    except OSError:
        return False


def check_scheduler(address: str, timeout: float) -> None:
    """Raise ``UserError("scheduler", ...)`` unless a dask scheduler answers at ``address`` within ``timeout`` s."""
    try:
        reply = asyncio.run(asyncio.wait_for(_identity(address, timeout), timeout))
    except ValueError as exc:
        raise UserError("scheduler", f"{address!r} is not an address like tcp://host:8786 ({exc})") from None
    except (TimeoutError, OSError):
        try:
            open_ = _port_open(address, min(timeout, 5.0))
        except Exception:  # an address dask parsed but we cannot: say what we know
            open_ = None
        if open_:
            raise UserError(
                "scheduler",
                f"{address} accepts connections, but is not a dask scheduler (no dask "
                f"answer within {timeout:g} s; a dashboard or another service?)",
            ) from None
        raise UserError(
            "scheduler",
            f"no dask scheduler answered at {address} within {timeout:g} s (is it running? is the address current?)",
        ) from None
    except Exception as exc:  # garbage on the wire: an HTTP server, another protocol
        raise UserError(
            "scheduler",
            f"{address} answers, but is not a dask scheduler "
            f"({type(exc).__name__} reading its reply; a dashboard port?)",
        ) from None
    kind = reply.get("type") if isinstance(reply, dict) else None
    if kind != "Scheduler":
        raise UserError(
            "scheduler", f"{address} answers, but is not a dask scheduler (it is a {kind or 'foreign service'})"
        )


def connect(address: str, timeout: float):
    """A :class:`distributed.Client` of the scheduler at ``address`` (checked first, see :func:`check_scheduler`)."""
    from distributed import Client

    check_scheduler(address, timeout)
    try:
        return Client(address, timeout=f"{timeout}s")
    except Exception as exc:
        raise UserError("scheduler", f"cannot connect to {address} ({type(exc).__name__}: {exc})") from None


def local_cluster(jobs: int, dashboard: str | None = None):
    """A :class:`distributed.LocalCluster` of ``jobs`` one-thread worker processes on this machine.

    Its scheduler listens on 127.0.0.1 only.  The dashboard (an unauthenticated web page that shows
    and can stop the sweep's tasks) is off unless ``dashboard`` names an address
    (``--dashboard``): ``127.0.0.1:8787`` keeps it on this machine, ``:8787`` opens it to the
    network (it needs the ``bokeh`` package).  Every worker runs :func:`dask_setup` first (ignores SIGINT)."""
    from distributed import LocalCluster

    cluster = LocalCluster(
        n_workers=jobs,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        # without a dashboard the scheduler still serves /health and /metrics: on loopback, a free port
        dashboard_address=dashboard or "127.0.0.1:0",
        scheduler_kwargs={"dashboard": dashboard is not None},
        silence_logs=logging.CRITICAL,
        preload=[__name__],
    )
    if dashboard is not None:
        print(f"dask dashboard (no login): {cluster.dashboard_link}", file=sys.stderr)
    return cluster


def dask_setup(worker) -> None:
    """Run by dask in each local worker process as it starts (``preload``): ignore SIGINT.

    Ctrl-C reaches the whole process group; the driver catches it, keeps the landed rows and stops
    the cluster.  A worker that took it as well printed a traceback of its event loop."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def count_workers(client, timeout: float | None = None) -> int | None:
    """Workers the scheduler knows now; ``None`` when the scheduler does not answer (within
    ``timeout`` s; ``None``: no limit, a scheduler that hangs without closing the connection then
    blocks the caller)."""
    try:
        return len(client.nthreads(callback_timeout=timeout))
    except Exception:
        return None


def close_client(client, timeout: float) -> None:
    """Close ``client`` within ``timeout`` s (dask's default waits up to twice the connect
    timeout for a scheduler that may be gone); a close that fails or runs late is logged, not raised."""
    try:
        client.close(timeout=timeout)
    except Exception as exc:
        log.warning("closing the dask client: %s: %s", type(exc).__name__, exc)


class WarmUpWorkers(WorkerPlugin):
    """Run ``warm(SolveParams.from_dict(base))`` once in each worker, when it joins.

    ``warm`` is the warm-up of the solver the driver uses (e.g. ``elastimap.solver.warmup``, a tiny
    solve that compiles the forms into the worker's JIT cache); it travels to the workers pickled,
    so it must be importable there (a module-level function, or a ``functools.partial`` of one).
    ``base`` is the sweep's base parameters as a dict.  The warm-up runs in a thread so that the
    worker keeps answering the scheduler meanwhile; a failing warm-up is logged and the worker
    compiles on its first sample instead.
    """

    idempotent = False

    def __init__(self, warm: Callable[[SolveParams], object], base: dict):
        self.warm = warm
        self.base = base

    def _warm(self) -> None:
        self.warm(SolveParams.from_dict(self.base))

    async def setup(self, worker) -> None:
        try:
            await asyncio.to_thread(self._warm)
        except Exception as exc:  # the worker still works: it compiles on its first sample
            log.warning(
                "elastimap warm-up failed on %s: %s: %s", getattr(worker, "address", "?"), type(exc).__name__, exc
            )
