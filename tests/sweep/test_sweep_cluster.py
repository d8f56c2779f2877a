"""Sweep driver on the cluster path: design changes into an existing folder, bad scheduler
addresses, a cluster that loses every worker, SIGTERM, foreign locks, per-worker warm-up.

Every dask cluster here lives on 127.0.0.1 (a ``LocalCluster`` started by the test or by the
driver); the solves are the SYNTHETIC stand-in of :mod:`elastimap.solver.synthetic`, passed with
the hidden option ``--solver synthetic[:...]`` (it travels to the workers with every task, so it
also reaches the workers of an external scheduler).  The real SLURM path is exercised by
``workflows/slurm_check.sh`` (see docs/sweep.md), not by this file.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from sweep_helpers import ROOT, run_sweep
from sweep_helpers import sweep_env as _env
from sweep_helpers import synthetic as _synthetic

from elastimap.dataset import io
from elastimap.sweep.cli import main as sweep_main


def _sweep(args, env=None, timeout=180):
    return run_sweep(args, env=env, timeout=timeout)


def _popen(args, env=None):
    return subprocess.Popen(
        [sys.executable, "-m", "elastimap.sweep.cli", *args],
        env=env or _env(),
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )


def _cli(args, capsys):
    with pytest.raises(SystemExit) as e:
        sweep_main(args)
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


def _snapshot(path: Path) -> dict:
    return {p.name: p.read_bytes() for p in sorted(path.iterdir())}


def _wait_rows(out: Path, k: int, proc, timeout=90) -> None:
    t0 = time.time()
    while time.time() - t0 < timeout:
        if len(io.landed_status(out)) >= k if out.is_dir() else False:
            return
        if proc.poll() is not None:
            raise AssertionError(f"sweep ended early: {proc.communicate()}")
        time.sleep(0.2)
    raise AssertionError("no rows landed in time")


# ----------------------------------------------------------------------------- another design, --append


def test_other_design_into_existing_out_refused_unless_append(tmp_path, capsys):
    out = tmp_path / "ds"
    base = ["run", *_synthetic(), "--mesh", "tiny", "--jobs", "1", "--no-progress", "--out", str(out)]
    r = _sweep([*base, "--n", "4", "--seed", "0"])
    assert r.returncode == 0, r.stderr
    before = _snapshot(out)
    for extra, flag in [
        (["--n", "4", "--seed", "1"], "--seed"),
        (["--n", "5", "--seed", "0"], "--n"),
        (["--n", "4", "--seed", "0", "--design", "sobol"], "--design"),
        (["--n", "4", "--seed", "0", "--ranges", "E=20:100"], "--ranges"),
        (["--n", "4", "--seed", "0", "--phantoms"], "--phantoms"),
    ]:
        code, _, err = _cli([*base, *extra], capsys)
        assert code == 2 and err.count("\n") == 1 and err.startswith("error: --out:"), (extra, err)
        assert flag in err and "--append" in err, (extra, err)
        assert _snapshot(out) == before, extra  # nothing written, not even the lock
    # the same design resumes (nothing to do)
    code, stdout, err = _cli([*base, "--n", "4", "--seed", "0"], capsys)  # nothing to run: no cluster starts
    assert code == 0 and "0 done this run" in stdout, stdout + err
    # --append extends the folder and says so in the manifest; the summary counts the whole folder
    r = _sweep([*base, "--n", "4", "--seed", "1", "--append"])
    assert r.returncode == 0, r.stderr
    assert "4 done this run (ok 4, failed 0)" in r.stdout
    assert "folder holds 8 samples: 8 ok, 0 failed" in r.stdout, r.stdout
    man = io.read_manifest(out)
    assert len(man["planned"]) == 8 and man["runs"][-1]["append"] is True
    assert [(d["seed"], d["n"]) for d in man["designs"]] == [(0, 4), (1, 4)]
    # after the append either design resumes without --append
    code, stdout, err = _cli([*base, "--n", "4", "--seed", "0"], capsys)
    assert code == 0 and "4 skipped" in stdout and "folder holds 8 samples" in stdout, stdout + err


# ----------------------------------------------------------------------------- bad scheduler addresses


@pytest.mark.parametrize("addr", ["", "   "])
def test_empty_scheduler_is_an_error_not_a_local_cluster(tmp_path, capsys, addr):
    out = tmp_path / "ds"
    code, _, err = _cli(
        ["run", *_synthetic(), "--n", "2", "--mesh", "tiny", "--out", str(out), "--scheduler", addr], capsys
    )
    assert code == 2 and err.count("\n") == 1 and err.startswith("error: --scheduler:"), err
    assert not out.exists()


@pytest.fixture
def silent_listener():
    """A TCP port on 127.0.0.1 that accepts connections and never answers (not a dask scheduler)."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    conns = []
    stop = threading.Event()

    def accept():
        srv.settimeout(0.2)
        while not stop.is_set():
            try:
                conns.append(srv.accept()[0])
            except OSError:
                pass

    t = threading.Thread(target=accept, daemon=True)
    t.start()
    yield f"tcp://127.0.0.1:{srv.getsockname()[1]}"
    stop.set()
    t.join()
    for c in conns:
        c.close()
    srv.close()


