"""Helpers shared by the sweep tests: run the real ``sweep`` command in a subprocess, with the
SYNTHETIC stand-in when asked (the hidden ``--solver`` option), in a clean environment."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def sweep_env(**extra) -> dict:
    """The environment for a sweep subprocess: one BLAS thread, no ELASTIMAP_* settings leaking in."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("ELASTIMAP_")}
    env["OMP_NUM_THREADS"] = "1"
    env.update(extra)
    return env


def synthetic(**faults) -> list[str]:
    """The hidden option that runs the SYNTHETIC stand-in (with fault injection) instead of the FEM."""
    spec = ",".join(f"{k}={v}" for k, v in faults.items())
    return ["--solver", f"synthetic:{spec}" if spec else "synthetic"]


def run_sweep(args, env=None, timeout=240) -> subprocess.CompletedProcess:
    """``python -m elastimap.sweep.cli ARGS`` from the repository root."""
    return subprocess.run(
        [sys.executable, "-m", "elastimap.sweep.cli", *args],
        env=env or sweep_env(),
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
    )
