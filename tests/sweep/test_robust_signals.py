"""SIGTERM (``scancel``) and Ctrl-C of ``sweep run`` with the REAL solver (tiny mesh).

The synthetic stand-in never starts gmsh, so the sweep tests that use it cannot see what the
forward model does to the driver: ``gmsh.initialize`` (run by the driver's warm-up solve) puts
SIGINT and SIGTERM back to their default action at C level, while ``signal.getsignal`` still
reports Python's handler.  A signal after the warm-up then killed the driver (exit -15 / -2): no
summary, the lock and the ``.attempts-*`` markers left behind.  Here the signal comes after the
first real solve has landed: the driver must print its summary, remove the lock and the markers
and exit with 143 (SIGTERM) or 130 (SIGINT).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
from sweep_helpers import ROOT, sweep_env

from elastimap.dataset import io

pytestmark = pytest.mark.slow


def _wait_first_row(out, proc, limit=240.0):
    t_end = time.time() + limit
    while time.time() < t_end:
        if out.is_dir() and io.landed_status(out):
            return
        if proc.poll() is not None:
            raise AssertionError(f"sweep ended early: {proc.communicate()[1]}")
        time.sleep(0.2)
    raise AssertionError("no row landed in time")


@pytest.mark.parametrize(("sig", "code", "group"), [(signal.SIGTERM, 143, False), (signal.SIGINT, 130, True)])
def test_signal_after_real_solves_is_handled(tmp_path, sig, code, group):
    out = tmp_path / "ds"
    args = ["run", "--n", "8", "--jobs", "1", "--mesh", "tiny", "--out", str(out), "--no-progress", "--timeout", "0"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "elastimap.sweep.cli", *args],
        env=sweep_env(),
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        _wait_first_row(out, proc)
        assert (out / io.LOCK).exists()
        if group:  # Ctrl-C in a terminal reaches the whole foreground process group
            os.killpg(proc.pid, sig)
        else:  # scancel / a SLURM time limit: SIGTERM to the driver
            proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == code, (proc.returncode, stderr[-2000:])
    assert "done this run" in stdout, stdout + stderr
    assert signal.Signals(sig).name in stderr, stderr
    assert "Traceback" not in stderr, stderr
    assert not (out / io.LOCK).exists()
    assert not list(out.glob(".attempts-*")) and not list(out.glob(".timeout-*"))
    landed = io.landed_status(out)
    assert 1 <= len(landed) < 8 and all(v == "ok" for v in landed.values())