def test_scheduler_that_never_answers_fails_within_the_connect_timeout(tmp_path, silent_listener):
    out = tmp_path / "ds"
    t0 = time.time()
    r = _sweep(
        [
            "run",
            *_synthetic(),
            "--n",
            "2",
            "--mesh",
            "tiny",
            "--out",
            str(out),
            "--scheduler",
            silent_listener,
            "--connect-timeout",
            "3",
        ],
        timeout=60,
    )
    took = time.time() - t0
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and r.stderr.startswith("error: --scheduler:") and silent_listener in r.stderr
    assert "not a dask scheduler" in r.stderr
    assert "Traceback" not in r.stderr and not out.exists()
    assert took < 45, took  # --connect-timeout 3 s, plus start-up on a loaded machine; without the check it hangs


def test_http_port_is_not_a_scheduler(tmp_path, capsys):
    import http.server

    class Quiet(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args):
            pass

    srv = http.server.HTTPServer(("127.0.0.1", 0), Quiet)
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    try:
        addr = f"tcp://127.0.0.1:{srv.server_address[1]}"
        code, _, err = _cli(
            [
                "run",
                *_synthetic(),
                "--n",
                "2",
                "--mesh",
                "tiny",
                "--out",
                str(tmp_path / "ds"),
                "--scheduler",
                addr,
                "--connect-timeout",
                "3",
            ],
            capsys,
        )
    finally:
        srv.shutdown()
    assert code == 2 and err.count("\n") == 1 and "not a dask scheduler" in err, err
    assert not (tmp_path / "ds").exists()


# ----------------------------------------------------------------------------- a cluster that loses its workers


def test_driver_notices_when_every_worker_is_gone(tmp_path):
    from distributed import LocalCluster

    out = tmp_path / "ds"
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        proc = _popen(
            [
                "run",
                *_synthetic(seconds=0.3),
                "--n",
                "40",
                "--mesh",
                "tiny",
                "--out",
                str(out),
                "--no-progress",
                "--scheduler",
                cluster.scheduler_address,
                "--worker-wait",
                "3",
            ],
        )
        try:
            _wait_rows(out, 2, proc)
            cluster.scale(0)
            t_gone = time.time()
            stdout, stderr = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
    noticed = time.time() - t_gone
    assert proc.returncode == 3, stderr
    assert "no dask worker" in stderr and "3 s" in stderr, stderr
    assert "done this run" in stdout and "folder holds" in stdout, stdout
    assert noticed < 30, noticed  # --worker-wait 3 s, plus the exit on a loaded machine
    assert not (out / io.LOCK).exists() and not list(out.glob(".attempts-*"))
    man = io.read_manifest(out)
    assert "no dask worker" in man["runs"][-1]["summary"]["aborted"]
    assert 2 <= len(io.landed_status(out)) < 40


