"""The benchmark's command: one stage per subcommand (see :mod:`elastimap.workflows.benchmarks.frames`)."""

import click

from .lesions import lesions
from .report import report_cmd
from .run import network_cmd, press_cmd, run_cmd


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main():
    """SYNTHETIC camera-frame benchmark of the physics fit: stages lesions, network, run, report
    (and the press check); docs/camera.md, 'Inference'."""


for _cmd in (lesions, network_cmd, run_cmd, report_cmd, press_cmd):
    main.add_command(_cmd)
