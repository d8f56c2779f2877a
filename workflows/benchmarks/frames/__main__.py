"""``python -m elastimap.workflows.benchmarks.frames STAGE ...``: the benchmark's command line."""

import sys

from elastimap.cli_util import run

from .cli import main

sys.exit(run(main, prog_name="python -m elastimap.workflows.benchmarks.frames"))