def test_driver_notices_when_the_last_worker_goes_with_an_unread_result(tmp_path, monkeypatch):
    """The race behind a rare hang of the test above on a loaded machine: a sample finishes, and its
    worker, the last one, is gone before the driver reads the result (a busy driver reads late).
    The result is lost with the worker; dask waits for a recompute that needs a worker, so an
    unbounded ``result()`` never returns.  Here the worker goes exactly then, every time: the
    driver, run in this process, must still end the run as a lost cluster within --worker-wait."""
    import copy

    import dask
    from distributed import Future, LocalCluster

    from elastimap.sweep import jobs
    from elastimap.sweep.run import SweepConfig
    from elastimap.sweep.run import run as run_sweep_here

    out = tmp_path / "ds"
    saved_config = copy.deepcopy(dask.config.config)  # the driver sets dask options for its run
    real_result = Future.result
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        seen = {"reads": 0, "gone": None}

        def late_result(self, *args, **kwargs):
            seen["reads"] += 1
            if seen["reads"] == 3:  # a finished sample, not read yet: its (only) worker goes first
                cluster.scale(0)
                t0 = time.monotonic()
                while cluster.scheduler.workers and time.monotonic() - t0 < 30:
                    time.sleep(0.05)
                assert not cluster.scheduler.workers, "the worker did not go"
                seen["gone"] = time.monotonic()
            return real_result(self, *args, **kwargs)

        monkeypatch.setattr(Future, "result", late_result)
        cfg = SweepConfig(
            n=40,
            mesh="tiny",
            out=str(out),
            progress=False,
            scheduler=cluster.scheduler_address,
            worker_wait=3.0,
            solver=jobs.resolve_solver("synthetic:seconds=0.3"),
        )
        box: dict = {}
        driver = threading.Thread(target=lambda: box.update(summary=run_sweep_here(cfg)), daemon=True)
        try:
            driver.start()
            driver.join(timeout=60)
            ended = time.monotonic()
        finally:
            dask.config.config.clear()
            dask.config.config.update(saved_config)
        assert not driver.is_alive(), "the driver hangs on a result lost with the last worker"
    assert seen["gone"] is not None, seen
    summary = box["summary"]
    assert "no dask worker" in summary.get("aborted", ""), summary
    assert ended - seen["gone"] < 30, ended - seen["gone"]  # --worker-wait 3 s, + a bounded fetch + exit
    assert summary["ok"] == 2 and summary["dataset_ok"] >= 2, summary  # the lost one may have landed
    assert not (out / io.LOCK).exists() and not list(out.glob(".attempts-*"))


@pytest.fixture
def scheduler_process(tmp_path):
    """A dask scheduler and one one-thread worker in their own processes (so a test can freeze the
    scheduler with SIGSTOP); yields ``(address, scheduler Popen)``."""
    sfile = tmp_path / "scheduler.json"
    logs = open(tmp_path / "dask.log", "w")
    common = {"cwd": ROOT, "env": _env(), "stdout": logs, "stderr": subprocess.STDOUT}
    sched = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0"]
        + ["--no-dashboard", "--scheduler-file", str(sfile)],
        **common,
    )
    procs = [sched]
    try:
        t0 = time.time()
        while not (sfile.exists() and sfile.stat().st_size) and time.time() - t0 < 60:
            time.sleep(0.2)
        address = json.loads(sfile.read_text())["address"]
        worker = subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1"]
            + ["--no-dashboard", "--local-directory", str(tmp_path / "dw")],
            **common,
        )
        procs.append(worker)
        from distributed import Client

        with Client(address, timeout="60s") as c:  # the worker is there before the driver starts
            c.wait_for_workers(1, timeout=120)
        yield address, sched
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGCONT)
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        logs.close()


def test_driver_notices_a_scheduler_that_stops_answering(tmp_path, scheduler_process):
    """A scheduler that hangs with its connections open (SIGSTOP here; a frozen node) makes every
    unbounded call to it wait for ever: the driver must end as a lost cluster within --worker-wait,
    plus its bounded calls and a bounded client close."""
    address, sched = scheduler_process
    out = tmp_path / "ds"
    proc = _popen(
        ["run", *_synthetic(seconds=0.3), "--n", "40", "--mesh", "tiny", "--out", str(out), "--no-progress"]
        + ["--scheduler", address, "--worker-wait", "3"],
    )
    try:
        _wait_rows(out, 2, proc)
        sched.send_signal(signal.SIGSTOP)
        t_stop = time.time()
        stdout, stderr = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
    took = time.time() - t_stop
    assert proc.returncode == 3, stderr
    assert "no dask worker" in stderr and "scheduler does not answer" in stderr, stderr
    assert "done this run" in stdout, stdout
    # the count bound (10 s, above --worker-wait 3 s) + the client close (10 s), plus the exit under load
    assert took < 45, took
    assert not (out / io.LOCK).exists()


