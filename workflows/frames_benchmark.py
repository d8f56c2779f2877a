"""The SYNTHETIC camera-frame benchmark as a script: ``python workflows/frames_benchmark.py STAGE ...``
runs :mod:`elastimap.workflows.benchmarks.frames` (the code, and its docstring with every stage)."""

import sys

from elastimap.cli_util import run
from elastimap.workflows.benchmarks.frames.cli import main

if __name__ == "__main__":
    sys.exit(run(main, prog_name="workflows/frames_benchmark.py"))