class _FakeScheduler:
    """A stand-in for ``distributed.Client`` in the worker watch: ``nthreads`` answers ``workers``
    after ``delay`` s, or, like dask, raises ``TimeoutError`` once ``callback_timeout`` has passed
    (``delay=None``: it never answers, a frozen scheduler)."""

    def __init__(self, workers: int, delay: float | None):
        self.workers, self.delay, self.calls = workers, delay, []

    def nthreads(self, callback_timeout=None):
        self.calls.append(callback_timeout)
        wait = self.delay if self.delay is not None else float("inf")
        if callback_timeout is not None and wait > callback_timeout:
            time.sleep(callback_timeout)
            raise TimeoutError(f"timed out after {callback_timeout} s")
        time.sleep(wait)
        return {f"tcp://w{i}": 1 for i in range(self.workers)}


def _watch(client, wait):
    from elastimap.sweep.run import SweepConfig, _WorkerWatch

    return _WorkerWatch(client, SweepConfig(scheduler="tcp://x:1", worker_wait=wait), local=False)


def _watch_until(watch, seconds):
    """Run ``watch.check()`` like the collect loop for ``seconds``; the ClusterLost and its time, or None."""
    from elastimap.sweep.run import ClusterLost

    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        try:
            watch.check()
        except ClusterLost as exc:
            return exc, time.monotonic() - t0
        time.sleep(0.05)
    return None


def test_worker_watch_a_slow_answer_is_not_a_lost_cluster():
    """A busy scheduler that answers slower than --worker-wait, with a worker, keeps the run going."""
    fake = _FakeScheduler(workers=1, delay=1.2)
    assert _watch_until(_watch(fake, wait=0.5), 4.0) is None
    assert len(fake.calls) >= 2 and all(t is not None and t >= 1.2 for t in fake.calls), fake.calls


def test_worker_watch_ends_on_no_worker_and_on_a_frozen_scheduler(monkeypatch):
    from elastimap.sweep.run import _WorkerWatch

    lost = _watch_until(_watch(_FakeScheduler(workers=0, delay=0.0), wait=0.5), 10.0)
    assert lost is not None and "all workers gone" in str(lost[0]) and "0.5 s" in str(lost[0])
    assert 0.5 <= lost[1] < 3.0, lost[1]
    monkeypatch.setattr(_WorkerWatch, "COUNT_TIMEOUT", 1.5)
    frozen = _FakeScheduler(workers=1, delay=None)
    lost = _watch_until(_watch(frozen, wait=0.5), 10.0)  # without a bound on the count: for ever
    assert lost is not None and "the scheduler does not answer" in str(lost[0]), lost
    assert 1.5 <= lost[1] < 4.0, lost[1]
    assert frozen.calls == [1.5]


# ----------------------------------------------------------------------------- SIGTERM, locks


def test_sigterm_like_ctrl_c_then_resume(tmp_path):
    out = tmp_path / "ds"
    args = [
        "run",
        *_synthetic(seconds=0.3),
        "--n",
        "16",
        "--mesh",
        "tiny",
        "--jobs",
        "1",
        "--out",
        str(out),
        "--no-progress",
    ]
    proc = _popen(args)
    try:
        _wait_rows(out, 2, proc)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, stderr
    assert "done this run" in stdout and "SIGTERM" in stderr, stdout + stderr
    assert "Traceback" not in stderr
    assert not (out / io.LOCK).exists() and not list(out.glob(".attempts-*"))
    landed = len(io.landed_status(out))
    assert 2 <= landed < 16
    r = _sweep(args)
    assert r.returncode == 0 and f"{landed} skipped" in r.stdout, r.stdout + r.stderr
    assert len(io.read_samples(out)) == 16


def test_lock_of_another_host_refused_then_broken(tmp_path, capsys):
    out = tmp_path / "ds"
    args = ["run", *_synthetic(), "--n", "2", "--mesh", "tiny", "--jobs", "1", "--out", str(out), "--no-progress"]
    r = _sweep(args)
    assert r.returncode == 0, r.stderr
    (out / io.LOCK).write_text(json.dumps({"pid": 4242, "host": "node-17.elsewhere", "created": 0.0}))
    before = _snapshot(out)
    code, _, err = _cli(args, capsys)
    assert code == 2 and err.count("\n") == 1 and "node-17.elsewhere" in err and "--break-lock" in err, err
    assert _snapshot(out) == before
    r = _sweep([*args, "--break-lock"])
    assert r.returncode == 0, r.stderr
    assert "node-17.elsewhere" in r.stderr  # says whose lock it broke
    assert not (out / io.LOCK).exists()


# ----------------------------------------------------------------------------- worker warm-up, attempt counts


def test_worker_plugin_warms_each_worker_once_when_it_joins(tmp_path, monkeypatch):
    from distributed import Client, LocalCluster

    from elastimap.sweep.cluster import WarmUpWorkers

    log = tmp_path / "warm.log"
    (tmp_path / "warmprobe.py").write_text(
        "import os\n"
        "def warmup(params):\n"
        f"    open({str(log)!r}, 'a').write(f'{{os.getpid()}} {{params.disc.mesh}}\\n')\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    import warmprobe

    from elastimap.solver.params import Discretisation, SolveParams

    base = SolveParams(disc=Discretisation(mesh="tiny")).to_dict()
    with (
        LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster,
        Client(cluster) as client,
    ):
        client.register_plugin(WarmUpWorkers(warmprobe.warmup, base), name="elastimap-warmup")
        cluster.scale(2)
        client.wait_for_workers(2, timeout=30)
        t0 = time.time()
        while time.time() - t0 < 20 and len(log.read_text().splitlines()) < 2:
            time.sleep(0.2)
        pids = {int(w) for w in client.run(os.getpid).values()}
    lines = [ln.split() for ln in log.read_text().splitlines()]
    assert len(lines) == 2 and {int(p) for p, _ in lines} == pids and {m for _, m in lines} == {"tiny"}


def test_crash_message_counts_the_real_attempts(tmp_path):
    """A scheduler with dask's allowed-failures 2 runs a crashing sample three times: say three."""
    import pickle

    import dask
    from distributed import LocalCluster

    from elastimap.solver.synthetic import SyntheticSolver
    from elastimap.sweep.cluster import WarmUpWorkers
    from elastimap.sweep.jobs import warmup

    table = tmp_path / "t.csv"
    table.write_text("d,h,E\n5,6,50\n7.5,8,70\n")
    out = tmp_path / "ds"
    log = tmp_path / "starts.log"
    with (
        dask.config.set({"distributed.scheduler.allowed-failures": 2}),
        LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster,
    ):
        r = _sweep(
            [
                "run",
                *_synthetic(crash_d=7.5, log=log),
                "--samples",
                str(table),
                "--mesh",
                "tiny",
                "--out",
                str(out),
                "--no-progress",
                "--scheduler",
                cluster.scheduler_address,
            ],
            timeout=240,  # three worker deaths and restarts: slow on a loaded machine
        )
        # the driver registered the warm-up of the solver it was given (the stand-in), not the FEM's
        plugin = pickle.loads(cluster.scheduler.worker_plugins["elastimap-warmup"])
    assert isinstance(plugin, WarmUpWorkers) and plugin.warm.func is warmup
    assert plugin.warm.args == (SyntheticSolver(crash_d=7.5, log=str(log)),)
    assert r.returncode == 0, r.stderr
    starts = [ln.split()[0] for ln in log.read_text().splitlines()].count("7.5")
    assert starts == 3
    df = io.read_samples(out, status=None).set_index("d")
    assert df.loc[7.5, "status"] == "failed"
    assert "3 attempts" in df.loc[7.5, "error"] and "twice" not in df.loc[7.5, "error"], df.loc[7.5, "error"]
